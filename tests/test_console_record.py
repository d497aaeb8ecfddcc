"""What the console records for the ledger, field by field, for one short scripted session on
the flat-panel room, and the state it starts in. The expected records are written out by hand
from the profile's numbers; a record may carry more fields than these, never fewer or others."""

from __future__ import annotations

from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console, minutes_and_tenths
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
FLAT = load_profile(REPO / "configs/fluoroscopes/generic-flat-detector.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
SCALE = (600.0 / 1100.0) ** 2     # detector plane (SID 1100 mm) to the reference point (750 - 150 mm)


def act(t, action, pressed=True):
    return InputEvent(t, "keypad", action, pressed)


def rate(zoom: int, mode: str) -> float:
    return FLAT.zoom_levels[zoom - 1].air_kerma_rate_mgy_per_min[mode]


def technique(zoom: int, fov: float, h: float, v: float, mode: str, pulse_rate):
    pulsed = pulse_rate is not None
    return {"mode": mode, "pulse_rate_per_s": pulse_rate, "pulse_width_ms": 8 if pulsed else None, "kvp": 70,
            "ma": 3.0, "focal_spot_mm": 0.4, "zoom": zoom, "fov_mm": fov, "collimation_h_mm": h,
            "collimation_v_mm": v, "field_area_cm2": pytest.approx(h * v / 100 * SCALE),
            "air_kerma_rate_mgy_per_min": pytest.approx(rate(zoom, mode)), "sid_mm": 1100,
            "source_to_isocentre_mm": 750, "source_to_reference_mm": 600}


def test_a_fresh_console_shows_nothing_and_has_recorded_nothing():
    c = Console(FLAT, KEYMAP, t0=5.0)
    s = c.snapshot()
    assert (s.t, s.fluoro_on, s.image, s.invert, s.breath_hold, s.alarm_sounding) == (5.0, False, "none", False, False,
                                                                                        False)
    assert (s.fluoro_time_s, s.air_kerma_mgy, s.dap_gy_cm2, s.air_kerma_rate_mgy_per_min) == (0.0, 0.0, 0.0, 0.0)
    assert (s.runs, s.alarm_count, s.save_count, s.pulses, s.image_due(None)) == (0, 0, 0, 0, False)
    assert s.fluoro_time_display == "0.0" and s.zoom == 1 and s.collimation_mm == (300.0, 300.0)
    c.tick(6.0)
    assert not c.snapshot().image_due(s) and c.snapshot().pulses == 0
    # Saving with nothing exposed yet saves nothing; resetting a silent alarm records nothing.
    assert c.handle(act(7.0, "save")) == [] and c.handle(act(7.5, "alarm_reset")) == []
    assert c.handle(act(8.0, "resume_breath")) == []


def test_the_session_is_recorded_field_by_field():
    c = Console(FLAT, KEYMAP, t0=0.0)
    ev = []
    ev += c.handle(act(1.0, "zoom_2"))
    ev += c.handle(act(2.0, "collimate_h_close"))
    ev += c.handle(act(3.0, "mode_next"))                   # pulsed-15
    ev += c.handle(act(4.0, "invert"))
    ev += c.handle(act(4.5, "hold_breath"))
    ev += c.handle(act(5.0, "pedal"))                       # pulses at 5 + k/15
    ev += c.handle(act(5.1, "save"))
    state_live = c.snapshot()
    ev += c.handle(act(5.5, "zoom_prev"))                   # back to zoom 1 while exposing
    ev += c.handle(act(6.0, "pedal", False))
    ev += c.handle(act(7.0, "save"))
    ev += c.handle(act(7.5, "resume_breath"))
    ev += c.handle(act(8.0, "mode_next"))                   # pulsed-7.5
    ev += c.handle(act(9.0, "pedal"))
    ev += c.tick(9.0)
    ev += c.set_fluoroscope(FLAT)                           # a reload, while exposing
    ev += c.end(9.4)

    def non_pulse(events):
        return [(e.t_monotonic, e.kind, e.detail) for e in events if e.kind != "pulse"]

    k2 = 8 * rate(2, "pulsed-15") / 60 / 15                 # pulses at 5 + k/15 < 5.5: k = 0..7
    k1 = 8 * rate(1, "pulsed-15") / 60 / 15                 # 5.5 + k/15 < 6: k = 0..7
    expected = [
        (1.0, "zoom", {"zoom": 2, "fov_mm": 220.0, "collimation_h_mm": 220.0, "collimation_v_mm": 220.0}),
        (2.0, "collimation", {"collimation_h_mm": 210.0, "collimation_v_mm": 220.0}),
        (3.0, "mode", {"mode": "pulsed-15", "pulse_rate_per_s": 15}),
        (4.0, "invert", {"invert": True}),
        (4.5, "hold_breath", {}),
        (5.0, "fluoro_on", {"run": 1, "reason": "pressed", **technique(2, 220.0, 210.0, 220.0, "pulsed-15", 15)}),
        (5.1, "save", {"n": 1, "image": "live"}),
        (5.5, "fluoro_off", {"run": 1, "reason": "settings changed", "start_t": 5.0, "duration_s": pytest.approx(0.5),
                             "air_kerma_mgy": pytest.approx(k2), "pulses": 8,
                             "dap_gy_cm2": pytest.approx(k2 / 1000 * 21 * 22 * SCALE),
                             **technique(2, 220.0, 210.0, 220.0, "pulsed-15", 15)}),
        # The narrowed blade is kept (210 mm), the open one opens to the wider field.
        (5.5, "zoom", {"zoom": 1, "fov_mm": 300.0, "collimation_h_mm": 210.0, "collimation_v_mm": 300.0}),
        (5.5, "fluoro_on", {"run": 2, "reason": "settings changed",
                            **technique(1, 300.0, 210.0, 300.0, "pulsed-15", 15)}),
        (6.0, "fluoro_off", {"run": 2, "reason": "released", "start_t": 5.5, "pulses": 8,
                             "air_kerma_mgy": pytest.approx(k1)}),
        (7.0, "save", {"n": 2, "image": "held"}),
        (7.5, "resume_breath", {}),
        (8.0, "mode", {"mode": "pulsed-7.5", "pulse_rate_per_s": 7.5}),
        (9.0, "fluoro_on", {"run": 3, "reason": "pressed", **technique(1, 300.0, 210.0, 300.0, "pulsed-7.5", 7.5)}),
        (9.0, "fluoro_off", {"run": 3, "reason": "profile reloaded", "start_t": 9.0, "pulses": 1}),
        (9.0, "profile", {"fluoroscope": FLAT.name, "mode": "pulsed-7.5"}),
        (9.0, "fluoro_on", {"run": 4, "reason": "profile reloaded"}),
        (9.4, "fluoro_off", {"run": 4, "reason": "session ended", "start_t": 9.0, "duration_s": pytest.approx(0.4)}),
    ]
    got = non_pulse(ev)
    assert [(t, k) for t, k, _ in got] == [(pytest.approx(t), k) for t, k, _ in expected]
    for (t, kind, detail), (_, _, want) in zip(got, expected):
        missing = {key: value for key, value in want.items() if key not in detail or detail[key] != value}
        assert not missing, (t, kind, missing, detail)
    # Every record carries the running totals and the increments since the one before.
    totals = 0.0
    for e in ev:
        totals += e.d_air_kerma_mgy
        assert e.air_kerma_mgy == pytest.approx(totals)
    assert ev[-1].air_kerma_mgy == pytest.approx(c.snapshot().air_kerma_mgy)
    assert ev[-1].dap_gy_cm2 == pytest.approx(c.snapshot().dap_gy_cm2)
    assert ev[-1].fluoro_time_s == pytest.approx(0.5 + 0.5 + 0.4)
    # Pulses name their run; the live state while exposing shows the rate and a live image.
    assert [e.detail["run"] for e in ev if e.kind == "pulse"][:9] == [1] * 8 + [2]
    assert state_live.air_kerma_rate_mgy_per_min == pytest.approx(rate(2, "pulsed-15"))
    assert state_live.image == "live" and state_live.invert and state_live.breath_hold
    assert c.snapshot().air_kerma_rate_mgy_per_min == 0.0 and c.snapshot().image == "held"


@pytest.mark.parametrize("seconds,shown", [(0.0, "0.0"), (5.9, "0.0"), (6.0, "0.1"), (59.99, "0.9"), (60.0, "1.0"),
                                           (299.99, "4.9"), (300.0, "5.0"), (-3.0, "0.0")])
def test_minutes_and_tenths_never_round_up(seconds, shown):
    assert minutes_and_tenths(seconds) == shown


def test_continuous_fluoroscopy_records_progress_each_second_with_its_run():
    c = Console(FLAT, KEYMAP, t0=0.0)
    c.handle(act(0.5, "pedal"))
    ev = c.tick(3.0)
    # Each with the run's technique integrated so far: 1 s and 2 s at the panel's 70 kV 3 mA.
    assert [(e.t_monotonic, e.detail) for e in ev if e.kind == "exposure"] == [
        (1.5, {"run": 1, "kvp_s": pytest.approx(70.0), "ma_s": pytest.approx(3.0)}),
        (2.5, {"run": 1, "kvp_s": pytest.approx(140.0), "ma_s": pytest.approx(6.0)})]
    drawn = c.snapshot()
    c.tick(3.1)
    s = c.snapshot()
    assert s.image_due(drawn) and s.pulses == 0              # continuous: every frame is a new image
    c.handle(act(3.2, "pedal", False))
    c.tick(3.3)
    held = c.snapshot()
    assert not held.image_due(s) and held.image == "held"   # released: the last image stays, none is made


def with_modes(names: list[str]) -> FluoroscopeProfile:
    modes = [m for m in FLAT.tube.modes if m.name in names]
    return FLAT.model_copy(update={"tube": FLAT.tube.model_copy(update={"modes": modes})})


@pytest.mark.parametrize("names,after", [(["continuous"], "continuous"), (["continuous", "pulsed-15"], "pulsed-15")])
def test_mode_key_on_machines_with_one_or_two_modes(names, after):
    c = Console(with_modes(names), KEYMAP, t0=0.0)
    events = c.handle(act(1.0, "mode_next"))
    assert c.snapshot().mode == after
    assert [e.kind for e in events] == ([] if len(names) == 1 else ["mode"])


def test_alarm_reset_and_breath_resume_are_recorded_when_pressed_and_clear_the_flags():
    c = Console(FLAT, KEYMAP, t0=0.0)
    c.handle(act(0.0, "pedal"))
    c.tick(300.0)                                           # the alarm lands exactly at 5:00
    c.handle(act(301.0, "pedal", False))
    (reset,) = c.handle(act(305.0, "alarm_reset"))
    assert (reset.kind, reset.t_monotonic) == ("alarm_reset", 305.0)
    c.handle(act(306.0, "hold_breath"))
    (resume,) = c.handle(act(307.0, "resume_breath"))
    assert (resume.kind, resume.t_monotonic) == ("resume_breath", 307.0)
    s = c.snapshot()
    assert s.alarm_sounding is False and s.breath_hold is False and s.fluoro_on is False


def test_a_reload_right_on_an_alarm_does_not_sound_it_again():
    c = Console(FLAT, KEYMAP, t0=0.0)
    c.handle(act(0.0, "pedal"))
    c.tick(300.0)
    assert c.snapshot().alarm_count == 1 and c.snapshot().fluoro_time_s == 300.0
    c.set_fluoroscope(FLAT)                                 # the next one is at 10:00, not 5:00 again
    assert [e for e in c.tick(310.0) if e.kind == "alarm"] == []
    assert c.snapshot().alarm_count == 1


def test_the_exposure_control_hands_back_the_pulses_due_before_it_changes_the_output():
    c = Console(FLAT, KEYMAP, t0=0.0)
    c.handle(act(0.0, "mode_next"))                         # pulsed-15
    c.handle(act(1.0, "pedal"))                             # first pulse at 1.0
    events = c.set_exposure_factor(2.0, 1.0 + 2.5 / 15)     # pulses at 1 + 1/15 and 1 + 2/15 came first
    assert [e.kind for e in events] == ["pulse", "pulse"]
    per_pulse = rate(1, "pulsed-15") / 60 / 15
    assert c.snapshot().air_kerma_mgy == pytest.approx(3 * per_pulse)
    c.tick(1.0 + 3.5 / 15)                                  # the next pulse at twice the output
    assert c.snapshot().air_kerma_mgy == pytest.approx(5 * per_pulse)


def test_a_frame_drawn_at_the_moment_fluoroscopy_starts_or_continues_is_a_new_image():
    c = Console(FLAT, KEYMAP, t0=0.0)
    c.handle(act(5.0, "pedal"))                             # continuous
    c.tick(5.0)                                             # the same instant: no time has passed
    first = c.snapshot()
    assert first.image_due(None)
    c.tick(6.0)
    drawn = c.snapshot()
    c.tick(6.0)                                             # a second frame at the same time, still exposing
    assert c.snapshot().image_due(drawn) and c.snapshot().image_due(first)
    (on,) = [e for e in c.handle(act(7.0, "pedal", False)) + c.handle(act(8.0, "pedal")) if e.kind == "fluoro_on"]
    assert on.detail["pulse_width_ms"] is None and on.detail["pulse_rate_per_s"] is None


def test_a_pulsed_image_is_due_only_after_a_new_pulse():
    c = Console(FLAT, KEYMAP, t0=0.0)
    c.handle(act(0.0, "mode_next"))
    c.handle(act(1.0, "pedal"))
    c.tick(1.01)
    drawn = c.snapshot()
    assert drawn.image_due(None) and not drawn.image_due(drawn)
    c.tick(1.02)                                            # no pulse since the one drawn
    assert not c.snapshot().image_due(drawn)
    c.tick(1.0 + 1.5 / 15)
    assert c.snapshot().image_due(drawn)
