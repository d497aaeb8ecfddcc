"""Keypads that are not evdev keyboards, read as raw HID reports through hidapi.

The profile names the device as `hid:VVVV:PPPP` (USB vendor:product, hex). Reports are the
boot keyboard layout: a modifier byte, a reserved byte, then up to six usage ids of the keys
now down (keyboard page 0x07); a key appears in one report and is gone from a later one.
Events name the usage as `hid:0x58`, which the keymap's `hid_usages` maps to actions.
"""

from __future__ import annotations

import re

import hid

from .input_event import HotplugInput, InputEvent

#: Largest report read at once (bytes); boot keyboards send 8.
REPORT_SIZE = 64

_SPEC = re.compile(r"^hid:([0-9a-fA-F]{4}):([0-9a-fA-F]{4})$")


def parse_spec(spec: str) -> tuple[int, int]:
    """(vendor, product) from 'hid:VVVV:PPPP', or ValueError saying what is expected."""
    m = _SPEC.match(spec)
    if not m:
        raise ValueError(f"'{spec}' is not a HID keypad; write hid:VVVV:PPPP with the USB ids in hex (see lsusb)")
    return int(m.group(1), 16), int(m.group(2), 16)


def usages_down(report: list[int] | bytes, report_id: bool = False) -> set[int]:
    """Usage ids held in one boot-keyboard report (0 = none, 1 = rollover error, both ignored)."""
    data = list(report)[1:] if report_id else list(report)
    return {u for u in data[2:8] if u > 1}


def usage_key(usage: int) -> str:
    return f"hid:0x{usage:02x}"


class HidKeypad(HotplugInput["hid.device"]):
    source = "keypad"

    def __init__(self, spec: str, *, report_id: bool = False, now: float = 0.0):
        self.spec = spec
        self.vendor, self.product = parse_spec(spec)
        self.report_id = report_id
        super().__init__(now)

    def _attach(self, now: float) -> hid.device | None:
        dev = hid.device()
        try:
            dev.open(self.vendor, self.product)
            dev.set_nonblocking(1)
        except OSError as e:
            self.problem = f"keypad {self.spec}: not found ({e}); plug it in or check the USB ids"
            return None
        return dev

    def _detach(self, dev: hid.device) -> None:
        try:
            dev.close()
        except (OSError, ValueError):
            pass

    def fileno(self) -> int:
        return -1  # hidapi hides its descriptor; the input worker polls every frame

    def _transitions(self, now: float, usages: set[int]) -> list[InputEvent]:
        """Releases, then presses, from the usages held in a report and those held before it."""
        down = {usage_key(u) for u in usages}
        events = [InputEvent(now, self.source, key, False) for key in sorted(self.held - down)]
        events += [InputEvent(now, self.source, key, True) for key in sorted(down - self.held)]
        self.held = down
        return events

    def _read(self, dev: hid.device, now: float) -> list[InputEvent]:
        events = []
        try:
            while True:
                report = dev.read(REPORT_SIZE)
                if not report:
                    break
                events += self._transitions(now, usages_down(report, self.report_id))
        except (OSError, ValueError) as e:
            events += self._lost(now, f"keypad {self.spec} unplugged ({e})")
        return events
