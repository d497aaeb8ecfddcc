"""Foot pedal on a serial port, speaking a small line protocol set in the appliance profile.

The pedal sends one text line when pressed (`press_line`), one when released
(`release_line`) and `heartbeat_line` periodically while connected. Lines end in LF (a CR
before it is ignored). Fail safe: if no line at all arrives for `silence_timeout_s` while
the pedal is down, it counts as released, so a cut cable or a crashed pedal can never leave
the simulator stuck in fluoroscopy. A port that vanishes (USB unplugged) is reopened by
path when it comes back.
"""

from __future__ import annotations

import os

import serial

from .input_event import InputEvent

#: How often an unplugged port is looked for again (s); opening a port is cheap.
REOPEN_INTERVAL_S = 1.0


class SerialPedal:
    source = "pedal"

    def __init__(self, port: str, *, baud: int = 9600, press_line: str = "DOWN", release_line: str = "UP",
                 heartbeat_line: str = "HB", silence_timeout_s: float = 0.5, now: float = 0.0):
        self.port = port
        self.baud = baud
        self.press_line = press_line
        self.release_line = release_line
        self.heartbeat_line = heartbeat_line
        self.silence_timeout_s = silence_timeout_s
        self.pressed = False
        self.state = "unplugged"
        self.problem = f"{port}: not opened yet"
        self._serial: serial.Serial | None = None
        self._buffer = b""
        self._last_heard = now
        self._last_try = None
        self._open(now)

    def _open(self, now: float) -> None:
        self._last_try = now
        try:
            self._serial = serial.Serial(self.port, self.baud, timeout=0)
        except (serial.SerialException, OSError) as e:
            self._serial = None
            self.state = "unplugged"
            self.problem = (f"{self.port}: cannot open the pedal ({getattr(e, 'strerror', None) or e}); "
                            "plug it in, or check the port name and its permissions")
            return
        self._buffer = b""
        self._last_heard = now
        self.state = "ok"
        self.problem = ""

    def fileno(self) -> int:
        return self._serial.fileno() if self._serial is not None else -1

    def _lost(self, now: float, why: str) -> list[InputEvent]:
        if self._serial is not None:
            try:
                self._serial.close()
            except (serial.SerialException, OSError):
                pass
        self._serial = None
        self.state = "unplugged"
        self.problem = why
        return self._release(now)

    def _release(self, now: float) -> list[InputEvent]:
        if not self.pressed:
            return []
        self.pressed = False
        return [InputEvent(now, self.source, "pedal", False)]

    def poll(self, now: float) -> list[InputEvent]:
        """Lines that arrived since the last poll as events stamped `now`; a silent pedal is released."""
        if self._serial is None:
            if self._last_try is None or now - self._last_try >= REOPEN_INTERVAL_S:
                self._open(now)
            if self._serial is None:
                return []
        try:
            waiting = self._serial.in_waiting
            data = self._serial.read(waiting) if waiting else b""
        except (serial.SerialException, OSError) as e:
            return self._lost(now, f"{self.port}: pedal disconnected ({getattr(e, 'strerror', None) or e})")
        events: list[InputEvent] = []
        if data:
            self._buffer += data
            *lines, self._buffer = self._buffer.split(b"\n")
            for raw in lines:
                line = raw.rstrip(b"\r").decode("ascii", errors="replace").strip()
                self._last_heard = now
                if self.state != "ok":
                    self.state, self.problem = "ok", ""
                if line == self.press_line and not self.pressed:
                    self.pressed = True
                    events.append(InputEvent(now, self.source, "pedal", True))
                elif line == self.release_line:
                    events.extend(self._release(now))
            if len(self._buffer) > 4096:  # a babbling device: keep memory bounded
                self._buffer = b""
        elif not os.path.exists(self.port):
            return self._lost(now, f"{self.port}: pedal unplugged")
        if now - self._last_heard > self.silence_timeout_s:
            if self.state == "ok":
                self.state = "unplugged"
                self.problem = f"{self.port}: pedal silent for more than {self.silence_timeout_s} s; counted as released"
            events.extend(self._release(now))
        return events

    def close(self) -> None:
        if self._serial is not None:
            self._serial.close()
            self._serial = None
        self.state = "unplugged"
