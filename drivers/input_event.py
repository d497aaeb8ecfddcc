"""The one event every console input source yields: a key or pedal going down or up.

A keypad (evdev or HID), a serial foot pedal and a scripted timeline all produce
`InputEvent`s through the same small `InputDevice` interface, so the console, the demo and
the tests run one code path whatever the hardware.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Generic, Protocol, TypeVar

#: How often an unplugged keypad or pedal is looked for again (s); opening one is cheap.
REOPEN_INTERVAL_S = 1.0


class DeviceState(StrEnum):
    """What an input device reports in `state` (and the health checks and status lines show)."""

    OK = "ok"
    UNPLUGGED = "unplugged"
    NONE = "none"             # nothing configured


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
    """What the input worker polls. `state` is a DeviceState: ok, unplugged or none (nothing configured)."""

    state: str

    def fileno(self) -> int: ...

    def poll(self, now: float) -> list[InputEvent]: ...

    def close(self) -> None: ...


class DeviceUnavailable(OSError):
    """A configured input device cannot be opened (absent, unplugged, no permission)."""


class NoInput:
    """Stands in where a profile says `source: none`: never yields, never fails."""

    state = DeviceState.NONE

    def fileno(self) -> int:
        return -1

    def poll(self, now: float) -> list[InputEvent]:
        return []

    def close(self) -> None:
        pass


H = TypeVar("H")


class HotplugInput(Generic[H]):
    """An input device that may be unplugged and plugged back: while it is away it reports
    `state` unplugged with `problem` saying why, and is looked for again every
    REOPEN_INTERVAL_S; when it is lost, every key it held is released (fail safe: a held
    fluoro key or pedal cannot stay down).

    A driver implements `_attach` (open the device: its handle, or None with `problem` set),
    `_detach` (close a handle, ignoring errors) and `_read` (events since the last poll; it
    returns `self._lost(...)` when the device has gone), and keeps `held` current.
    """

    source = "input"

    def __init__(self, now: float):
        self.state: str = DeviceState.UNPLUGGED
        self.problem = ""
        #: Keys (or "pedal") down now, released if the device is lost.
        self.held: set[str] = set()
        self._handle: H | None = None
        self._last_try: float | None = None
        self._try_attach(now)

    def _attach(self, now: float) -> H | None:
        raise NotImplementedError

    def _detach(self, handle: H) -> None:
        raise NotImplementedError

    def _read(self, handle: H, now: float) -> list[InputEvent]:
        raise NotImplementedError

    def _try_attach(self, now: float) -> None:
        self._last_try = now
        self._handle = self._attach(now)
        if self._handle is not None:
            self.state, self.problem = DeviceState.OK, ""
        else:
            self.state = DeviceState.UNPLUGGED

    def poll(self, now: float) -> list[InputEvent]:
        """Events since the last poll, stamped `now`; an unplugged device is looked for once a REOPEN_INTERVAL_S."""
        if self._handle is None:
            if self._last_try is None or now - self._last_try >= REOPEN_INTERVAL_S:
                self._try_attach(now)
            if self._handle is None:
                return []
        return self._read(self._handle, now)

    def _lost(self, now: float, why: str) -> list[InputEvent]:
        """The device went away: close it, say why, release what it held."""
        if self._handle is not None:
            self._detach(self._handle)
            self._handle = None
        self.state, self.problem = DeviceState.UNPLUGGED, why
        return self._release_all(now)

    def _release_all(self, now: float) -> list[InputEvent]:
        released = [InputEvent(now, self.source, key, False) for key in sorted(self.held)]
        self.held.clear()
        return released

    def close(self) -> None:
        if self._handle is not None:
            self._detach(self._handle)
            self._handle = None
        self.state = DeviceState.UNPLUGGED
