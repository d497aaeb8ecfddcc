"""Keypads that are not evdev keyboards, read as raw HID reports through hidapi.

The profile names the device as `hid:VVVV:PPPP` (USB vendor:product, hex). Reports are the
boot keyboard layout: a modifier byte, a reserved byte, then up to six usage ids of the keys
now down (keyboard page 0x07); a key appears in one report and is gone from a later one.
Events name the usage as `hid:0x58`, which the keymap's `hid_usages` maps to actions.
"""

from __future__ import annotations

import re

import hid

from .input_event import InputEvent

#: How often an unplugged keypad is looked for again (s).
REOPEN_INTERVAL_S = 1.0
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


class HidKeypad:
    source = "keypad"

    def __init__(self, spec: str, *, report_id: bool = False, now: float = 0.0):
        self.spec = spec
        self.vendor, self.product = parse_spec(spec)
        self.report_id = report_id
        self.held: set[int] = set()
        self.state = "unplugged"
        self.problem = ""
        self._device = None
        self._last_try: float | None = None
        self._open(now)

    def _open(self, now: float) -> None:
        self._last_try = now
        dev = hid.device()
        try:
            dev.open(self.vendor, self.product)
            dev.set_nonblocking(1)
        except (OSError, IOError) as e:
            self.state, self.problem = "unplugged", f"keypad {self.spec}: not found ({e}); plug it in or check the USB ids"
            return
        self._device = dev
        self.state, self.problem = "ok", ""

    def fileno(self) -> int:
        return -1  # hidapi hides its descriptor; the input worker polls every frame

    def _transitions(self, now: float, down: set[int]) -> list[InputEvent]:
        events = [InputEvent(now, self.source, usage_key(u), False) for u in sorted(self.held - down)]
        events += [InputEvent(now, self.source, usage_key(u), True) for u in sorted(down - self.held)]
        self.held = down
        return events

    def poll(self, now: float) -> list[InputEvent]:
        if self._device is None:
            if self._last_try is None or now - self._last_try >= REOPEN_INTERVAL_S:
                self._open(now)
            if self._device is None:
                return []
        events = []
        try:
            while True:
                report = self._device.read(REPORT_SIZE)
                if not report:
                    break
                events += self._transitions(now, usages_down(report, self.report_id))
        except (OSError, IOError, ValueError) as e:
            try:
                self._device.close()
            except (OSError, IOError, ValueError):
                pass
            self._device = None
            self.state, self.problem = "unplugged", f"keypad {self.spec} unplugged ({e})"
            events += self._transitions(now, set())
        return events

    def close(self) -> None:
        if self._device is not None:
            self._device.close()
            self._device = None
        self.state = "unplugged"
