"""USB keypad read through evdev, found by path, udev symlink, name or vendor:product.

`source` in the appliance profile is one of:
  /dev/input/event3, /dev/fluorosim/keypad, /dev/input/by-id/...   a path (udev symlinks resolve)
  name:TEXT                                                        first device whose name contains TEXT
  VVVV:PPPP                                                        USB vendor:product (hex)

The device is grabbed exclusively so key presses do not also reach a text console. When it
is unplugged every held key is released (fail safe: a held fluoro key cannot stay down) and
the device is looked for again once a second until it returns.
"""

from __future__ import annotations

import errno
import os
import re

import evdev
from evdev import ecodes

from .input_event import DeviceUnavailable, HotplugInput, InputEvent

_VENDOR_PRODUCT = re.compile(r"^([0-9a-fA-F]{4}):([0-9a-fA-F]{4})$")


def key_name(code: int, prefer: frozenset[str] = frozenset()) -> str:
    """The evdev name of a key code; among aliases, one the keymap uses, else the most specific."""
    names = ecodes.keys.get(code, f"KEY_{code}")
    if isinstance(names, str):
        return names
    for n in names:
        if n in prefer:
            return n
    generic = ("KEY_MIN_INTERESTING", "BTN_MISC", "BTN_MOUSE", "BTN_JOYSTICK", "BTN_GAMEPAD", "BTN_DIGI")
    specific = [n for n in names if n not in generic]
    return (specific or list(names))[0]


def find_device(source: str) -> evdev.InputDevice:
    """Open the evdev device `source` names, or raise DeviceUnavailable saying why."""
    if source.startswith("name:"):
        wanted = source[5:]
        for path in evdev.list_devices():
            try:
                dev = evdev.InputDevice(path)
            except OSError:
                continue
            if wanted.lower() in dev.name.lower():
                return dev
            dev.close()
        raise DeviceUnavailable(errno.ENODEV, f"no input device whose name contains '{wanted}'")
    m = _VENDOR_PRODUCT.match(source)
    if m:
        vendor, product = int(m.group(1), 16), int(m.group(2), 16)
        for path in evdev.list_devices():
            try:
                dev = evdev.InputDevice(path)
            except OSError:
                continue
            if dev.info.vendor == vendor and dev.info.product == product and ecodes.EV_KEY in dev.capabilities():
                return dev
            dev.close()
        raise DeviceUnavailable(errno.ENODEV, f"no input device with USB id {source}")
    if not os.path.exists(source):
        raise DeviceUnavailable(errno.ENOENT, f"{source} does not exist")
    try:
        return evdev.InputDevice(source)
    except OSError as e:
        raise DeviceUnavailable(e.errno or errno.EIO, f"{source}: {e.strerror or e}") from None


class EvdevKeypad(HotplugInput[evdev.InputDevice]):
    source = "keypad"

    def __init__(self, source: str, *, grab: bool = True, key_names: frozenset[str] = frozenset(), now: float = 0.0):
        self.spec = source
        self.grab = grab
        self.key_names = frozenset(key_names)
        super().__init__(now)

    def _attach(self, now: float) -> evdev.InputDevice | None:
        try:
            dev = find_device(self.spec)
        except DeviceUnavailable as e:
            self.problem = f"keypad {self.spec}: {e.strerror}; plug it in"
            return None
        if self.grab:
            try:
                dev.grab()
            except OSError as e:
                dev.close()
                self.problem = (f"keypad {self.spec}: cannot take it exclusively ({e.strerror or e}); "
                                f"is another program using it?")
                return None
        return dev

    def _detach(self, dev: evdev.InputDevice) -> None:
        try:
            if self.grab:
                dev.ungrab()
        except OSError:
            pass   # already gone with the device
        try:
            dev.close()
        except OSError:
            pass

    @property
    def name(self) -> str:
        return self._handle.name if self._handle is not None else ""

    def fileno(self) -> int:
        return self._handle.fd if self._handle is not None else -1

    def _read(self, dev: evdev.InputDevice, now: float) -> list[InputEvent]:
        """Key presses and releases since the last poll, stamped `now`; auto-repeats are dropped."""
        events = []
        try:
            while True:
                ev = dev.read_one()
                if ev is None:
                    break
                if ev.type != ecodes.EV_KEY or ev.value == 2:
                    continue
                name = key_name(ev.code, self.key_names)
                pressed = ev.value == 1
                if pressed:
                    self.held.add(name)
                else:
                    self.held.discard(name)
                events.append(InputEvent(now, self.source, name, pressed))
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                return events
            return events + self._lost(now, f"keypad {self.spec} unplugged ({e.strerror or e})")
        return events
