"""The automatic window over the log signal, on fields whose percentiles are known in closed form.

Ground truth: on a field whose values run evenly from 0 to 1, the 1st and 99th percentiles
are 0.01 and 0.99, so the window is 0.98 x latitude wide; its centre is the measuring
field's median, moved only as far as keeps both percentiles inside the window; a uniform
field gets the minimum width.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.xray.display_lut import auto_window

ROWS, COLS = 300, 301          # 90,300 pixels: every third one sampled still steps by 3e-5


def ramp() -> np.ndarray:
    return (np.arange(ROWS * COLS, dtype=np.float32) / (ROWS * COLS - 1)).reshape(ROWS, COLS)


def rows_between(lo: float, hi: float) -> np.ndarray:
    """The pixels whose ramp value lies in [lo, hi] (whole rows, as a measuring field)."""
    p = ramp()
    return (p >= lo) & (p <= hi)


@pytest.mark.parametrize("measuring, centre", [
    ((0.4, 0.6), 0.5),                              # the middle: the median itself
    ((0.0, 0.1), 0.99 - 0.98 * 1.15 / 2),           # a dark middle: moved up until 0.99 fits
    ((0.9, 1.0), 0.01 + 0.98 * 1.15 / 2),           # a bright one: moved down until 0.01 fits
])
def test_window_spans_the_1st_to_99th_percentile_times_the_latitude(measuring, centre):
    field = np.ones((ROWS, COLS), bool)
    c, w = auto_window(ramp(), field, rows_between(*measuring), latitude=1.15, min_width=0.1)
    assert w == pytest.approx(0.98 * 1.15, abs=2e-4)
    assert c == pytest.approx(centre, abs=2e-4)


def test_only_the_field_counts_and_a_uniform_field_gets_the_minimum_width():
    p = ramp()
    field = rows_between(0.5, 1.0)                  # the other half is outside the beam
    c, w = auto_window(p, field, rows_between(0.7, 0.8), latitude=1.0, min_width=0.1)
    assert w == pytest.approx(0.98 * 0.5, abs=2e-4)     # 0.505 .. 0.995
    assert c == pytest.approx(0.75, abs=2e-4)
    flat = np.full((ROWS, COLS), 2.5, np.float32)
    assert auto_window(flat, field, field, latitude=1.15, min_width=0.3) == pytest.approx((2.5, 0.3))
