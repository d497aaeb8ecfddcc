"""The one event every console input source yields: a key or pedal going down or up.

A keypad (evdev or HID), a serial foot pedal and a scripted timeline all produce
`InputEvent`s through the same small `InputDevice` interface, so the console, the demo and
the tests run one code path whatever the hardware.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol


@dataclass(frozen=True)
class InputEvent:
    """A key or pedal transition.

    t_monotonic: when it happened, on the monotonic clock of whoever polls (s).
    source: "keypad", "pedal" or "scripted".
    key: an evdev key name ("KEY_KPENTER"), a HID usage ("hid:0x58"), "pedal", or (scripted
         files only) an action name such as "zoom_2".
    pressed: True on press, False on release.
    """

    t_monotonic: float
    source: str
    key: str
    pressed: bool


class InputDevice(Protocol):
    """What the input worker polls. `state` is "ok", "unplugged" or "none" (nothing configured)."""

    state: str

    def fileno(self) -> int: ...

    def poll(self, now: float) -> list[InputEvent]: ...

    def close(self) -> None: ...


class DeviceUnavailable(OSError):
    """A configured input device cannot be opened (absent, unplugged, no permission)."""


class NoInput:
    """Stands in where a profile says `source: none`: never yields, never fails."""

    state = "none"

    def fileno(self) -> int:
        return -1

    def poll(self, now: float) -> list[InputEvent]:
        return []

    def close(self) -> None:
        pass
