"""The breathing patient as the daemon draws it: depth states blended in projection space, live keys."""

from pathlib import Path

import numpy as np
import pytest
import synthetic_chest as sc
from test_breathing_motion import SOD, T_XRAY_FROM_CT, dome_edge_row

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.config.case import Materials, Respiration
from appliance.console.state import Console
from appliance.patient.breathing_timeline import BreathingTimeline
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer, View
from drivers.input_event import InputEvent

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def timeline():
    renderer = Renderer(flat_profile(128), Materials(), device="cpu")
    ct = sc.chest()
    tl = BreathingTimeline(lambda: ct, Respiration(), Materials(), renderer)
    assert tl.wait_ready(120, all_phases=True)
    yield tl
    tl.close()


def test_states_span_end_expiration_to_the_deepest_breath(timeline):
    p = timeline.params
    assert timeline.ready_count == p.depth_states
    assert timeline.excursions[0] == 0 and timeline.excursions[-1] == pytest.approx(p.depth_max)
    a, b, w = timeline.at(3.0)                       # end-expiration at 15/min
    assert a is timeline._prepared[0] and b is None and w == 0
    a, b, w = timeline.at(1.0)                       # end-inspiration: excursion 1
    step = timeline.excursions[1]
    k = int(1.0 / step)
    assert a is timeline._prepared[k] and b is timeline._prepared[k + 1] and w == pytest.approx(1.0 / step - k)


def test_blended_states_put_the_dome_where_the_breath_is(timeline):
    """Displayed image of the blend at end-inspiration: the dome edge is fy * 15 / SOD pixels below
    end-expiration's (within 10 %), though no state was drawn at exactly 15 mm."""
    r = timeline.renderer
    f = r.fluoroscope
    column = int(round(f.intrinsics.cx + f.intrinsics.fx * -50.0 / SOD))
    view = View(quantity="intensity", noise=False)
    images = []
    for t in (3.0, 1.0):
        a, b, w = timeline.at(t)
        images.append(-np.log(np.maximum(r.render(a, T_XRAY_FROM_CT, view, blend=None if b is None else (b, w)).image, 1e-6)))
    r_apex = int(round(f.intrinsics.cy - f.intrinsics.fy * sc.DOME_APEX_Z / SOD))
    level = 0.5 * (images[0][r_apex - 4, column] + images[0][r_apex + 4, column])
    rows = [dome_edge_row(img, column, level, r_apex - 6) for img in images]
    assert rows[1] - rows[0] == pytest.approx(f.intrinsics.fy * 15.0 / SOD, rel=0.1)


def test_keys_count_presses_for_the_breathing_model():
    fl = load_profile(ROOT / "configs" / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    keymap = load_profile(ROOT / "configs" / "keymaps" / "usb-numeric-keypad.yaml", KeymapProfile)
    console = Console(fl, keymap, 0.0)
    kinds = []
    for t, key in ((1.0, "KEY_F11"), (1.5, "KEY_F11"), (2.0, "KEY_F12"), (3.0, "KEY_KPEQUAL"), (4.0, "KEY_KPCOMMA"),
                   (4.5, "KEY_KPCOMMA")):
        kinds += [e.kind for e in console.handle(InputEvent(t, "scripted", key, True))]
    s = console.snapshot()
    assert (s.breath_rate_steps, s.breath_depth_steps) == (1, -1)
    assert kinds.count("breath_rate") == 3 and kinds.count("breath_depth") == 3


def test_phase_worker_hands_the_presses_to_the_breathing_model(timeline):
    """The daemon's phase worker, on the real timeline and a real console's state: two faster
    presses raise the rate by two steps at the case time they are seen, shown on the overlay line."""
    from types import SimpleNamespace

    from appliance.daemon.handoff import LatestValue
    from appliance.daemon.phase_worker import PhaseWorker

    fl = load_profile(ROOT / "configs" / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    keymap = load_profile(ROOT / "configs" / "keymaps" / "usb-numeric-keypad.yaml", KeymapProfile)
    console = Console(fl, keymap, 0.0)
    for t, key in ((0.1, "KEY_F11"), (0.2, "KEY_F11"), (0.3, "KEY_KPEQUAL")):
        console.handle(InputEvent(t, "scripted", key, True))
    states, phases = LatestValue("console"), LatestValue("phases")
    states.put(console.snapshot())
    worker = PhaseWorker(SimpleNamespace(timeline=timeline, generation=0), states, phases)
    before = timeline.control.at(0.0)
    assert worker.step()
    p = timeline.params
    assert timeline.control.rate_per_min == p.rate_per_min + 2 * p.rate_step_per_min
    assert timeline.control.depth_target == pytest.approx(1 + p.depth_step)
    value, _ = phases.get()
    assert value.breathing == f"RESP {p.rate_per_min + 2 * p.rate_step_per_min:.0f}/min  depth {1 + p.depth_step:.2f}"
    # Seen once: a second look at the same state changes nothing.
    assert worker.step() and timeline.control.rate_per_min == p.rate_per_min + 2 * p.rate_step_per_min
    assert before.rate_per_min == p.rate_per_min
    timeline.control = type(timeline.control)(p)        # leave the shared timeline as the other tests found it


def _worker_at(timeline, now: list[float]):
    """(console, its state's hand-off, the phases' hand-off, a PhaseWorker) on `timeline`, the
    session begun at appliance time 100 s and the clock reading `now[0]`."""
    from types import SimpleNamespace

    from appliance.daemon.handoff import LatestValue
    from appliance.daemon.phase_worker import PhaseWorker

    fl = load_profile(ROOT / "configs" / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    keymap = load_profile(ROOT / "configs" / "keymaps" / "usb-numeric-keypad.yaml", KeymapProfile)
    console = Console(fl, keymap, 100.0)
    states, phases = LatestValue("console"), LatestValue("phases")
    states.put(console.snapshot())
    worker = PhaseWorker(SimpleNamespace(timeline=timeline, generation=0, t0=100.0), states, phases,
                         clock=lambda: now[0])
    return console, states, phases, worker


def test_phase_worker_runs_the_case_on_the_console_clock_and_holds_only_the_breath(timeline):
    """One clock: the case time is the appliance clock since the session's start (parts.t0). A
    breath hold on the breathing model freezes the breath at the press's console time while the
    case time (the contrast's timeline) runs on; resume carries the breath on from there."""
    from appliance.patient.respiration import state_at

    now = [110.0]
    console, states, phases, worker = _worker_at(timeline, now)
    p = timeline.params
    try:
        assert worker.step()
        assert phases.get()[0].t_case_s == pytest.approx(10.0)
        console.handle(InputEvent(110.5, "scripted", "KEY_KPSLASH", True))
        console.tick(110.5)
        states.put(console.snapshot())
        now[0] = 113.0
        assert worker.step()
        held = phases.get()[0]
        assert held.t_case_s == pytest.approx(13.0)                      # the case runs on
        assert held.inspired == pytest.approx(state_at(p, 10.5).inspired)  # the breath stopped at the press
        console.handle(InputEvent(115.0, "scripted", "KEY_KPDOT", True))
        console.tick(115.0)
        states.put(console.snapshot())
        now[0] = 116.0
        assert worker.step()
        # Resumed at 15.0 from where it stood: one second of breath on from 10.5.
        assert phases.get()[0].inspired == pytest.approx(state_at(p, 11.5).inspired)
    finally:
        timeline.control = type(timeline.control)(p)        # leave the shared timeline as the other tests found it


def test_phase_worker_hands_on_the_states_the_breath_reaches_next(timeline):
    """During inspiration (case time 0.2 s at 15/min, the breath rising) the phase worker hands on,
    beside the frame's two states, the states the closed-form breath reaches within its look ahead
    and no others; in a breath hold, none (the breath stands still)."""
    from appliance.daemon.phase_worker import LOOKAHEAD_S
    from appliance.patient.respiration import state_at

    now = [100.2]
    console, states, phases, worker = _worker_at(timeline, now)
    p, step = timeline.params, timeline.excursions[1]

    def indices(t):
        e = state_at(p, t).excursion / step
        return {int(e), int(e) + 1} if e > int(e) else {int(e)}
    try:
        assert worker.step()
        value = phases.get()[0]
        here = indices(0.2)
        expected = set().union(*(indices(0.2 + dt) for dt in LOOKAHEAD_S)) - here
        assert expected                                  # the breath moves on within the look ahead
        assert {timeline._prepared.index(v) for v in value.upcoming} == expected
        assert {timeline._prepared.index(v) for v in (value.prepared_a, value.prepared_b)} == here
        console.handle(InputEvent(100.25, "scripted", "KEY_KPSLASH", True))
        console.tick(100.25)
        states.put(console.snapshot())
        now[0] = 100.3
        assert worker.step()
        assert phases.get()[0].upcoming == ()
    finally:
        timeline.control = type(timeline.control)(p)        # leave the shared timeline as the other tests found it
