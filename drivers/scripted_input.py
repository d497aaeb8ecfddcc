"""Scripted console input: a JSONL timeline of key and pedal events, for the demo and tests.

The file holds one JSON object per line; blank lines and lines starting with `#` are
ignored. Times are seconds from the start of the script (on the console's clock, which the
demo may run faster than the wall clock). Three kinds of line:

    {"t": 2.0, "key": "pedal", "pressed": true}       one transition
    {"t": 2.0, "tap": "KEY_KP2"}                      press at t, release tap_s later (default 0.1 s)
    {"t": 2.0, "hold": "pedal", "for_s": 30.0}        press at t, release at t + for_s

`key`, `tap` and `hold` name an evdev key (`KEY_KP1`), a HID usage (`hid:0x58`), `pedal`,
or directly a console action (`zoom_2`, `alarm_reset`, ...). An optional `"tap_s"` sets
the press length of a tap (s). Events come out in time order; ties keep file order.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

from .input_event import DeviceState, InputEvent
from .jsonl import json_lines


class ScriptProblem(ValueError):
    """A line of a script that cannot be read; the message names file and line."""


#: Latest time a script may name: one day (s). A session runs for hours; a larger number
#: is a typo that would hold the pedal down, or never arrive.
MAX_SCRIPT_TIME_S = 86_400.0
#: A script is a few kilobytes; a larger file is the wrong file (bytes).
MAX_SCRIPT_BYTES = 4_000_000


def _number(obj: dict, field: str, where: str, default: float | None = None) -> float:
    value = obj.get(field, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ScriptProblem(f"{where}: '{field}' must be a number of seconds (got {value!r})")
    if not math.isfinite(value) or value < 0 or value > MAX_SCRIPT_TIME_S:
        raise ScriptProblem(f"{where}: '{field}' must be between 0 and {MAX_SCRIPT_TIME_S:g} s (one day; got {value:g})")
    return float(value)


def _name(obj: dict, field: str, where: str) -> str:
    value = obj[field]
    if not isinstance(value, str) or not value:
        raise ScriptProblem(f"{where}: '{field}' must name a key, 'pedal' or an action (got {value!r})")
    return value


def parse_script(text: str, display: str = "<script>",
                 known: Callable[[str], bool] | None = None) -> list[tuple[float, str, bool]]:
    """(t_s, key, pressed) of every transition, in time order.

    `known(name)` says whether a key name means something on this console (the keymap);
    a name it refuses is an error rather than a key press that silently does nothing.
    """
    out: list[tuple[float, int, str, bool]] = []
    for where, obj in json_lines(text.splitlines(), display, ScriptProblem):
        if not isinstance(obj, dict):
            raise ScriptProblem(f"{where}: each line must be a JSON object such as {{\"t\": 1.0, \"tap\": \"zoom_2\"}}")
        kinds = [k for k in ("key", "tap", "hold") if k in obj]
        if len(kinds) != 1:
            raise ScriptProblem(f"{where}: give exactly one of 'key', 'tap' or 'hold'")
        allowed = {"t", kinds[0], {"key": "pressed", "tap": "tap_s", "hold": "for_s"}[kinds[0]]}
        extra = sorted(set(obj) - allowed)
        if extra:
            raise ScriptProblem(f"{where}: unknown field(s) {', '.join(extra)}; allowed: {', '.join(sorted(allowed))}")
        t = _number(obj, "t", where)
        kind = kinds[0]
        name = _name(obj, kind, where)
        if known is not None and not known(name):
            raise ScriptProblem(f"{where}: '{name}' is no key of the keymap, 'pedal' or a console action; "
                                "check its spelling against the keymap profile")
        if kind == "key":
            pressed = obj.get("pressed")
            if not isinstance(pressed, bool):
                raise ScriptProblem(f"{where}: 'pressed' must be true or false")
            out.append((t, len(out), name, pressed))
        else:
            length = _number(obj, "tap_s", where, 0.1) if kind == "tap" else _number(obj, "for_s", where)
            if length <= 0:
                raise ScriptProblem(f"{where}: the press must last longer than 0 s")
            out.append((t, len(out), name, True))
            out.append((t + length, len(out), name, False))
    out.sort(key=lambda e: (e[0], e[1]))
    return [(t, key, pressed) for t, _, key, pressed in out]


def read_script(path: Path) -> str:
    """The text of a script file, or ScriptProblem naming the file and what is wrong with it."""
    try:
        if path.stat().st_size > MAX_SCRIPT_BYTES:
            raise ScriptProblem(f"{path}: is larger than {MAX_SCRIPT_BYTES // 1_000_000} MB; is this the input script?")
        raw = path.read_bytes()
    except OSError as e:
        raise ScriptProblem(f"{path}: cannot read the input script ({e.strerror or e})") from None
    if b"\x00" in raw:
        raise ScriptProblem(f"{path}: is a binary file, not a JSONL input script")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ScriptProblem(f"{path}: is not UTF-8 text (bad byte at offset {e.start}); save it as UTF-8") from None


class ScriptedInput:
    """Replays a script against the console's clock: `poll(now)` yields what is due by `now`.

    Each event carries its exact scripted time (t0 + t), not the time it was polled, so a
    console driven at any frame rate sees the same timeline.
    """

    source = "scripted"

    def __init__(self, path: str | Path, t0: float = 0.0, known: Callable[[str], bool] | None = None):
        self.path = Path(path)
        self._events = parse_script(read_script(self.path), str(self.path), known)
        self.t0 = t0
        self._next = 0
        self.state = DeviceState.OK

    @property
    def duration_s(self) -> float:
        """Time of the last event (s from the start of the script)."""
        return self._events[-1][0] if self._events else 0.0

    @property
    def finished(self) -> bool:
        return self._next >= len(self._events)

    def fileno(self) -> int:
        return -1

    def poll(self, now: float) -> list[InputEvent]:
        due = []
        while self._next < len(self._events) and self.t0 + self._events[self._next][0] <= now:
            t, key, pressed = self._events[self._next]
            due.append(InputEvent(self.t0 + t, self.source, key, pressed))
            self._next += 1
        return due

    def close(self) -> None:
        self._next = len(self._events)
