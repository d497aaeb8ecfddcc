"""A real NOTIFY_SOCKET for tests: a bound AF_UNIX datagram socket, read by a thread.

Every message systemd would receive is kept with the monotonic time it arrived, so tests
can check what was said and when (READY after the first frame, WATCHDOG=1 stopping).
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path


class NotifyListener:
    def __init__(self, path: Path):
        self.path = str(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.05)
        self.messages: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                self.messages.append((time.monotonic(), data.decode()))

    def lines(self) -> list[tuple[float, str]]:
        """Every KEY=VALUE line received, with its arrival time."""
        with self._lock:
            return [(t, line) for t, m in self.messages for line in m.split("\n")]

    def times_of(self, line: str) -> list[float]:
        return [t for t, l in self.lines() if l == line]

    def starting(self, prefix: str) -> list[str]:
        return [l for _, l in self.lines() if l.startswith(prefix)]

    def wait_for(self, line: str, timeout_s: float = 5.0) -> float | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            times = self.times_of(line)
            if times:
                return times[0]
            time.sleep(0.01)
        return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1)
        self.sock.close()
