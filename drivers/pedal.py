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

from .input_event import DeviceState, HotplugInput, InputEvent

#: A line longer than this (bytes) is a babbling device, not the pedal: it is dropped to keep memory bounded.
MAX_LINE_BYTES = 4096


class SerialPedal(HotplugInput[serial.Serial]):
    source = "pedal"

    def __init__(self, port: str, *, baud: int = 9600, press_line: str = "DOWN", release_line: str = "UP",
                 heartbeat_line: str = "HB", silence_timeout_s: float = 0.5, now: float = 0.0):
        self.port = port
        self.baud = baud
        self.press_line = press_line
        self.release_line = release_line
        self.heartbeat_line = heartbeat_line
        self.silence_timeout_s = silence_timeout_s
        self._buffer = b""
        self._last_heard = now
        super().__init__(now)

    @property
    def pressed(self) -> bool:
        return "pedal" in self.held

    def _attach(self, now: float) -> serial.Serial | None:
        try:
            port = serial.Serial(self.port, self.baud, timeout=0)
        except (serial.SerialException, OSError) as e:
            self.problem = (f"{self.port}: cannot open the pedal ({getattr(e, 'strerror', None) or e}); "
                            "plug it in, or check the port name and its permissions")
            return None
        self._buffer = b""
        self._last_heard = now
        return port

    def _detach(self, port: serial.Serial) -> None:
        try:
            port.close()
        except (serial.SerialException, OSError):
            pass

    def fileno(self) -> int:
        return self._handle.fileno() if self._handle is not None else -1

    def _read(self, port: serial.Serial, now: float) -> list[InputEvent]:
        """Lines that arrived since the last poll as events stamped `now`; a silent pedal is released."""
        try:
            waiting = port.in_waiting
            data = port.read(waiting) if waiting else b""
        except (serial.SerialException, OSError) as e:
            return self._lost(now, f"{self.port}: pedal disconnected ({getattr(e, 'strerror', None) or e})")
        events: list[InputEvent] = []
        if data:
            self._buffer += data
            *lines, self._buffer = self._buffer.split(b"\n")
            for raw in lines:
                line = raw.rstrip(b"\r").decode("ascii", errors="replace").strip()
                self._last_heard = now
                if self.state != DeviceState.OK:
                    self.state, self.problem = DeviceState.OK, ""
                if line == self.press_line and not self.pressed:
                    self.held.add("pedal")
                    events.append(InputEvent(now, self.source, "pedal", True))
                elif line == self.release_line:
                    events.extend(self._release_all(now))
            if len(self._buffer) > MAX_LINE_BYTES:
                self._buffer = b""
        elif not os.path.exists(self.port):
            return self._lost(now, f"{self.port}: pedal unplugged")
        if now - self._last_heard > self.silence_timeout_s:
            if self.state == DeviceState.OK:
                self.state = DeviceState.UNPLUGGED
                self.problem = (f"{self.port}: pedal silent for more than {self.silence_timeout_s} s; "
                                f"counted as released")
            events.extend(self._release_all(now))
        return events
