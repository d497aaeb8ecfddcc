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

import json
from pathlib import Path

from .input_event import DeviceState, InputEvent


class ScriptProblem(ValueError):
    """A line of a script that cannot be read; the message names file and line."""


def _number(obj: dict, field: str, where: str, default: float | None = None) -> float:
    value = obj.get(field, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ScriptProblem(f"{where}: '{field}' must be a number of seconds (got {value!r})")
    if value < 0:
        raise ScriptProblem(f"{where}: '{field}' must not be negative (got {value})")
    return float(value)


def _name(obj: dict, field: str, where: str) -> str:
    value = obj[field]
    if not isinstance(value, str) or not value:
        raise ScriptProblem(f"{where}: '{field}' must name a key, 'pedal' or an action (got {value!r})")
    return value


def parse_script(text: str, display: str = "<script>") -> list[tuple[float, str, bool]]:
    """(t_s, key, pressed) of every transition, in time order."""
    out: list[tuple[float, int, str, bool]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{display}:{number}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as e:
            raise ScriptProblem(f"{where}: not valid JSON ({e.msg})") from None
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


class ScriptedInput:
    """Replays a script against the console's clock: `poll(now)` yields what is due by `now`.

    Each event carries its exact scripted time (t0 + t), not the time it was polled, so a
    console driven at any frame rate sees the same timeline.
    """

    source = "scripted"

    def __init__(self, path: str | Path, t0: float = 0.0):
        self.path = Path(path)
        try:
            text = self.path.read_text(encoding="utf-8")
        except OSError as e:
            raise ScriptProblem(f"{self.path}: cannot read the input script ({e.strerror or e})") from None
        self._events = parse_script(text, str(self.path))
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
