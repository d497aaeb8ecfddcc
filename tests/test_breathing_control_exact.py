"""The console's breathing controls, worked by hand: the depth eases in as a smoothstep, stops
where it is during a hold and eases a change asked for during the hold in from the resume,
the depth stays within 0..depth_max, and a resume from rate 0 breathes at the case's rate.

Ground truth: smoothstep s(x) = 3x^2 - 2x^3 (s(1/4) = 5/32, s(1/2) = 1/2, s(3/4) = 27/32) over
depth_ramp_s = 4 s, and the breath count f t at a constant rate.
"""

from __future__ import annotations

import pytest

from appliance.config.case import Respiration
from appliance.patient.respiration import BreathingControl

PARAMS = Respiration(rate_per_min=12.0, rate_step_per_min=3.0, depth_step=0.25, depth_max=2.0, depth_ramp_s=4.0,
                     diaphragm_mm=20.0, rib_gamma_deg=2.0, rib_lambda_deg=3.0)


def test_a_depth_change_eases_in_as_a_smoothstep():
    control = BreathingControl(PARAMS)
    assert control.set_depth(10.0, 2.0) == 2.0
    depths = [control.at(t).depth for t in (9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 30.0)]
    assert depths == pytest.approx([1.0, 1.0, 1.0 + 5 / 32, 1.5, 1.0 + 27 / 32, 2.0, 2.0], abs=1e-12)


def test_depth_is_clamped_to_the_profiles_range():
    control = BreathingControl(PARAMS)
    assert control.set_depth(1.0, 9.0) == 2.0
    assert control.deeper(2.0) == 2.0
    assert control.at(20.0).depth == pytest.approx(2.0)
    assert control.set_depth(30.0, -1.0) == 0.0
    assert control.shallower(31.0) == 0.0
    assert control.at(50.0).depth == pytest.approx(0.0, abs=1e-12)
    assert control.at(50.0).descent_mm == pytest.approx(0.0, abs=1e-12)


def test_a_hold_stops_phase_and_depth_mid_ramp():
    """Held at 12 s, halfway through a 4 s ramp from depth 1 to 2: the anatomy stays at depth
    1.5 and breath count 12/60 x 12 = 2.4 for as long as the hold lasts."""
    control = BreathingControl(PARAMS)
    control.set_depth(10.0, 2.0)
    control.hold(12.0)
    for t in (12.0, 13.0, 20.0, 100.0):
        s = control.at(t)
        assert s.held and s.depth == pytest.approx(1.5) and s.cycles == pytest.approx(2.4)


def test_a_depth_asked_for_during_a_hold_eases_in_from_the_resume():
    control = BreathingControl(PARAMS)
    control.hold(10.0)
    control.set_depth(11.0, 2.0)
    assert control.at(15.0).depth == pytest.approx(1.0)          # still held: nothing moves
    control.resume(20.0)
    s = [control.at(t) for t in (20.0, 22.0, 24.0)]
    assert [x.depth for x in s] == pytest.approx([1.0, 1.5, 2.0])
    # The breath goes on from 12/60 x 10 = 2 breaths, at 12 a minute from the resume.
    assert [x.cycles for x in s] == pytest.approx([2.0, 2.4, 2.8])


@pytest.mark.parametrize("rate, expected", [(12.0, 12.0), (0.0, 3.0)])
def test_resume_from_rate_zero_breathes_at_the_cases_rate(rate, expected):
    """Slowed to 0, a resume brings back the case's own rate (or one step where the case is held at 0)."""
    control = BreathingControl(PARAMS.model_copy(update={"rate_per_min": rate}))
    control.set_rate(5.0, 0.0)
    assert control.at(60.0).held
    control.resume(60.0)
    assert control.rate_per_min == expected
    assert control.at(70.0).cycles - control.at(60.0).cycles == pytest.approx(expected / 6.0)
