"""The supervisor with real threads, real signals and a real NOTIFY_SOCKET."""

from __future__ import annotations

import os
import queue
import signal
import sqlite3
import threading
import time

import pytest
from notify_listener import NotifyListener
from stop_deadline import stop_deadline_s

from appliance.daemon.health import Health, Level
from appliance.daemon.notify import Notifier
from appliance.daemon.supervisor import Supervisor
from appliance.daemon.worker import Worker


@pytest.fixture
def listener(tmp_path, monkeypatch):
    sock = NotifyListener(tmp_path / "notify.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", sock.path)
    monkeypatch.setenv("WATCHDOG_USEC", "400000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    yield sock
    sock.close()


def _run_in_thread(sup: Supervisor, **kw) -> threading.Thread:
    t = threading.Thread(target=sup.run, kwargs={"signals": False, "shutdown_s": 0.5, **kw})
    t.start()
    return t


def test_ready_only_after_the_first_frame(listener):
    sup = Supervisor([Worker("idle", lambda w: w.sleep(0.02))], Notifier(), period_s=0.02, status_period_s=10)
    runner = _run_in_thread(sup)
    try:
        time.sleep(0.4)
        assert listener.times_of("READY=1") == []
        assert listener.times_of("WATCHDOG=1")  # alive and beating, just not showing anything yet
        t_frame = time.monotonic()
        sup.first_frame.set()
        t_ready = listener.wait_for("READY=1", 2)
        assert t_ready is not None and t_ready >= t_frame
    finally:
        sup.stop_requested.set()
        runner.join(5)
    assert len(listener.times_of("READY=1")) == 1


def test_a_crashing_worker_is_restarted_at_most_restart_limit_times(listener):
    calls = []

    def crash(w: Worker) -> bool:
        calls.append(time.monotonic())
        raise OSError(5, "Input/output error")

    worker = Worker("input", crash)
    steady = Worker("capture", lambda w: w.sleep(0.02))
    sup = Supervisor([steady, worker], Notifier(), restart_limit=3, restart_window_s=60, period_s=0.02, status_period_s=0.1)
    runner = _run_in_thread(sup)
    try:
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline and not sup.worker_problems:
            time.sleep(0.02)
        time.sleep(0.3)
        assert worker.starts == 4  # the first start and three restarts
        assert len(calls) == 4 and not worker.alive
        assert sup.worker_problems == ["input keeps crashing (OSError: [Errno 5] Input/output error)"]
        last_ping = listener.times_of("WATCHDOG=1")[-1]
        time.sleep(0.5)
        assert listener.times_of("WATCHDOG=1")[-1] == last_ping  # no more pings: systemd takes over
        assert any("input keeps crashing" in s for s in listener.starting("STATUS="))
    finally:
        sup.stop_requested.set()
        runner.join(5)


def test_restarts_outside_the_window_are_forgotten():
    clock = [0.0]
    dead = Worker("w", lambda w: (_ for _ in ()).throw(RuntimeError("boom")), clock=lambda: clock[0])
    sup = Supervisor([dead], Notifier({}), restart_limit=2, restart_window_s=10, clock=lambda: clock[0])
    dead.start()
    for now in (1.0, 2.0, 3.0, 13.0, 14.0):
        dead.join(2)
        clock[0] = now
        problems = sup.check_workers(now)
        # Two restarts in any 10 s: at 1 and 2; refused at 3; at 13 the one at 1... and 2 have aged out.
        expected_problem = now == 3.0
        assert bool(problems) == expected_problem, (now, problems)
    assert dead.starts == 1 + 4


def test_sigterm_stops_flushes_and_returns_0_within_2_s(listener, tmp_path):
    """Producer, then a ledger worker writing to real SQLite: every event produced is on disk after SIGTERM."""
    events: queue.Queue = queue.Queue(maxsize=1000)
    produced = []
    db_path = tmp_path / "ledger.sqlite"

    def produce(w: Worker) -> bool:
        produced.append(len(produced))
        events.put(produced[-1])
        w.sleep(0.005)
        return True

    state = {}

    def open_db(w: Worker) -> None:
        state["db"] = sqlite3.connect(db_path)
        state["db"].execute("CREATE TABLE IF NOT EXISTS event (n INTEGER)")

    def write(w: Worker) -> bool:
        try:
            n = events.get(timeout=0.05)
        except queue.Empty:
            return False
        state["db"].execute("INSERT INTO event VALUES (?)", (n,))
        return True

    def flush(w: Worker) -> None:
        while True:
            try:
                state["db"].execute("INSERT INTO event VALUES (?)", (events.get_nowait(),))
            except queue.Empty:
                break
        state["db"].commit()
        state["db"].close()

    sup = Supervisor([Worker("input", produce), Worker("ledger", write, setup=open_db, teardown=flush)],
                     Notifier(), period_s=0.02)
    sup.first_frame.set()
    sent = []
    threading.Timer(0.5, lambda: (sent.append(time.monotonic()), os.kill(os.getpid(), signal.SIGTERM))).start()
    before = signal.getsignal(signal.SIGTERM)
    rc = sup.run(shutdown_s=1.5)
    took = time.monotonic() - sent[0]
    assert rc == 0
    assert took < stop_deadline_s(), (took, os.getloadavg())
    assert signal.getsignal(signal.SIGTERM) is before
    assert listener.wait_for("STOPPING=1", 1) is not None
    rows = [r[0] for r in sqlite3.connect(db_path).execute("SELECT n FROM event ORDER BY n")]
    assert len(produced) > 10
    assert rows == list(range(len(produced)))


def test_sigterm_with_a_hung_worker_still_exits_within_2_s(listener):
    release = threading.Event()
    hung = Worker("renderer", lambda w: release.wait(30))
    sup = Supervisor([hung, Worker("ledger", lambda w: w.sleep(0.02))], Notifier(), period_s=0.02)
    threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGTERM)).start()
    t0 = time.monotonic()
    try:
        assert sup.run(shutdown_s=1.5) == 0
        assert time.monotonic() - t0 < 0.3 + stop_deadline_s(), os.getloadavg()
        assert hung.alive and not sup.workers[1].alive  # the ledger still got its turn
    finally:
        release.set()


def test_sighup_calls_reload_and_tells_systemd(listener):
    reloads = []
    sup = Supervisor([Worker("idle", lambda w: w.sleep(0.02))], Notifier(), period_s=0.02)
    sup.first_frame.set()

    def on_reload():
        reloads.append(time.monotonic())
        sup.stop_requested.set()

    threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGHUP)).start()
    assert sup.run(on_reload=on_reload, shutdown_s=0.5) == 0
    assert len(reloads) == 1

    def after_reloading() -> list[str]:
        lines = [l for _, l in listener.lines()]
        return lines[lines.index("RELOADING=1"):] if "RELOADING=1" in lines else []

    # The datagrams reach the listener's thread a moment after they are sent: wait for them.
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and "READY=1" not in after_reloading():
        time.sleep(0.02)
    lines = after_reloading()
    assert lines and lines[1].startswith("MONOTONIC_USEC=") and "READY=1" in lines[2:], lines


def test_health_banners_appear_and_clear_with_the_condition():
    class Flaky:
        name = "camera"
        state = "camera lost"

        def check(self):
            return Health(Level.OK) if self.state == "ok" else Health(Level.WARNING, "tracking lost: camera lost")

    check = Flaky()
    sup = Supervisor([], Notifier({}), health_checks=[check], status=lambda: "10.0 fps")
    sup.tick(0.0)
    assert sup.banners() == ["tracking lost: camera lost"]
    assert sup.status_line() == "10.0 fps; tracking lost: camera lost"
    check.state = "ok"
    sup.tick(5.0)
    assert sup.banners() == [] and sup.status_line() == "10.0 fps"


def test_a_check_that_raises_is_an_error_not_a_crash():
    class Broken:
        name = "disk"

        def check(self):
            raise PermissionError("denied")

    sup = Supervisor([], Notifier({}), health_checks=[Broken()])
    sup.tick(0.0)
    assert sup.health["disk"].level == Level.ERROR
    assert "denied" in sup.banners()[0]
