"""The console's five-minute alarm in pulsed fluoroscopy and after a carried timer is reset, and the
breathing keys' counts, under an injected clock.

Ground truth: 21 CFR 1020.32(h): the alarm sounds at 5:00 of cumulative fluoroscopy time
whatever the mode; pulses at t0 + k / 15 for k = 0, 1, ... while the pedal is down (pulsed-15
mode, 4 mGy/min at zoom 1, so 4 / 60 / 15 mGy a pulse); the breathing keys counted as they
are pressed in the test.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)


def key(t: float, name: str, down: bool = True) -> InputEvent:
    return InputEvent(t, "scripted", name, down)


@pytest.mark.timeout(60)       # an alarm taken for a pulse never leaves the loop: fail in a minute, not five
def test_pulsed_fluoroscopy_sounds_the_alarm_at_five_minutes_and_keeps_pulsing():
    """Pedal down at 10 s for 310 s in pulsed-15: the alarm at 310 s (300 s of fluoroscopy), once,
    and one pulse every 1/15 s throughout: k/15 < 310 for k = 0..4649, 4650 pulses."""
    assert II.dose.alarm_period_s == 300.0
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(key(0.0, "mode_next"))
    assert console.snapshot().mode == "pulsed-15"
    events = console.handle(key(10.0, "pedal"))
    t = 10.0
    while t < 320.0:
        t = min(t + 0.5, 320.0)
        events += console.tick(t)
    events += console.handle(key(320.0, "pedal", False))
    alarms = [e for e in events if e.kind == "alarm"]
    assert [e.t_monotonic for e in alarms] == [pytest.approx(310.0, abs=1e-6)]
    assert alarms[0].fluoro_time_s == 300.0
    pulses = [e for e in events if e.kind == "pulse"]
    assert len(pulses) == 4650
    assert pulses[-1].t_monotonic == pytest.approx(10.0 + 4649 / 15)
    state = console.snapshot()
    assert state.alarm_sounding and state.alarm_count == 1
    assert state.fluoro_time_s == pytest.approx(310.0)
    assert state.air_kerma_mgy == pytest.approx(4650 * 4.0 / 60 / 15)


def test_breathing_keys_count_from_none_pressed_and_stamp_their_times():
    console = Console(II, KEYMAP, t0=0.0)
    fresh = console.snapshot()
    # Nothing pressed yet: no steps, and no press after the console's start (times the phase
    # worker subtracts from, so they must be numbers).
    assert (fresh.breath_rate_steps, fresh.breath_depth_steps) == (0, 0)
    assert fresh.breath_changed_t - 0.0 <= 0.0 and fresh.breath_step_t - 0.0 <= 0.0
    assert not fresh.breath_hold and fresh.image == "none"
    events = []
    for t, name in [(1.0, "KEY_F11"), (2.0, "KEY_F11"), (3.0, "KEY_F12"),                  # faster, faster, slower
                    (4.0, "KEY_KPEQUAL"), (5.0, "KEY_KPEQUAL"), (6.0, "KEY_KPEQUAL"), (7.5, "KEY_KPCOMMA")]:
        events += console.handle(key(t, name))
    # Each press is recorded with its step, so the ledger can replay the lesson's breathing.
    assert [(e.t_monotonic, e.kind, e.detail) for e in events] == [
        (1.0, "breath_rate", {"step": 1}), (2.0, "breath_rate", {"step": 1}), (3.0, "breath_rate", {"step": -1}),
        (4.0, "breath_depth", {"step": 1}), (5.0, "breath_depth", {"step": 1}), (6.0, "breath_depth", {"step": 1}),
        (7.5, "breath_depth", {"step": -1})]
    state = console.snapshot()
    assert (state.breath_rate_steps, state.breath_depth_steps) == (1, 2)
    assert state.breath_step_t == 7.5 and state.breath_changed_t == 0.0
    assert [e.kind for e in console.handle(key(9.0, "KEY_KPSLASH"))] == ["hold_breath"]
    assert console.snapshot().breath_hold and console.snapshot().breath_changed_t == 9.0
    assert console.handle(key(10.0, "KEY_KPSLASH")) == []                                # already held
    assert [e.kind for e in console.handle(key(11.0, "KEY_KPDOT"))] == ["resume_breath"]
    state = console.snapshot()
    assert not state.breath_hold and state.breath_changed_t == 11.0 and state.breath_step_t == 7.5
    console.handle(key(12.0, "KEY_F12"))                                                  # slower, last
    assert console.snapshot().breath_step_t == 12.0 and console.snapshot().breath_rate_steps == 0


def test_a_run_of_no_length_records_the_technique_it_was_set_at():
    """Pedal pressed and released at one instant (a bounce): the run lasted no time, so its kV
    and mA are the technique of that moment, the profile's reference technique."""
    console = Console(II, KEYMAP, t0=0.0)
    events = console.handle(key(2.0, "pedal")) + console.handle(key(2.0, "pedal", False))
    (off,) = [e for e in events if e.kind == "fluoro_off"]
    assert off.detail["duration_s"] == 0.0
    assert (off.detail["kvp"], off.detail["ma"]) == (II.tube.kvp, II.tube.ma)
    assert off.detail["air_kerma_mgy"] == 0.0


def expose(console: Console, start: float, length: float) -> list:
    events = console.handle(key(start, "pedal"))
    t = start
    while t < start + length:
        t = min(t + 0.5, start + length)
        events += console.tick(t)
    return events + console.handle(key(start + length, "pedal", False))


def test_a_person_resets_a_timer_carried_over_a_crash_and_the_alarm_counts_afresh():
    """200 s carried: the alarm would come after 100 s more. Reset (no alarm sounding) after
    50 s of this session: the press is recorded with what it reset, and the alarm then comes
    at 300 s of this session's own time, 250 s into a run that starts at 100 s: at 350 s."""
    console = Console(II, KEYMAP, t0=0.0)
    console.carry_over(200.0, 0)
    expose(console, 0.0, 50.0)
    (reset,) = console.handle(key(60.0, "KEY_KPASTERISK"))
    assert reset.kind == "alarm_reset"
    assert reset.detail == {"timer": "reset", "carried_fluoro_time_s": 200.0, "carried_alarms": 0}
    alarms = [e for e in expose(console, 100.0, 260.0) if e.kind == "alarm"]
    assert [e.t_monotonic for e in alarms] == [pytest.approx(350.0, abs=1e-6)]


def test_resetting_carried_alarms_takes_them_off_the_count_once():
    console = Console(II, KEYMAP, t0=0.0)
    console.carry_over(650.0, 2)
    assert console.snapshot().alarm_count == 2
    (reset,) = console.handle(key(1.0, "KEY_KPASTERISK"))
    assert reset.detail == {"timer": "reset", "carried_fluoro_time_s": 650.0, "carried_alarms": 2}
    assert console.snapshot().alarm_count == 0
    assert console.handle(key(2.0, "KEY_KPASTERISK")) == []       # nothing carried any more
    alarms = [e for e in expose(console, 10.0, 301.0) if e.kind == "alarm"]
    assert [e.t_monotonic for e in alarms] == [pytest.approx(310.0, abs=1e-6)]
    assert console.snapshot().alarm_count == 1
