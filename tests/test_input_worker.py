"""InputWorker: presses keep the times the device stamped them, whatever else the step applies."""

from __future__ import annotations

import queue
from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.alarm_sound import AlarmSound
from appliance.console.state import Console
from appliance.daemon.handoff import LatestValue, Technique
from appliance.daemon.input_worker import InputWorker
from drivers.scripted_input import ScriptedInput

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)


def test_a_new_tube_output_does_not_move_a_press_polled_in_the_same_step(tmp_path):
    script = tmp_path / "s.jsonl"
    script.write_text('{"t": 1.0, "hold": "pedal", "for_s": 2.0}\n')      # 2.0 s of fluoroscopy
    now = [0.0]
    console = Console(II, KEYMAP, t0=0.0)
    events: queue.Queue = queue.Queue()
    exposure: LatestValue[Technique] = LatestValue("technique")
    worker = InputWorker(console, [ScriptedInput(script, t0=0.0)], AlarmSound(), lambda: now[0],
                         console_state=LatestValue("console"), events=events, fluoroscope=LatestValue("fl"),
                         exposure_factor=exposure)
    # Each poll comes 4 ms after the transition it finds, and each brings a new tube output,
    # as the brightness control sends one after every live image.
    for t, factor in ((1.004, 1.5), (3.004, 0.5)):
        now[0] = t
        exposure.put(Technique(factor))
        worker.step()
    recorded = []
    while not events.empty():
        recorded.append(events.get().event)
    on = next(e for e in recorded if e.kind == "fluoro_on")
    off = next(e for e in recorded if e.kind == "fluoro_off")
    assert on.t_monotonic == 1.0 and off.t_monotonic == 3.0
    assert off.fluoro_time_s == pytest.approx(2.0, abs=1e-12)
    assert console.exposure_factor == 0.5
