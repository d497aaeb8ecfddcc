"""A rate or depth change mid-breath keeps the image continuous: the frames either side of the
key press differ by quantum noise alone, as two frames of a held breath do.

Ground truth: photon statistics. Two independent frames of the same anatomy differ with a
standard deviation of sqrt(2 I / N) relative (Poisson, N photons per pixel at full signal); a
jump in the anatomy at the press would add to that. Half a second later the breath has moved
the dome, and the difference is beyond what noise allows.
"""

import numpy as np
import pytest
import synthetic_chest as sc

from appliance.config.case import Materials, Respiration
from appliance.geometry import make_transform
from appliance.patient.breathing_motion import BreathingAnatomy
from appliance.patient.respiration import BreathingControl
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer, View

#: AP view of the synthetic chest at 750 mm from the focal spot.
T_XRAY_FROM_CT = make_transform(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), [0.0, 0.0, 750.0])
#: The press, in mid-inspiration (t = 1/(8f) at 15/min), where the dome moves fastest.
PRESS_S = 0.5


@pytest.fixture(scope="module")
def setup():
    anatomy = BreathingAnatomy(sc.chest(), Respiration(), Materials())
    return anatomy, Renderer(flat_profile(128), Materials(), device="cpu")


def _frame(setup, state, seed):
    anatomy, renderer = setup
    view = View(quantity="intensity", noise=True, seed=seed)
    return renderer.render(renderer.prepare(anatomy.volume_at(state)), T_XRAY_FROM_CT, view).image


def _noise_ratio(setup, a, b) -> float:
    """rms of (a - b) over the Poisson expectation of two independent frames (1 = noise alone)."""
    photons = setup[1].photons_per_pixel(1)
    sel = a > 0.05
    return float(np.sqrt(np.mean(((a - b)[sel] / np.sqrt(2 * a[sel] / photons)) ** 2)))


@pytest.mark.parametrize("press", ["faster", "slower", "deeper", "shallower"])
def test_a_key_press_mid_breath_leaves_no_jump_in_the_image(setup, press):
    c = BreathingControl(Respiration())
    before = c.at(PRESS_S - 1e-3)
    getattr(c, press)(PRESS_S)
    after = c.at(PRESS_S + 1e-3)
    # The anatomy itself: the tendon moved no more than its fastest slope allows in 2 ms.
    steepest_mm_per_s = 7.5 * 2 * np.pi * c.params.rate_max_per_min / 60 * c.params.depth_max
    assert abs(after.descent_mm - before.descent_mm) <= steepest_mm_per_s * 2e-3
    a, b = _frame(setup, before, 1), _frame(setup, after, 2)
    assert _noise_ratio(setup, a, b) == pytest.approx(1.0, rel=0.15)
    later = _frame(setup, c.at(PRESS_S + 0.5), 3)
    assert _noise_ratio(setup, a, later) > 1.3        # beyond the 15 % noise alone allows
