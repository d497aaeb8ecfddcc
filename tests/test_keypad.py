"""Keypads: evdev through uinput where the kernel has it, HID report parsing, the scripted driver."""

import os
import time

import pytest
from evdev import ecodes

from drivers.hid_keypad import HidKeypad, parse_spec, usage_key, usages_down
from drivers.keypad import EvdevKeypad, key_name
from drivers.scripted_input import ScriptedInput, ScriptProblem, parse_script


@pytest.mark.skipif(not os.path.exists("/dev/uinput"), reason="/dev/uinput does not exist on this machine (no uinput module)")
def test_evdev_keypad_through_uinput():
    from evdev import UInput
    keys = [ecodes.KEY_KPENTER, ecodes.KEY_KP1]
    with UInput({ecodes.EV_KEY: keys}, name="fluorosim test keypad") as ui:
        time.sleep(0.2)
        pad = EvdevKeypad("name:fluorosim test keypad", grab=True)
        assert pad.state == "ok"
        ui.write(ecodes.EV_KEY, ecodes.KEY_KPENTER, 1)
        ui.syn()
        ui.write(ecodes.EV_KEY, ecodes.KEY_KPENTER, 2)   # auto-repeat: dropped
        ui.syn()
        ui.write(ecodes.EV_KEY, ecodes.KEY_KPENTER, 0)
        ui.syn()
        time.sleep(0.05)
        evs = pad.poll(1.0)
        assert [(e.key, e.pressed) for e in evs] == [("KEY_KPENTER", True), ("KEY_KPENTER", False)]
        ui.write(ecodes.EV_KEY, ecodes.KEY_KP1, 1)
        ui.syn()
        time.sleep(0.05)
        assert pad.poll(2.0)[0].key == "KEY_KP1"
    # The device is gone: held keys are released, the pad says it is unplugged.
    evs = pad.poll(3.0)
    assert [(e.key, e.pressed) for e in evs] == [("KEY_KP1", False)] and pad.state == "unplugged"
    pad.close()


def test_evdev_keypad_absent_device_reports_unplugged():
    pad = EvdevKeypad("/dev/input/fluorosim-no-such-keypad")
    assert pad.state == "unplugged" and "does not exist" in pad.problem and pad.poll(0.0) == []
    assert EvdevKeypad("name:no keypad has this name").state == "unplugged"
    assert EvdevKeypad("ffff:fffe").state == "unplugged"


def test_key_names_prefer_the_keymaps_alias():
    assert key_name(ecodes.KEY_KPENTER) == "KEY_KPENTER"
    assert key_name(ecodes.KEY_MUTE) == "KEY_MUTE"
    assert key_name(ecodes.BTN_0) == "BTN_0"
    assert key_name(ecodes.BTN_0, frozenset({"BTN_MISC"})) == "BTN_MISC"


def test_hid_boot_reports_become_press_and_release():
    # Boot keyboard report: modifiers, reserved, six usages. Keypad Enter is 0x58, Keypad 1 is 0x59.
    assert usages_down([0, 0, 0x58, 0, 0, 0, 0, 0]) == {0x58}
    assert usages_down([0, 0, 0x58, 0x59, 0, 0, 0, 0]) == {0x58, 0x59}
    assert usages_down([1, 0, 0, 0, 0, 0, 0, 0]) == set()
    assert usages_down([2, 0, 0, 0x58, 0, 0, 0, 0, 0], report_id=True) == {0x58}
    assert usage_key(0x58) == "hid:0x58"
    assert parse_spec("hid:16c0:05df") == (0x16C0, 0x05DF)
    with pytest.raises(ValueError, match="hid:VVVV:PPPP"):
        parse_spec("16c0:05df")


def test_hid_keypad_absent_device_reports_unplugged():
    pad = HidKeypad("hid:ffff:fffe")
    assert pad.state == "unplugged" and "not found" in pad.problem and pad.poll(0.0) == []
    # Transitions from successive reports, through the driver's own bookkeeping.
    assert [(e.key, e.pressed) for e in pad._transitions(1.0, {0x58})] == [("hid:0x58", True)]
    assert [(e.key, e.pressed) for e in pad._transitions(1.1, {0x58, 0x59})] == [("hid:0x59", True)]
    assert [(e.key, e.pressed) for e in pad._transitions(1.2, set())] == [("hid:0x58", False), ("hid:0x59", False)]


def test_scripted_input_yields_events_at_their_scripted_times(tmp_path):
    path = tmp_path / "s.jsonl"
    path.write_text('# a comment\n\n{"t": 1.0, "hold": "pedal", "for_s": 2.5}\n'
                    '{"t": 1.5, "tap": "KEY_KP2"}\n{"t": 2.0, "key": "zoom_3", "pressed": true}\n'
                    '{"t": 2.0, "tap": "save", "tap_s": 0.5}\n')
    s = ScriptedInput(path, t0=100.0)
    assert s.poll(100.9) == []
    evs = s.poll(102.05)
    assert [(e.t_monotonic, e.key, e.pressed) for e in evs] == [
        (101.0, "pedal", True), (101.5, "KEY_KP2", True), (101.6, "KEY_KP2", False),
        (102.0, "zoom_3", True), (102.0, "save", True)]
    evs = s.poll(200.0)
    assert [(e.t_monotonic, e.key, e.pressed) for e in evs] == [(102.5, "save", False), (103.5, "pedal", False)]
    assert s.finished and s.duration_s == 3.5 and all(e.source == "scripted" for e in evs)


@pytest.mark.parametrize("line, message", [
    ('{"t": 1, "tap": "x"', "not valid JSON"),
    ('[1, 2]', "JSON object"),
    ('{"t": -1, "tap": "x"}', "must not be negative"),
    ('{"t": "soon", "tap": "x"}', "must be a number"),
    ('{"t": 1, "tap": "x", "hold": "y"}', "exactly one"),
    ('{"t": 1, "key": "x"}', "'pressed' must be true or false"),
    ('{"t": 1, "hold": "pedal"}', "'for_s' must be a number"),
    ('{"t": 1, "tap": "x", "colour": 1}', "unknown field"),
])
def test_script_errors_name_file_and_line(line, message):
    with pytest.raises(ScriptProblem, match=message) as e:
        parse_script('{"t": 0, "tap": "save"}\n' + line, "demo.jsonl")
    assert str(e.value).startswith("demo.jsonl:2:")
