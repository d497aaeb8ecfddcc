"""Tell systemd how the service is doing: READY=1, STATUS=, WATCHDOG=1, RELOADING=1, STOPPING=1.

Messages go through systemd-python's `sd_notify` wrapper; where that module is missing
(a bare virtualenv, a non-systemd machine) the same datagram is sent on a plain AF_UNIX
socket, which is all the protocol is. Without NOTIFY_SOCKET (run by hand) nothing is sent.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)


def _systemd_sender() -> Callable[[str], bool] | None:
    try:
        from systemd import daemon  # type: ignore[attr-defined]  # a C extension mypy cannot see into
    except ImportError:
        return None
    return lambda message: bool(daemon.notify(message))


def _socket_address(path: str) -> str | bytes:
    # A leading '@' names a socket in the abstract namespace (sd_notify(3)).
    return b"\0" + path[1:].encode() if path.startswith("@") else path


class Notifier:
    """The service's side of the sd_notify protocol.

    `watchdog_interval_s` is half of WATCHDOG_USEC, the rate systemd.service(5) asks for,
    or None when systemd did not enable the watchdog for this process.
    """

    def __init__(self, environ: Mapping[str, str] | None = None, *, use_systemd: bool = True):
        env = os.environ if environ is None else environ
        self.socket_path = env.get("NOTIFY_SOCKET") or None
        self.watchdog_interval_s: float | None = None
        usec, pid = env.get("WATCHDOG_USEC"), env.get("WATCHDOG_PID")
        if usec and (not pid or pid == str(os.getpid())):
            try:
                self.watchdog_interval_s = int(usec) / 1e6 / 2
            except ValueError:
                log.warning("WATCHDOG_USEC=%r is not a number of microseconds; watchdog pings disabled", usec)
        self._systemd = _systemd_sender() if use_systemd else None
        # systemd-python reads NOTIFY_SOCKET from the process environment; an explicit
        # environment (tests, a child told where to report) goes over the plain socket.
        if environ is not None and environ is not os.environ:
            self._systemd = None
        self._sock: socket.socket | None = None
        self.sent: int = 0

    @property
    def enabled(self) -> bool:
        return self.socket_path is not None

    @property
    def backend(self) -> str:
        return "systemd-python" if self._systemd else "socket"

    def send(self, message: str) -> bool:
        """Send one message (newline-separated KEY=VALUE lines); False if it could not be delivered."""
        if not self.enabled:
            return False
        try:
            if self._systemd is not None:
                ok = self._systemd(message)
            else:
                ok = self._send_datagram(message)
        except OSError as e:
            log.warning("sd_notify to %s failed: %s", self.socket_path, e)
            return False
        if ok:
            self.sent += 1
        return ok

    def _send_datagram(self, message: str) -> bool:
        if self._sock is None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        if not self.socket_path:
            return False
        self._sock.sendto(message.encode(), _socket_address(self.socket_path))
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        # STATUS is one line; a newline would start another KEY=VALUE pair.
        return self.send("STATUS=" + " ".join(text.splitlines()))

    def watchdog(self) -> bool:
        return self.send("WATCHDOG=1")

    def reloading(self) -> bool:
        # Type=notify-reload wants the monotonic time beside RELOADING=1 (systemd >= 253).
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.send(f"RELOADING=1\nMONOTONIC_USEC={usec}")

    def stopping(self) -> bool:
        return self.send("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
