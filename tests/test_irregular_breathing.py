"""Irregular breathing (`respiration.irregularity`): each breath's length and depth vary within
the set fraction, the motion stays continuous, a seed repeats it, and 0 is the regular law.

Ground truth: the definition (breath n lasts (1 + a u_n) / f and reaches depth 1 + a v_n,
|u_n|, |v_n| <= 1), read back from the sampled breath only: end-expirations found as the
minima of `inspired`, peaks as its maxima."""

import math

import numpy as np
import pytest
from pydantic import ValidationError

from appliance.config.case import Respiration
from appliance.patient.respiration import BreathingControl, state_at

RATE = 20.0
F = RATE / 60.0
DT = 0.01


def _sampled(params, breaths=60):
    t = np.arange(0.0, breaths / F, DT)
    e = np.array([state_at(params, float(x)).excursion for x in t])
    return t, e


def _extremes(t, e):
    inner = e[1:-1]
    lows = np.flatnonzero((inner <= e[:-2]) & (inner < e[2:])) + 1
    highs = np.flatnonzero((inner >= e[:-2]) & (inner > e[2:])) + 1
    return t[lows], e[highs]


def test_breaths_vary_within_the_fraction_and_keep_the_rate_on_average():
    a = 0.2
    params = Respiration(rate_per_min=RATE, irregularity=a, irregularity_seed=3)
    t, e = _sampled(params)
    ends, peaks = _extremes(t, e)
    lengths = np.diff(ends) * F                      # in breaths of the set rate
    assert len(lengths) >= 55
    assert lengths.min() >= 1 - a - 0.01 and lengths.max() <= 1 + a + 0.01
    assert lengths.std() > 0.25 * a / math.sqrt(3)   # uniform in +-a: sd a / sqrt(3); not regular
    assert lengths.mean() == pytest.approx(1.0, abs=0.05)
    assert peaks.min() >= 1 - a - 1e-6 and peaks.max() <= 1 + a + 1e-6
    assert peaks.std() > 0.25 * a / math.sqrt(3)
    # No jump: the fastest change is the regular breath's at the deepest and shortest breath.
    slope = np.abs(np.diff(e)) / DT
    regular_max = math.pi * F                         # d/dt of 1/2 (1 + sin 2 pi f t)
    assert slope.max() <= regular_max * (1 + a) / (1 - a) + 1e-6


def test_zero_is_the_regular_law_and_a_seed_repeats_the_breathing():
    regular = Respiration(rate_per_min=RATE)
    for x in (0.0, 0.75, 1.9, 7.3):
        s = state_at(regular, x)
        assert s.inspired == pytest.approx(0.5 * (1 + math.sin(2 * math.pi * F * x)))
    a = Respiration(rate_per_min=RATE, irregularity=0.3, irregularity_seed=7)
    b = Respiration(rate_per_min=RATE, irregularity=0.3, irregularity_seed=7)
    c = Respiration(rate_per_min=RATE, irregularity=0.3, irregularity_seed=8)
    ts = np.linspace(5.0, 90.0, 40)
    ea = [state_at(a, float(x)).excursion for x in ts]
    assert ea == [state_at(b, float(x)).excursion for x in ts]
    assert not np.allclose(ea, [state_at(c, float(x)).excursion for x in ts])


def test_the_console_holds_and_rate_changes_act_on_the_irregular_breath():
    params = Respiration(rate_per_min=RATE, irregularity=0.2, irregularity_seed=1)
    control = BreathingControl(params)
    before = control.at(10.0).excursion
    control.hold(10.0)
    assert control.at(14.0).excursion == pytest.approx(before)
    control.resume(14.0)
    control.faster(14.0)
    assert control.at(14.0).excursion == pytest.approx(before)   # no jump on resume or rate change


def test_irregularity_beyond_half_a_breath_is_refused():
    with pytest.raises(ValidationError, match="irregularity"):
        Respiration(irregularity=0.6)
