"""The 4D phase timeline: background preparation, never stalling, interpolation weights."""

import threading
import time

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.errors import FluorosimError
from appliance.patient.timeline import PhaseTimeline
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer
from appliance.xray.truth.analytic import box_volume


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(32), Materials(), device="cpu")


def phase(hu, delay_s=0.0, gate: threading.Event | None = None):
    def load():
        if gate is not None:
            gate.wait(10)
        time.sleep(delay_s)
        return box_volume((8, 8, 8), (2.0, 2.0, 2.0), (2, 2, 2), (5, 5, 5), hu=hu)[0]
    return load


def test_interpolation_weights_and_loop(renderer):
    tl = PhaseTimeline([(0.0, phase(0)), (1.0, phase(100)), (2.0, phase(200)), (3.0, phase(300))], renderer, "loop")
    try:
        assert tl.wait_ready(10, all_phases=True)
        a, b, w = tl.at(1.25)
        assert (a.time_s, b.time_s, w) == (1.0, 2.0, pytest.approx(0.25))
        a, b, w = tl.at(3.5)             # between the last phase and the loop back to the first
        assert (a.time_s, b.time_s, w) == (3.0, 0.0, pytest.approx(0.5))
        a, b, w = tl.at(4.0 + 2.0)       # one 4 s cycle later
        assert (a.time_s, b, w) == (2.0, None, 0.0)
    finally:
        tl.close()


def test_a_look_ahead_gives_the_later_phases_and_leaves_the_loaders_order(renderer):
    """`at(t, steer=False)` (the phase worker's look ahead) gives the phases of that time as `at`
    does, and leaves the phase the loader prepares first as the frame's `at` set it."""
    tl = PhaseTimeline([(0.0, phase(0)), (1.0, phase(100)), (2.0, phase(200)), (3.0, phase(300))], renderer, "loop")
    try:
        assert tl.wait_ready(10, all_phases=True)
        tl.at(1.6)                       # the frame's: nearer phase 2
        assert tl._wanted == 2
        a, b, w = tl.at(3.25, steer=False)
        assert (a.time_s, b.time_s, w) == (3.0, 0.0, pytest.approx(0.25))
        assert tl._wanted == 2
        tl.at(3.25)
        assert tl._wanted == 3
    finally:
        tl.close()


def test_hold_stays_on_the_last_phase(renderer):
    tl = PhaseTimeline([(0.0, phase(0)), (1.0, phase(100))], renderer, "hold")
    try:
        assert tl.wait_ready(10, all_phases=True)
        a, b, w = tl.at(7.0)
        assert (a.time_s, b, w) == (1.0, None, 0.0)
    finally:
        tl.close()


def test_at_never_waits_for_a_slow_phase(renderer):
    gate = threading.Event()
    tl = PhaseTimeline([(0.0, phase(0)), (1.0, phase(100, gate=gate)), (2.0, phase(200, gate=gate))], renderer)
    try:
        assert tl.wait_ready(10)
        worst = 0.0
        for t in np.linspace(0, 2.9, 30):
            t0 = time.perf_counter()
            a, b, w = tl.at(t)
            worst = max(worst, time.perf_counter() - t0)
            assert a.time_s == 0.0 and b is None       # the only ready phase, no blend with a missing one
        assert worst < 0.05
        gate.set()
        assert tl.wait_ready(10, all_phases=True)
        assert tl.at(1.5)[0].time_s == 1.0
    finally:
        gate.set()
        tl.close()


def test_a_broken_first_phase_is_reported(renderer):
    def broken():
        raise FluorosimError("ct/phase0.nii: cannot read this volume")
    tl = PhaseTimeline([(0.0, broken), (1.0, phase(0))], renderer)
    try:
        with pytest.raises(FluorosimError, match="phase0.nii"):
            tl.wait_ready(10)
    finally:
        tl.close()


def test_bad_time_stamps():
    with pytest.raises(FluorosimError, match="increase"):
        PhaseTimeline([(1.0, phase(0)), (0.5, phase(0))], renderer=None)


def test_a_4d_ct_under_the_breathing_controls(renderer):
    """Rate stretches the CT's cycle (end-expiration at the model's 3/4 of a breath), depth
    blends the phase with end-expiration; a rate change keeps the CT time where it was."""
    from appliance.config.case import Respiration
    from appliance.patient.breathing_4d import FourDBreathing

    tl = PhaseTimeline([(0.0, phase(0)), (1.0, phase(100)), (2.0, phase(200)), (3.0, phase(300))], renderer, "loop")
    params = Respiration(rate_per_min=15, ct_end_expiration_s=2.0)     # 4 s breath, as the CT's 4 s cycle
    breathing = FourDBreathing(tl, params, 2.0)
    try:
        assert breathing.wait_ready(10, all_phases=True)
        # At 15/min end-expiration is t = 3 s: the CT's phase at 2.0 s.
        a, b, w = breathing.at(3.0)
        assert (a.time_s, b, w) == (2.0, None, 0.0)
        # Half a breath later (end-inspiration): half the CT's cycle on, 0.0 s.
        a, b, w = breathing.at(5.0)
        assert (a.time_s, b, w) == (0.0, None, 0.0)
        # Twice the rate: from t = 5 s, a quarter breath takes 0.5 s instead of 1 s.
        breathing.control.set_rate(5.0, 30.0)
        a, b, w = breathing.at(5.5)
        assert (a.time_s, b, w) == (1.0, None, 0.0)
        # Half depth: the phase blended half way with end-expiration.
        breathing.control.set_depth(5.5, 0.5)
        # 2 s on at 30/min is one breath: the CT's phase at 1.0 s again, now half way to end-expiration.
        a, b, w = breathing.at(7.5)
        assert (a.time_s, b.time_s, w) == (2.0, 1.0, pytest.approx(0.5))
    finally:
        breathing.close()
