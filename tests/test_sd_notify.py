"""sd_notify over a real NOTIFY_SOCKET datagram socket, through systemd-python and the plain-socket fallback."""

from __future__ import annotations

import os
import socket
import sys
import threading
import time

import pytest
from notify_listener import NotifyListener

from appliance.daemon.notify import Notifier
from appliance.daemon.supervisor import Supervisor
from appliance.daemon.worker import Worker


@pytest.fixture
def listener(tmp_path, monkeypatch):
    sock = NotifyListener(tmp_path / "notify.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", sock.path)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    yield sock
    sock.close()


@pytest.mark.parametrize("use_systemd", [True, False], ids=["systemd-python", "plain-socket"])
def test_each_message_arrives_on_the_socket(listener, use_systemd):
    n = Notifier(use_systemd=use_systemd)
    assert n.backend == ("systemd-python" if use_systemd else "socket")
    assert n.ready("first frame")
    assert n.status("12.0 fps; camera ok\nsecond line")
    assert n.watchdog()
    assert n.reloading()
    assert n.stopping()
    assert listener.wait_for("STOPPING=1") is not None
    got = [line for _, line in listener.lines()]
    mono = [line for line in got if line.startswith("MONOTONIC_USEC=")]
    assert got == ["READY=1", "STATUS=first frame", "STATUS=12.0 fps; camera ok second line", "WATCHDOG=1",
                   "RELOADING=1", mono[0], "STOPPING=1"]
    # MONOTONIC_USEC is CLOCK_MONOTONIC in microseconds, read independently here.
    now_us = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    assert 0 <= now_us - int(mono[0].split("=")[1]) < 5_000_000


def test_fallback_reaches_an_abstract_socket(monkeypatch):
    name = f"fluorosim-test-{os.getpid()}-{threading.get_ident()}"
    receiver = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    receiver.bind(b"\0" + name.encode())
    receiver.settimeout(2)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.backend == "socket"
        assert n.watchdog()
        assert receiver.recv(100) == b"WATCHDOG=1"
    finally:
        receiver.close()


def test_watchdog_interval_is_half_of_watchdog_usec():
    assert Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "3000000"}).watchdog_interval_s == pytest.approx(1.5)
    # WATCHDOG_PID names the process meant; another process's setting is not ours.
    assert Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "3000000", "WATCHDOG_PID": "1"}).watchdog_interval_s is None
    assert Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "3000000",
                     "WATCHDOG_PID": str(os.getpid())}).watchdog_interval_s == pytest.approx(1.5)
    assert Notifier({"NOTIFY_SOCKET": "/x"}).watchdog_interval_s is None


def test_without_notify_socket_nothing_is_sent(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier()
    assert not n.enabled
    assert not n.ready() and not n.watchdog()
    assert n.sent == 0


def test_a_hung_worker_stops_watchdog_pings_within_watchdog_sec(listener, monkeypatch):
    watchdog_sec = 1.0
    monkeypatch.setenv("WATCHDOG_USEC", str(int(watchdog_sec * 1e6)))
    hang = threading.Event()
    release = threading.Event()

    def render(w: Worker) -> bool:
        if hang.is_set():
            release.wait(20)  # stuck inside a "kernel call": no heartbeat from here on
        w.sleep(0.02)
        return True

    renderer = Worker("renderer", render)
    capture = Worker("capture", lambda w: w.sleep(0.02) or True)
    sup = Supervisor([capture, renderer], Notifier(), stall_timeout_s=0.4, status_period_s=0.2, period_s=0.02)
    sup.first_frame.set()
    runner = threading.Thread(target=sup.run, kwargs={"signals": False, "shutdown_s": 0.3})
    runner.start()
    try:
        assert listener.wait_for("READY=1") is not None
        time.sleep(1.6)
        healthy_pings = listener.times_of("WATCHDOG=1")
        # Pinged at half of WatchdogSec while everything beats: about 4 in 1.6 s.
        assert len(healthy_pings) >= 3
        t_hang = time.monotonic()
        hang.set()
        time.sleep(2.5 * watchdog_sec)
        pings = listener.times_of("WATCHDOG=1")
        after = [t for t in pings if t > t_hang]
        # At most the one already due before the stall was noticed, and never past WatchdogSec.
        assert all(t - t_hang < watchdog_sec for t in after), [t - t_hang for t in after]
        assert time.monotonic() - pings[-1] > watchdog_sec  # systemd would now restart the service
        assert any("renderer hung" in s for s in listener.starting("STATUS="))
        assert renderer.alive and capture.alive
    finally:
        sup.stop_requested.set()
        release.set()
        runner.join(5)
    assert listener.wait_for("STOPPING=1") is not None


def test_without_systemd_python_the_plain_socket_is_used(listener, monkeypatch):
    # None in sys.modules makes `from systemd import daemon` raise ImportError, as on a
    # machine where systemd-python is not installed.
    monkeypatch.setitem(sys.modules, "systemd", None)
    monkeypatch.setitem(sys.modules, "systemd.daemon", None)
    n = Notifier()
    assert n.backend == "socket"
    assert n.ready("up")
    assert listener.wait_for("READY=1") is not None
    assert "STATUS=up" in [line for _, line in listener.lines()]
