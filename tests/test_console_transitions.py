"""Console transitions the everyday tests do not reach: the session ending mid-run, a profile
reload while exposing, the alarm rescheduled by a reload, the pulse record and zooming out
with the blades open. Every number is worked by hand from the shipped profiles."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)      # SID 1000, SOD 620
FLAT = load_profile(REPO / "configs/fluoroscopes/generic-flat-detector.yaml", FluoroscopeProfile)  # SID 1100, SOD 750
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)


def act(t: float, action: str, pressed: bool = True) -> InputEvent:
    return InputEvent(t, "keypad", action, pressed)


def with_alarm_period(fl: FluoroscopeProfile, period_s: float) -> FluoroscopeProfile:
    return fl.model_copy(update={"dose": fl.dose.model_copy(update={"alarm_period_s": period_s})})


def kinds(events, kind):
    return [e for e in events if e.kind == kind]


def test_session_end_closes_the_run_in_progress_and_records_it():
    c = Console(II, KEYMAP, t0=0.0)
    c.handle(act(1.0, "pedal"))
    events = c.end(11.0)
    (off,) = kinds(events, "fluoro_off")
    assert off.t_monotonic == 11.0 and off.detail["reason"] == "session ended" and off.detail["run"] == 1
    assert off.detail["duration_s"] == pytest.approx(10.0)
    assert off.detail["air_kerma_mgy"] == pytest.approx(8.0 * 10 / 60)      # zoom 1, continuous: 8 mGy/min
    state = c.snapshot()
    assert not state.fluoro_on and state.fluoro_time_s == pytest.approx(10.0)
    assert state.air_kerma_mgy == pytest.approx(8.0 * 10 / 60)
    # The pedal still held at the end is forgotten: its release starts or ends nothing.
    assert c.handle(act(12.0, "pedal", False)) == []
    assert c.end(13.0) == [] and c.snapshot().fluoro_time_s == pytest.approx(10.0)


def test_reload_while_exposing_splits_the_run_at_the_new_machine_rates():
    c = Console(II, KEYMAP, t0=0.0)
    c.handle(act(0.0, "pedal"))
    c.tick(30.0)
    events = c.set_fluoroscope(FLAT)
    c.tick(45.0)
    events += c.handle(act(60.0, "pedal", False))
    offs, ons = kinds(events, "fluoro_off"), kinds(events, "fluoro_on")
    assert [e.detail["reason"] for e in offs] == ["profile reloaded", "released"]
    assert [(e.detail["run"], e.detail["reason"], e.t_monotonic) for e in ons] == [(2, "profile reloaded", 30.0)]
    assert kinds(events, "profile")[0].detail["fluoroscope"] == FLAT.name
    # 30 s at the intensifier's 8 mGy/min, then 30 s at the flat panel's 6 mGy/min (zoom 1, continuous).
    assert offs[0].t_monotonic == 30.0 and offs[0].detail["air_kerma_mgy"] == pytest.approx(4.0)
    assert offs[1].detail["air_kerma_mgy"] == pytest.approx(3.0)
    # Blades fully open on the intensifier stay fully open on the flat panel's 300 mm field;
    # its field at the reference point: 300 x 300 mm at 1100 mm scaled to 750 - 150 = 600 mm.
    state = c.snapshot()
    assert state.collimation_mm == (300.0, 300.0) and state.mode == "continuous"
    assert offs[1].detail["dap_gy_cm2"] == pytest.approx(3.0 / 1000 * 900.0 * (600 / 1100) ** 2)
    assert offs[0].detail["dap_gy_cm2"] == pytest.approx(4.0 / 1000 * math.pi * 11.5**2 * (470 / 1000) ** 2)
    assert state.fluoro_time_s == pytest.approx(60.0) and state.air_kerma_mgy == pytest.approx(7.0)
    assert state.runs == 2


def test_reload_reschedules_the_alarm_at_the_next_multiple_of_the_new_period():
    c = Console(II, KEYMAP, t0=0.0)
    c.handle(act(0.0, "pedal"))
    c.tick(310.0)
    assert c.snapshot().alarm_count == 1                    # 300 s
    c.set_fluoroscope(with_alarm_period(II, 120.0))
    # 310 s of fluoroscopy so far: the next multiple of 120 s is 360 s.
    assert kinds(c.tick(359.0), "alarm") == []
    (alarm,) = kinds(c.tick(361.0), "alarm")
    assert alarm.detail["at_fluoro_time_s"] == 360.0 and alarm.detail["n"] == 2
    assert alarm.t_monotonic == pytest.approx(360.0)
    # Back to 300 s: after 361 s the next multiple is 600 s, not 300 s again.
    c.set_fluoroscope(II)
    assert kinds(c.tick(599.0), "alarm") == []
    assert [e.detail["at_fluoro_time_s"] for e in kinds(c.tick(601.0), "alarm")] == [600.0]


def test_a_reload_without_the_current_mode_falls_back_to_the_first():
    c = Console(FLAT, KEYMAP, t0=0.0)
    for k in range(3):
        c.handle(act(1.0 + k, "mode_next"))
    assert c.snapshot().mode == "pulsed-3"                  # the flat panel's fourth mode
    c.set_fluoroscope(II)                                   # the intensifier has no pulsed-3
    assert c.snapshot().mode == II.tube.modes[0].name == "continuous"
    c.set_fluoroscope(FLAT)
    c.handle(act(5.0, "mode_next"))
    c.set_fluoroscope(II)
    assert c.snapshot().mode == "pulsed-15"                 # kept: the intensifier has it too


def test_each_pulse_names_its_run_and_its_number_and_a_frame_counts_its_pulses():
    c = Console(II, KEYMAP, t0=0.0)
    c.handle(act(0.0, "mode_next"))                          # pulsed-15
    events = c.handle(act(1.0, "pedal"))
    c.tick(1.0)
    drawn = c.snapshot()                                     # the pulse at pedal-down
    events += c.tick(1.0 + 2.5 / 15)                         # pulses at 1 + 1/15 and 1 + 2/15
    s = c.snapshot()
    assert s.pulses - drawn.pulses == 2 and s.image_due(drawn)
    events += c.tick(1.0 + 2.7 / 15)                         # no pulse in this frame
    assert c.snapshot().pulses == s.pulses and not c.snapshot().image_due(s)
    events += c.handle(act(1.5, "pedal", False))             # pulses at 1 + k/15 < 1.5: k = 0..7
    events += c.handle(act(3.0, "pedal"))
    events += c.handle(act(3.2, "pedal", False))             # 3 + k/15 < 3.2: k = 0..2
    pulses = kinds(events, "pulse")
    assert [(p.detail["run"], p.detail["n"]) for p in pulses] == [(1, n) for n in range(1, 9)] + [(2, n) for n in (1, 2, 3)]
    assert [p.t_monotonic for p in pulses[:3]] == pytest.approx([1.0, 1.0 + 1 / 15, 1.0 + 2 / 15])


def test_zooming_out_with_the_blades_open_opens_them_to_the_wider_field():
    c = Console(II, KEYMAP, t0=0.0)
    c.handle(act(1.0, "zoom_3"))
    assert c.snapshot().collimation_mm == (130.0, 130.0)
    c.handle(act(2.0, "zoom_1"))
    assert c.snapshot().collimation_mm == (230.0, 230.0)
    c.handle(act(3.0, "collimate_h_close"))
    c.handle(act(4.0, "zoom_2"))                             # 220 mm blade clipped to the 170 mm field
    assert c.snapshot().collimation_mm == (170.0, 170.0)
    c.handle(act(5.0, "collimate_h_close"))
    c.handle(act(6.0, "zoom_1"))                             # a closed blade stays where it was
    assert c.snapshot().collimation_mm == (160.0, 230.0)
