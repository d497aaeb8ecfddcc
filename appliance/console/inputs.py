"""Open the console's input devices as the appliance profile names them.

`devices.keypad.source`: 'none', 'scripted' (with `script`), an evdev path, udev symlink,
'name:TEXT' or 'VVVV:PPPP', or 'hid:VVVV:PPPP' for hidapi keypads. `devices.pedal.source`:
'none', 'scripted' (its events come from the keypad's script) or a serial port. A device
that is missing at start is not an error: it reports "unplugged" and attaches when it
appears; a script that cannot be read is one (a FluorosimError naming file and line).
"""

from __future__ import annotations

from drivers.hid_keypad import HidKeypad, parse_spec
from drivers.input_event import DeviceState, NoInput
from drivers.keypad import EvdevKeypad
from drivers.pedal import SerialPedal
from drivers.scripted_input import ScriptedInput, ScriptProblem

from ..config.loading import ApplianceConfig
from ..errors import FluorosimError
from .keys import action_for, typed_by_badge_reader


def known_keys(config: ApplianceConfig):
    """Whether a key name in a script means something to this console's keymap."""
    return lambda name: action_for(config.keymap, name) is not None or typed_by_badge_reader(name)


def open_keypad(config: ApplianceConfig, now: float):
    keypad = config.appliance.devices.keypad
    source = keypad.source
    if source == "none":
        return NoInput()
    if source == "scripted":
        if keypad.script is None:   # the profile's loader refuses this; a hand-built config may not
            raise FluorosimError("devices.keypad.script is required when devices.keypad.source is 'scripted'")
        try:
            return ScriptedInput(config.resolve(keypad.script), t0=now, known=known_keys(config))
        except ScriptProblem as e:
            raise FluorosimError(str(e)) from None
    if source.startswith("hid:"):
        try:
            parse_spec(source)
        except ValueError as e:
            raise FluorosimError(f"{config.path}: devices.keypad.source: {e}") from None
        return HidKeypad(source, now=now)
    return EvdevKeypad(source, grab=keypad.grab, key_names=frozenset(config.keymap.keys), now=now)


def open_pedal(config: ApplianceConfig, now: float):
    pedal = config.appliance.devices.pedal
    if pedal.source in ("none", "scripted"):
        return NoInput()
    return SerialPedal(pedal.source, baud=pedal.baud, press_line=pedal.press_line, release_line=pedal.release_line,
                       heartbeat_line=pedal.heartbeat_line, silence_timeout_s=pedal.silence_timeout_s, now=now)


class BadgeReader(EvdevKeypad):
    """A badge or barcode reader that types like a keyboard: only characters, Shift and Enter pass."""

    source = "badge"


def open_badge_reader(config: ApplianceConfig, now: float):
    """`teaching.badge_reader` of the appliance profile (a NoInput when it names none)."""
    from ..teaching.live import BADGE_KEYS

    source = config.appliance.teaching.badge_reader
    if source is None:
        return NoInput()
    return BadgeReader(source, grab=True, key_names=BADGE_KEYS, now=now)


def open_inputs(config: ApplianceConfig, now: float) -> list:
    """The keypad and pedal (either may be a NoInput), ready to poll with the console's clock."""
    return [open_keypad(config, now), open_pedal(config, now)]


def problems(devices) -> list[str]:
    """One line per configured device that is not working now (unplugged, silent), for the screen."""
    lines = []
    for device in devices:
        if getattr(device, "state", DeviceState.NONE) not in (DeviceState.OK, DeviceState.NONE):
            lines.append(getattr(device, "problem", "") or f"{getattr(device, 'source', 'input')} unplugged")
    return lines
