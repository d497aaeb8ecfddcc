"""The console state machine under an injected clock, checked against hand-worked numbers."""

import math
import random
from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console import dose
from appliance.console.state import Console, minutes_and_tenths
from drivers.input_event import InputEvent
from drivers.scripted_input import ScriptedInput

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
FLAT = load_profile(REPO / "configs/fluoroscopes/generic-flat-detector.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)


def press(t, key, source="scripted"):
    return InputEvent(t, source, key, True)


def release(t, key, source="scripted"):
    return InputEvent(t, source, key, False)


def run_script(console, script: ScriptedInput, frame_s: float, jitter: float, rng) -> list:
    events = []
    now = script.t0
    while not script.finished:
        now += frame_s * (1 + rng.uniform(-jitter, jitter))
        for ev in script.poll(now):
            events += console.handle(ev)
        events += console.tick(now)
    events += console.tick(now + 1.0)
    return events


def test_fluoro_time_equals_pedal_down_time_within_10_ms(tmp_path):
    rng = random.Random(7)
    lines, t, down = [], 1.0, 0.0
    for _ in range(25):
        hold = round(rng.uniform(0.05, 20.0), 3)
        lines.append(f'{{"t": {t}, "hold": "pedal", "for_s": {hold}}}')
        down += hold
        t = round(t + hold + rng.uniform(0.05, 5.0), 3)
    path = tmp_path / "pedal.jsonl"
    path.write_text("\n".join(lines) + "\n")
    console = Console(II, KEYMAP, t0=100.0)
    run_script(console, ScriptedInput(path, t0=100.0), 1 / 30, 0.5, rng)
    state = console.snapshot()
    assert abs(state.fluoro_time_s - down) < 0.010
    assert state.runs == 25 and not state.fluoro_on and state.image == "held"
    # Continuous at zoom 1: 8 mGy/min for the whole pedal-down time.
    assert state.air_kerma_mgy == pytest.approx(8.0 * down / 60.0, rel=1e-9)


def test_pulsed_kerma_is_one_dose_per_pulse_from_pedal_down():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "mode_next"))                     # pulsed-15
    evs = console.handle(press(1.0, "pedal"))
    for i in range(1, 200):
        evs += console.tick(1.0 + i * 0.0123)
    evs += console.handle(release(3.5, "pedal"))
    pulses = [e for e in evs if e.kind == "pulse"]
    # Pulses at 1.0 + k/15 for times in [1.0, 3.5): k = 0..37.
    assert len(pulses) == 38
    assert pulses[5].t_monotonic == pytest.approx(1.0 + 5 / 15)
    per_pulse = 4.0 / 60 / 15                                   # zoom 1, pulsed-15: 4 mGy/min
    off = [e for e in evs if e.kind == "fluoro_off"][0]
    assert off.detail["air_kerma_mgy"] == pytest.approx(38 * per_pulse)
    assert off.detail["pulses"] == 38 and off.detail["pulse_rate_per_s"] == 15
    assert console.snapshot().fluoro_time_s == pytest.approx(2.5)


def test_automatic_brightness_scales_the_dose_rate_from_the_moment_it_changes():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "pedal"))                          # continuous, zoom 1: 8 mGy/min
    console.tick(10.0)
    console.set_exposure_factor(2.5, 10.0)                       # a lateral view: 20 mGy/min
    console.tick(16.0)
    console.set_exposure_factor(0.5, 16.0)                       # a thin part: 4 mGy/min
    console.handle(release(19.0, "pedal"))
    # 10 s at 8, 6 s at 20 and 3 s at 4 mGy/min.
    kerma = (10 * 8.0 + 6 * 20.0 + 3 * 4.0) / 60.0
    state = console.snapshot()
    assert state.air_kerma_mgy == pytest.approx(kerma, rel=1e-9)
    # Blades fully open on the intensifier: its 230 mm circular field at the detector (SID
    # 1000 mm), scaled to the reference point at 620 - 150 = 470 mm from the focal spot.
    assert state.collimation_mm == (230.0, 230.0)
    area_cm2 = math.pi * 11.5 ** 2 * (470.0 / 1000.0) ** 2
    assert state.dap_gy_cm2 == pytest.approx(kerma / 1000 * area_cm2, rel=1e-9)
    # Pulsed: each pulse carries the rate in force when it is fired.
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "mode_next"))                     # pulsed-15: 4 mGy/min
    console.set_exposure_factor(3.0, 0.5)                       # kept from the last image
    evs = console.handle(press(1.0, "pedal"))
    for i in range(1, 100):
        evs += console.tick(1.0 + i * 0.01)
    evs += console.handle(release(1.99, "pedal"))
    pulses = [e for e in evs if e.kind == "pulse"]
    assert len(pulses) == 15                                    # 1.0 + k/15 for k = 0..14
    assert console.snapshot().air_kerma_mgy == pytest.approx(15 * 3.0 * 4.0 / 60 / 15)


def test_alarm_at_exactly_300_s_across_runs_and_reset_silences_it():
    console = Console(II, KEYMAP, t0=0.0)
    starts, lengths = [10.0, 200.0, 400.0, 700.0], [70.0, 80.0, 90.0, 100.0]
    evs = []
    for start, length in zip(starts, lengths):
        evs += console.handle(press(start, "KEY_KPENTER", "keypad"))
        t = start
        while t < start + length:
            t = min(t + 0.04, start + length)
            evs += console.tick(t)
            if start == 700.0 and t < 760.0 - 1e-9:
                assert not console.snapshot().alarm_sounding
        evs += console.handle(release(start + length, "KEY_KPENTER", "keypad"))
    alarms = [e for e in evs if e.kind == "alarm"]
    # 70 + 80 + 90 = 240 s before the last run, so 300 s falls 60 s into it.
    assert len(alarms) == 1
    assert alarms[0].t_monotonic == pytest.approx(760.0, abs=1e-6)
    assert alarms[0].fluoro_time_s == 300.0
    state = console.snapshot()
    assert state.alarm_sounding and state.fluoro_time_s == pytest.approx(340.0)
    console.tick(900.0)
    assert console.snapshot().alarm_sounding                    # sounds until reset
    assert [e.kind for e in console.handle(press(901.0, "KEY_KPASTERISK", "keypad"))] == ["alarm_reset"]
    assert not console.snapshot().alarm_sounding
    # The next alarm comes at 600 s cumulative: 260 s more.
    console.handle(press(1000.0, "pedal"))
    evs = console.tick(1259.9)
    assert not [e for e in evs if e.kind == "alarm"]
    evs = console.tick(1260.1)
    assert [e.t_monotonic for e in evs if e.kind == "alarm"] == [pytest.approx(1260.0)]


def test_alarm_when_release_lands_exactly_on_the_threshold():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "pedal"))
    evs = console.handle(release(300.0, "pedal"))
    assert [e.kind for e in evs][-2:] == ["alarm", "fluoro_off"]


def test_collimation_steps_clamp_and_dap_follows_the_field():
    console = Console(FLAT, KEYMAP, t0=0.0)
    assert console.snapshot().collimation_mm == (300.0, 300.0)
    console.handle(press(1.0, "KEY_KP7"))                       # open: already at the field, no change
    for i in range(5):
        console.handle(press(2.0 + i, "KEY_KP9"))               # close h 5 x 10 mm
    for i in range(30):
        console.handle(press(10.0 + i, "KEY_KP6"))              # close v to the 20 mm minimum
    assert console.snapshot().collimation_mm == (250.0, 20.0)
    console.handle(press(50.0, "KEY_KP4"))
    assert console.snapshot().collimation_mm == (250.0, 30.0)
    console.handle(press(60.0, "pedal"))
    console.handle(release(120.0, "pedal"))
    state = console.snapshot()
    # 60 s continuous at 6 mGy/min = 6 mGy; field 250 x 30 mm at the detector (1100 mm),
    # scaled to the reference point at 750 - 150 = 600 mm: 75 cm^2 x (600/1100)^2.
    area_cm2 = 25.0 * 3.0 * (600.0 / 1100.0) ** 2
    assert state.air_kerma_mgy == pytest.approx(6.0)
    assert state.dap_gy_cm2 == pytest.approx(6.0 / 1000 * area_cm2)


def test_image_intensifier_field_is_clipped_by_the_circle():
    # Fully open: the circular input field of 230 mm; tiny blades: the rectangle itself.
    assert dose.field_area_detector_mm2(II, 1, (230.0, 230.0)) == pytest.approx(math.pi * 115.0 ** 2)
    assert dose.field_area_detector_mm2(II, 1, (100.0, 50.0)) == pytest.approx(5000.0)
    # A slot as wide as the circle, 2b tall: 4 * integral_0^R min(b, sqrt(R^2-x^2)) dx, by quadrature.
    r, b = 115.0, 40.0
    xs = [(i + 0.5) * r / 200000 for i in range(200000)]
    expected = 4 * sum(min(b, math.sqrt(r * r - x * x)) for x in xs) * r / 200000
    assert dose.field_area_detector_mm2(II, 1, (230.0, 80.0)) == pytest.approx(expected, rel=1e-6)


def test_zoom_mode_and_collimation_while_exposing_split_the_run():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "pedal"))
    evs = console.handle(press(10.0, "KEY_KP2"))                # zoom 2 at 10 s
    # Progress records each second of the run, at 1..9 s (the one due at 10 s itself waits for the
    # next advance), then the run ends, the zoom changes and a new run starts, all at 10 s.
    assert [e.kind for e in evs] == ["exposure"] * 9 + ["fluoro_off", "zoom", "fluoro_on"]
    assert [e.t_monotonic for e in evs] == pytest.approx([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 10, 10])
    evs = console.handle(release(20.0, "pedal"))
    offs = [e for e in evs if e.kind == "fluoro_off"]
    state = console.snapshot()
    assert state.zoom == 2 and state.fov_mm == 170.0 and state.collimation_mm == (170.0, 170.0)
    assert offs[0].detail["zoom"] == 2 and offs[0].detail["duration_s"] == pytest.approx(10.0)
    # 10 s at 8 mGy/min then 10 s at 14.6 mGy/min.
    assert state.air_kerma_mgy == pytest.approx((8.0 + 14.6) * 10 / 60)
    assert state.runs == 2


def test_zoom_levels_invert_save_breath_and_hold():
    console = Console(II, KEYMAP, t0=0.0)
    assert console.snapshot().image == "none"
    assert console.handle(press(0.5, "KEY_KPPLUS")) == []          # nothing to save yet
    for key, level, fov in (("KEY_KP2", 2, 170), ("KEY_KP3", 3, 130), ("KEY_KP0", 4, 100), ("KEY_KP1", 1, 230)):
        console.handle(press(1.0, key))
        assert (console.snapshot().zoom, console.snapshot().fov_mm) == (level, fov)
    console.handle(press(2.0, "pedal"))
    assert console.snapshot().image == "live"
    console.handle(release(3.0, "pedal"))
    assert console.snapshot().image == "held" and console.snapshot().held
    assert [e.kind for e in console.handle(press(4.0, "KEY_KPPLUS"))] == ["save"]
    assert console.snapshot().save_count == 1
    console.handle(press(5.0, "KEY_KPMINUS"))
    assert console.snapshot().invert is True
    console.handle(press(6.0, "KEY_KPSLASH"))
    assert console.snapshot().breath_hold
    console.handle(press(7.0, "KEY_KPDOT"))
    assert not console.snapshot().breath_hold
    console.handle(press(8.0, "KEY_KP5"))
    assert console.snapshot().mode == "pulsed-15"
    assert console.handle(press(9.0, "KEY_F24")) == []           # unmapped keys do nothing


def test_pedal_and_key_together_expose_until_both_are_released():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(1.0, "pedal", "pedal"))
    console.handle(press(2.0, "KEY_KPENTER", "keypad"))
    console.handle(release(3.0, "pedal", "pedal"))
    assert console.snapshot().fluoro_on
    console.handle(release(4.0, "KEY_KPENTER", "keypad"))
    assert not console.snapshot().fluoro_on and console.snapshot().fluoro_time_s == pytest.approx(3.0)


def test_increments_sum_to_totals():
    console = Console(II, KEYMAP, t0=0.0)
    rng = random.Random(3)
    evs, t = [], 0.0
    keys = ["KEY_KP5", "KEY_KP2", "KEY_KP9", "KEY_KP0", "KEY_KP7", "KEY_KP1"]
    for _run in range(40):
        evs += console.handle(press(t, "pedal"))
        for _ in range(rng.randint(1, 20)):
            t += rng.uniform(0.01, 0.4)
            evs += console.tick(t)
            if rng.random() < 0.2:
                evs += console.handle(press(t, rng.choice(keys)))
        evs += console.handle(release(t, "pedal"))
        t += 1.0
    s = console.snapshot()
    assert sum(e.d_fluoro_time_s for e in evs) == pytest.approx(s.fluoro_time_s, rel=1e-12)
    assert sum(e.d_air_kerma_mgy for e in evs) == pytest.approx(s.air_kerma_mgy, rel=1e-12)
    assert sum(e.d_dap_gy_cm2 for e in evs) == pytest.approx(s.dap_gy_cm2, rel=1e-12)
    offs = [e for e in evs if e.kind == "fluoro_off"]
    assert sum(o.detail["air_kerma_mgy"] for o in offs) == pytest.approx(s.air_kerma_mgy, rel=1e-9)


def test_an_image_is_due_only_on_pulse_frames():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "KEY_KP5"))                        # pulsed-15 at 60 frames/s
    console.handle(press(1.0, "pedal"))
    flags, drawn = [], None
    for i in range(1, 61):
        console.tick(1.0 + i / 60 - 1e-6)
        state = console.snapshot()
        flags.append(state.image_due(drawn))
        drawn = state
    # Pulses at 1 + k/15 s, k = 0..14: one frame in four shows a new image.
    assert sum(flags) == 15 and flags[0] and flags[4] and not any(flags[1:4])


def test_image_due_counts_pulses_a_slower_reader_did_not_see():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "KEY_KP5"))                        # pulsed-15: pulses at 1 + k/15 s
    console.handle(press(1.0, "pedal"))
    drawn, images = None, 0
    for i in range(1, 201):                                      # the console ticks every 5 ms...
        console.tick(1.0 + i * 0.005 - 1e-6)
        if i % 20 == 0:                                          # ...a renderer looks every 100 ms
            state = console.snapshot()
            if state.image_due(drawn):
                drawn, images = state, images + 1
    # Every 100 ms holds one or two pulses (15 /s), so each look finds one not drawn; the
    # per-tick flag would have been set at only the looks that fell on a pulse's tick.
    assert images == 10
    console.handle(release(2.0, "pedal"))
    console.tick(2.1)
    assert not console.snapshot().image_due(drawn)               # no beam, no new image
    console.handle(press(3.0, "KEY_KP5"))                        # pulsed-7.5, then continuous:
    console.handle(press(3.0, "KEY_KP5"))                        # there every look gets one
    console.handle(press(3.0, "pedal"))
    state = console.snapshot()
    assert state.pulse_rate_per_s is None and state.image_due(state)


def test_collimation_is_reported_only_when_the_blades_cut_the_field():
    console = Console(II, KEYMAP, t0=0.0)
    assert console.snapshot().collimated_mm is None              # blades fully open at 230 mm
    console.handle(press(1.0, "KEY_KP9"))                        # horizontal closes one 10 mm step
    assert console.snapshot().collimated_mm == (220.0, 230.0)
    console.handle(press(2.0, "KEY_KP7"))                        # and opens again: fully open
    assert console.snapshot().collimated_mm is None


def test_minutes_and_tenths_display():
    assert minutes_and_tenths(0) == "0.0"
    assert minutes_and_tenths(5.99) == "0.0"
    assert minutes_and_tenths(6.0) == "0.1"
    assert minutes_and_tenths(299.9) == "4.9"
    assert minutes_and_tenths(300.0) == "5.0"
    assert minutes_and_tenths(3725.0) == "62.0"
    assert minutes_and_tenths(-1.0) == "0.0"


def test_profile_reload_keeps_settings_that_still_apply():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "KEY_KP5"))
    console.handle(press(0.0, "KEY_KP9"))
    console.set_fluoroscope(FLAT)
    s = console.snapshot()
    assert s.mode == "pulsed-15" and s.collimation_mm == (220.0, 300.0) and s.fov_mm == 300.0


def test_reference_point_beyond_the_source_is_refused(tmp_path):
    from appliance.config.yamlfile import ProfileProblems
    text = (REPO / "configs/fluoroscopes/generic-ii-carm.yaml").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("reference_point_from_isocentre_mm: 150", "reference_point_from_isocentre_mm: 700"))
    with pytest.raises(ProfileProblems) as e:
        load_profile(bad, FluoroscopeProfile)
    assert "dose.reference_point_from_isocentre_mm" in str(e.value.problems[0])


def test_hid_usages_and_direct_actions_map_through_the_keymap():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(InputEvent(1.0, "keypad", "hid:0x58", True))          # keypad Enter usage: fluoro
    assert console.snapshot().fluoro_on
    console.handle(InputEvent(2.0, "keypad", "hid:0x58", False))
    assert not console.snapshot().fluoro_on
    console.handle(InputEvent(3.0, "keypad", "hid:0x5a", True))          # zoom_2
    console.handle(press(4.0, "zoom_next"))
    assert console.snapshot().zoom == 3
    console.handle(press(5.0, "zoom_next"))
    console.handle(press(6.0, "zoom_next"))                               # stays at the narrowest
    assert console.snapshot().zoom == 4
    console.handle(press(7.0, "zoom_prev"))
    assert console.snapshot().zoom == 3
    assert console.handle(InputEvent(8.0, "keypad", "hid:0x04", True)) == []   # 'a': not mapped
    assert console.handle(InputEvent(8.0, "keypad", "hid:zz", True)) == []
