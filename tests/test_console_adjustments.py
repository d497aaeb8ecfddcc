"""The console's adjustments that are not keys of a real unit's exposure: window and level
steps, the technique the exposure control sets, notes in the ledger's order, and the timer a
crash carries over. Each figure is worked by hand from the profile's numbers as typed in
configs/fluoroscopes/generic-ii-carm.yaml (window_step 1.25, level_step 0.05, 8 mGy/min
continuous at zoom 1, reference technique 75 kV 2.0 mA, a 300 s alarm)."""

from __future__ import annotations

from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
NARROWER, WIDER, LEVEL_DOWN, LEVEL_UP, RESET, PEDAL = "KEY_F5", "KEY_F6", "KEY_F7", "KEY_F8", "KEY_KP8", "KEY_KPENTER"


def test_the_profile_numbers_this_file_works_from():
    assert (II.image.window_step, II.image.level_step) == (1.25, 0.05)
    assert (II.tube.kvp, II.tube.ma, II.dose.alarm_period_s) == (75, 2.0, 300)
    assert II.zoom_levels[0].air_kerma_rate_mgy_per_min["continuous"] == 8.0


def taps(console: Console, key: str, n: int, t: float = 1.0) -> tuple[float, float]:
    for k in range(n):
        console.handle(InputEvent(t + k * 0.01, "keypad", key, True))
        console.handle(InputEvent(t + k * 0.01 + 0.005, "keypad", key, False))
    s = console.snapshot()
    return s.window_scale, s.level_shift


def test_window_keys_step_by_a_quarter_between_a_quarter_and_four_times():
    console = Console(II, KEYMAP, t0=0.0)
    assert taps(console, WIDER, 1) == (pytest.approx(1.25), 0.0)
    assert taps(console, WIDER, 5) == (pytest.approx(1.25 ** 6), 0.0)       # 3.81
    assert taps(console, WIDER, 1) == (4.0, 0.0)                            # 4.77 stops at 4
    assert taps(console, WIDER, 3) == (4.0, 0.0)
    assert taps(console, NARROWER, 1) == (pytest.approx(4.0 / 1.25), 0.0)   # from the stop, not from 4.77
    assert taps(console, RESET, 1) == (1.0, 0.0)
    assert taps(console, NARROWER, 6) == (pytest.approx(0.8 ** 6), 0.0)     # 0.262
    assert taps(console, NARROWER, 1) == (0.25, 0.0)                        # 0.21 stops at a quarter
    assert taps(console, WIDER, 1) == (pytest.approx(0.25 * 1.25), 0.0)


def test_level_keys_step_by_a_twentieth_within_half_a_window_either_way():
    console = Console(II, KEYMAP, t0=0.0)
    assert taps(console, LEVEL_UP, 3) == (1.0, pytest.approx(0.15))
    assert taps(console, LEVEL_UP, 8) == (1.0, 0.5)                         # 0.55 stops at 0.5
    assert taps(console, LEVEL_DOWN, 1) == (1.0, pytest.approx(0.45))
    assert taps(console, LEVEL_DOWN, 20) == (1.0, -0.5)                     # -0.55 stops at -0.5
    assert taps(console, LEVEL_UP, 2) == (1.0, pytest.approx(-0.4))
    # Window and level are independent, and one reset clears both.
    assert taps(console, WIDER, 2) == (pytest.approx(1.5625), pytest.approx(-0.4))
    assert taps(console, RESET, 1) == (1.0, 0.0)
    # Neither is an exposure setting: no time, dose or run comes of them.
    s = console.snapshot()
    assert (s.fluoro_time_s, s.air_kerma_mgy, s.runs) == (0.0, 0.0, 0)


def test_the_technique_the_exposure_control_sets_is_the_runs_and_its_dose_rate_applies_from_then():
    console = Console(II, KEYMAP, t0=0.0)
    assert (console.snapshot().kvp, console.snapshot().ma) == (75, 2.0)
    console.handle(InputEvent(10.0, "pedal", PEDAL, True))
    console.set_exposure_factor(2.0, 40.0, kvp=90, ma=3.0)
    s = console.snapshot()
    assert (s.kvp, s.ma) == (90.0, 3.0) and s.air_kerma_rate_mgy_per_min == pytest.approx(16.0)
    off = [e for e in console.handle(InputEvent(70.0, "pedal", PEDAL, False)) if e.kind == "fluoro_off"]
    # 30 s at 8 mGy/min, then 30 s at twice that: 4 + 8 mGy; the run records the time-weighted
    # means of its technique: (30 x 75 + 30 x 90) / 60 = 82.5 kV, (30 x 2 + 30 x 3) / 60 = 2.5 mA.
    assert len(off) == 1 and off[0].air_kerma_mgy == pytest.approx(12.0, rel=1e-9)
    assert (off[0].detail["kvp"], off[0].detail["ma"]) == (pytest.approx(82.5), pytest.approx(2.5))
    # Without a technique, the reference kV, and the factor alone scales the tube current
    # (2.0 mA x 0.5) and the rate.
    console.set_exposure_factor(0.5, 80.0)
    assert (console.snapshot().kvp, console.snapshot().ma) == (75, pytest.approx(1.0))
    on = [e for e in console.handle(InputEvent(90.0, "pedal", PEDAL, True)) if e.kind == "fluoro_on"]
    assert on[0].detail["air_kerma_rate_mgy_per_min"] == pytest.approx(4.0)
    assert (on[0].detail["kvp"], on[0].detail["ma"]) == (75, pytest.approx(1.0))
    # Only the one given is replaced.
    console.set_exposure_factor(1.0, 95.0, kvp=60)
    assert (console.snapshot().kvp, console.snapshot().ma) == (60.0, 2.0)
    console.set_exposure_factor(1.0, 96.0, ma=1.0)
    assert (console.snapshot().kvp, console.snapshot().ma) == (75, 1.0)


def test_a_note_is_recorded_at_its_time_with_the_totals_then_and_never_before_the_last_event():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(InputEvent(10.0, "pedal", PEDAL, True))
    events = console.note(40.0, "geometry", angle_deg=3.0)
    note = events[-1]
    assert (note.kind, note.detail, note.t_monotonic) == ("geometry", {"angle_deg": 3.0}, 40.0)
    # 30 s of continuous fluoroscopy at 8 mGy/min accrued up to the note: 4 mGy.
    assert note.fluoro_time_s == pytest.approx(30.0) and note.air_kerma_mgy == pytest.approx(4.0)
    assert sum(e.d_air_kerma_mgy for e in events) == pytest.approx(4.0)
    # A note stamped before the last thing the console saw is kept in order, at that time.
    late = console.note(35.0, "trainee", name="A")[-1]
    assert late.t_monotonic == 40.0 and late.fluoro_time_s == pytest.approx(30.0) and late.detail == {"name": "A"}


def alarm_times(console: Console, until: float) -> list[float]:
    events = console.handle(InputEvent(10.0, "pedal", PEDAL, True)) + console.tick(until)
    return [e.t_monotonic for e in events if e.kind == "alarm"]


def test_a_carried_timer_brings_the_alarm_forward_and_its_alarms_count():
    # 200 s carried: the 300 s alarm is due after 100 s of this session's fluoroscopy.
    console = Console(II, KEYMAP, t0=0.0)
    console.carry_over(200.0, 1)
    s = console.snapshot()
    assert (s.fluoro_time_s, s.alarm_count) == (200.0, 1)
    assert alarm_times(console, 400.0) == [pytest.approx(110.0)]
    assert console.snapshot().alarm_count == 2 and console.snapshot().air_kerma_mgy == pytest.approx(8.0 * 390 / 60)
    # Exactly on a multiple, the alarm there has sounded: the next is a whole period on (900 s).
    console = Console(II, KEYMAP, t0=0.0)
    console.carry_over(600.0, 2)
    assert alarm_times(console, 400.0) == [pytest.approx(310.0)]
    # Nonsense from a damaged ledger carries nothing.
    console = Console(II, KEYMAP, t0=0.0)
    console.carry_over(-5.0, -2)
    assert (console.snapshot().fluoro_time_s, console.snapshot().alarm_count) == (0.0, 0)
    assert alarm_times(console, 400.0) == [pytest.approx(310.0)]
