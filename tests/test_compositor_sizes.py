"""The compositor's edges: the smallest screen it takes, a portrait screen's image square, and
the dose figures at each change of their number of decimals.

Ground truth: typed here (64 px a side the least; a 512 x 640 screen's square centred 64 px
down; three significant digits up to 1000: 0.999, 1.00, 9.99, 10.0, 99.9, 100, 1000).
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.display.compositor import Compositor, Overlay
from appliance.display.text import dose_number


@pytest.mark.parametrize("value, shown", [(0.9994, "0.999"), (1.0, "1.00"), (9.994, "9.99"), (10.0, "10.0"),
                                          (10.5, "10.5"), (99.94, "99.9"), (100.0, "100"), (100.5, "100"),
                                          (999.4, "999"), (1000.0, "1000"), (12345.6, "12346")])
def test_dose_figures_change_decimals_at_1_10_and_100(value, shown):
    assert dose_number(value) == shown


def test_the_smallest_screen_is_64_px_a_side():
    Compositor(64, 64)
    for size in ((63, 200), (200, 63)):
        with pytest.raises(ValueError, match=r"screen must be at least 64x64 pixels, got \d+x\d+"):
            Compositor(*size)


def test_a_portrait_screen_centres_the_image_square_vertically():
    comp = Compositor(512, 640, circular_fov=False)
    frame = comp.compose(np.ones((64, 64), np.float32), Overlay(), now=0.0)
    bright = np.nonzero((frame[:, 256] > 200).all(axis=1))[0]     # the middle column: the white field
    assert bright.min() == 64 and bright.max() == 64 + 512 - 1
