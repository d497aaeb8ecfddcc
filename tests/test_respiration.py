"""The respiration model against the seed's formulas (PTC simulator, section 2.2), and its live control."""

import math

import numpy as np
import pytest

from appliance.config.case import CaseProfile, Respiration
from appliance.patient.respiration import BreathingControl, state_at

P = Respiration(diaphragm_mm=15, rib_gamma_deg=2, rib_lambda_deg=3, rate_per_min=15)


@pytest.mark.parametrize("t", np.linspace(0.0, 9.7, 23))
def test_angles_and_tendon_follow_the_seed_formulas(t):
    f = 15 / 60
    s = state_at(P, t)
    assert s.gamma_deg == pytest.approx(2 * 0.5 * (1 + math.sin(2 * math.pi * f * t)), abs=1e-12)
    assert s.lambda_deg == pytest.approx(3 * 0.5 * (1 + math.sin(2 * math.pi * f * t)), abs=1e-12)
    # F_d = F_max sin(2 pi f t) with F_max = diaphragm_mm / 2: 15 mm from end-expiration to end-inspiration.
    assert s.tendon_mm == pytest.approx(7.5 * math.sin(2 * math.pi * f * t), abs=1e-12)
    assert s.descent_mm == pytest.approx(7.5 + s.tendon_mm, abs=1e-12)


def test_end_inspiration_and_end_expiration_times():
    f = 15 / 60
    for k in range(3):
        ins, exp = state_at(P, 1 / (4 * f) + k / f), state_at(P, 3 / (4 * f) + k / f)
        assert ins.descent_mm == pytest.approx(15.0) and ins.lambda_deg == pytest.approx(3.0)
        assert exp.descent_mm == pytest.approx(0.0, abs=1e-9) and exp.gamma_deg == pytest.approx(0.0, abs=1e-9)


def test_intercostal_share_splits_the_breath():
    s = state_at(P.model_copy(update=dict(intercostal_share=0.75)), 1.0)     # end-inspiration
    assert s.gamma_deg == pytest.approx(2 * 1.5) and s.descent_mm == pytest.approx(15 * 0.5)
    s = state_at(P.model_copy(update=dict(intercostal_share=0.0)), 1.0)      # diaphragm alone
    assert s.gamma_deg == 0 and s.lambda_deg == 0 and s.descent_mm == pytest.approx(30.0)


def test_rate_zero_is_held():
    s = state_at(P.model_copy(update=dict(rate_per_min=0)), 3.0)
    assert s.held and s.descent_mm == pytest.approx(7.5)


def _trace(control, times):
    return np.array([control.at(t).descent_mm for t in times])


def test_rate_change_mid_breath_is_continuous_and_then_runs_at_the_new_rate():
    c = BreathingControl(P)
    dt = 1e-3
    before = c.at(1.3 - 1e-9).descent_mm
    c.set_rate(1.3, 30.0)
    assert c.at(1.3).descent_mm == pytest.approx(before, abs=1e-6)
    # After the change the phase advances at 30/min from where it was: closed form.
    phase0 = 15 / 60 * 1.3
    for t in (1.5, 2.0, 3.7):
        expect = 7.5 * (1 + math.sin(2 * math.pi * (phase0 + 0.5 * (t - 1.3))))
        assert c.at(t).descent_mm == pytest.approx(expect, abs=1e-9)
    # No step anywhere: the largest change per millisecond stays below the fastest slope.
    times = np.arange(0, 5, dt)
    c2 = BreathingControl(P)
    trace = []
    for t in times:
        if abs(t - 2.2) < dt / 2:
            c2.faster(t)
        if abs(t - 3.1) < dt / 2:
            c2.slower(t)
        trace.append(c2.at(t).descent_mm)
    steepest = 7.5 * 2 * math.pi * c2.params.rate_max_per_min / 60
    assert np.abs(np.diff(trace)).max() <= steepest * dt * 1.01


def test_depth_change_eases_in_without_a_jump():
    c = BreathingControl(P)
    times = np.arange(0, 4, 1e-3)
    trace = []
    for t in times:
        if abs(t - 0.9) < 5e-4:
            c.deeper(t)
            c.deeper(t)          # to 1.5
        trace.append(c.at(t).descent_mm)
    trace = np.array(trace)
    assert np.abs(np.diff(trace)).max() < 0.05           # mm per ms: no jump
    assert c.depth_target == pytest.approx(1.5)
    # Once eased in (depth_ramp_s = 1 s), the excursion is 1.5 times the profile's.
    t = 1 + 4 * 1.0 + 0.0     # end-inspiration of the second breath: 1/(4f) + 1/f
    assert c.at(t).descent_mm == pytest.approx(22.5, abs=1e-9)


def test_hold_freezes_and_resume_continues_from_there():
    c = BreathingControl(P)
    c.hold(1.7)
    frozen = c.at(1.7)
    for t in (2.0, 5.0, 60.0):
        s = c.at(t)
        assert s.held and s.descent_mm == frozen.descent_mm and s.lambda_deg == frozen.lambda_deg
    c.resume(60.0)
    assert c.at(60.0).descent_mm == pytest.approx(frozen.descent_mm)
    # The phase goes on from 1.7 s of breathing: t = 60 + x looks like 1.7 + x.
    assert c.at(60.4).descent_mm == pytest.approx(state_at(P, 2.1).descent_mm, abs=1e-9)
    assert "RESP 15/min" in c.overlay_text(61.0)
    c.hold(62.0)
    assert "HELD" in c.overlay_text(62.5)


def test_console_limits():
    c = BreathingControl(P)
    for k in range(30):
        c.faster(0.1 * k)
    assert c.rate_per_min == P.rate_max_per_min
    for k in range(30):
        c.shallower(3 + 0.1 * k)
    assert c.depth_target == 0.0
    for k in range(30):
        c.slower(7 + 0.1 * k)
    assert c.rate_per_min == 0 and c.at(20).held


def test_profile_section_is_validated():
    from pydantic import ValidationError
    with pytest.raises(ValidationError):
        Respiration(diaphragm_mm=-1)
    with pytest.raises(ValidationError):
        Respiration(spleen=3)
    with pytest.raises(ValidationError):
        Respiration(labels={"heart": [1]})
    case = CaseProfile(title="t", phases=[{"volume": "ct.nii", "time_s": 0}],
                       respiration={"labels": {"lungs": [10]}, "rate_per_min": 50})
    problems = dict(case.problems())
    assert ("respiration", "labels") in problems and ("respiration", "rate_per_min") in problems
