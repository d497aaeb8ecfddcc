"""The shipped demo session, played through the scripted driver into the console and ledger."""

from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_appliance, load_profile
from appliance.console.alarm_sound import AlarmSound, alarm_wav
from appliance.console.inputs import open_inputs
from appliance.console.state import Console
from appliance.errors import FluorosimError
from appliance.records.ledger import Ledger, open_readonly, verify
from drivers.input_event import NoInput
from drivers.scripted_input import ScriptedInput, parse_script

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "configs/scripts/demo-session.jsonl"
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)


def play(path, frame_s=1 / 30):
    script = ScriptedInput(path, t0=0.0)
    console = Console(II, KEYMAP, t0=0.0)
    events, states, now = [], [], 0.0
    while not script.finished:
        now += frame_s
        frame = []
        for ev in script.poll(now):
            frame += console.handle(ev)
        frame += console.tick(now)
        states.append(console.snapshot())
        events += frame
    return console, events, states


def test_demo_session_exercises_every_control_and_the_alarm(tmp_path):
    with Ledger(tmp_path / "ledger.sqlite") as ledger:
        ledger.start_session("demo", "demo", II.name, t_wall=1_700_000_000.0, t_monotonic=0.0)
        console, events, states = play(SCRIPT)
        ledger.record(events)
        ledger.end_session(1_700_000_400.0)
    kinds = [e.kind for e in events]
    # Hand sum of the script's pedal and hand-switch holds:
    # 9 + 3 + 3 + 7 + 7 + 6 + 2.5 + 10 + 10 + 100 + 20 + 132.5 s.
    assert console.snapshot().fluoro_time_s == pytest.approx(310.0, abs=0.01)
    assert {s.zoom for s in states} == {1, 2, 3, 4}
    collimations = [tuple(e.detail[k] for k in ("collimation_h_mm", "collimation_v_mm")) for e in events if e.kind == "collimation"]
    h, v = zip(*collimations)
    assert any(b < a for a, b in zip(h, h[1:])) and any(b > a for a, b in zip(h, h[1:]))
    assert any(b < a for a, b in zip(v, v[1:])) and any(b > a for a, b in zip(v, v[1:]))
    assert {s.mode for s in states} == {"continuous", "pulsed-15", "pulsed-7.5"}
    assert kinds.count("invert") == 2 and kinds.count("save") == 6
    assert kinds.count("hold_breath") == 3 and kinds.count("resume_breath") == 3
    alarms = [e for e in events if e.kind == "alarm"]
    assert len(alarms) == 1 and alarms[0].fluoro_time_s == 300.0
    assert alarms[0].t_monotonic == pytest.approx(272.0 + 122.5, abs=1e-6)
    assert kinds.index("alarm_reset") > kinds.index("alarm") and not console.snapshot().alarm_sounding
    assert any(s.alarm_sounding for s in states)
    runs = [e for e in events if e.kind == "fluoro_off"]
    assert sum(r.detail["duration_s"] for r in runs) == pytest.approx(310.0, abs=0.01)
    conn = open_readonly(tmp_path / "ledger.sqlite")
    assert verify(conn).ok
    s = conn.execute("SELECT * FROM sessions").fetchone()
    assert s["fluoro_time_s"] == pytest.approx(310.0, abs=0.01) and s["alarms"] == 1 and s["saves"] == 6


def test_inputs_from_the_appliance_profile(tmp_path):
    config = load_appliance(REPO / "configs/appliance.yaml")
    keypad, pedal = open_inputs(config, now=0.0)
    assert isinstance(keypad, NoInput) and isinstance(pedal, NoInput)
    scripted = config.__class__(**{**config.__dict__, "appliance": config.appliance.model_copy(update={
        "devices": config.appliance.devices.model_copy(update={
            "keypad": config.appliance.devices.keypad.model_copy(update={"source": "scripted", "script": str(SCRIPT)})})})})
    keypad, _ = open_inputs(scripted, now=10.0)
    # The script's times count from the console time it was opened at (10 s here).
    first = min(t for t, _, _ in parse_script(SCRIPT.read_text()))
    assert isinstance(keypad, ScriptedInput) and keypad.poll(10.0 + first)[0].t_monotonic == 10.0 + first
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"t": 1, "tap": "save"}\n{"t": 2, "tap"}\n')
    broken = scripted.__class__(**{**scripted.__dict__, "appliance": scripted.appliance.model_copy(update={
        "devices": scripted.appliance.devices.model_copy(update={
            "keypad": scripted.appliance.devices.keypad.model_copy(update={"script": str(bad)})})})})
    with pytest.raises(FluorosimError, match=r"bad.jsonl:2: not valid JSON"):
        open_inputs(broken, now=0.0)


def test_alarm_tone_is_the_stated_pitch():
    import io
    import wave

    import numpy as np
    with wave.open(io.BytesIO(alarm_wav(tone_hz=880.0, beep_s=0.5, gap_s=0.0, beeps=1, rate_hz=16000))) as w:
        samples = np.frombuffer(w.readframes(w.getnframes()), dtype="<i2").astype(float)
        assert w.getframerate() == 16000 and len(samples) == 8000
    spectrum = np.abs(np.fft.rfft(samples))
    assert np.argmax(spectrum) * 16000 / len(samples) == pytest.approx(880.0, abs=2.0)


def test_alarm_sound_without_a_sound_card_is_visual_only(tmp_path):
    cards = tmp_path / "cards"
    cards.write_text("--- no soundcards ---\n")
    sound = AlarmSound(cards=cards)
    assert not sound.available and "visual only" in sound.reason
    sound.update(True)
    assert not sound.playing


def test_alarm_sound_plays_until_reset(tmp_path, monkeypatch):
    # A stand-in player where the test machine has no sound card: it records what ALSA would play.
    cards = tmp_path / "cards"
    cards.write_text(" 0 [PCH            ]: HDA-Intel - HDA Intel PCH\n")
    player = tmp_path / "bin" / "aplay"
    player.parent.mkdir()
    player.write_text(f"#!/bin/sh\ncat > {tmp_path}/played.wav\nexec sleep 30\n")
    player.chmod(0o755)
    monkeypatch.setenv("PATH", f"{player.parent}:/usr/bin:/bin")
    sound = AlarmSound(cards=cards)
    assert sound.available
    sound.update(True)
    assert sound.playing
    sound.update(True)                       # still the same pattern playing
    import time
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and (not (tmp_path / "played.wav").exists()
                                           or (tmp_path / "played.wav").stat().st_size < len(alarm_wav())):
        time.sleep(0.01)
    assert (tmp_path / "played.wav").read_bytes() == alarm_wav()
    sound.update(False)
    assert not sound.playing
