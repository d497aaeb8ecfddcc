"""The supervisor: starts the workers, watches their heartbeats, and speaks to systemd.

Every `period_s` it checks each worker: a dead thread is restarted (at most
`restart_limit` times per `restart_window_s`), a stale heartbeat means hung. Only when
every worker is alive and beating does it send WATCHDOG=1, so a hung renderer stops the
pings and systemd restarts the service. READY=1 goes out once the first frame is on
screen (`first_frame` is set by whoever writes it). SIGTERM and SIGINT stop, SIGHUP
reloads; the handlers only set flags and the supervisor's own loop acts on them.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence

from .health import Health, HealthCheck, Level, run_check
from .notify import Notifier
from .worker import Worker

log = logging.getLogger(__name__)

#: The STATUS= line goes to the log at least this often, and whenever a banner comes or goes (s).
STATUS_LOG_PERIOD_S = 60.0


class Supervisor:
    def __init__(self, workers: Sequence[Worker], notifier: Notifier | None = None, *,
                 stall_timeout_s: float = 5.0, restart_limit: int = 5, restart_window_s: float = 60.0,
                 health_checks: Iterable[HealthCheck] = (), health_period_s: float = 1.0,
                 status_period_s: float = 2.0, status: Callable[[], str] | None = None,
                 period_s: float = 0.05, clock: Callable[[], float] = time.monotonic):
        self.workers = list(workers)
        self.notifier = notifier or Notifier()
        self.stall_timeout_s = stall_timeout_s
        self.restart_limit = restart_limit
        self.restart_window_s = restart_window_s
        self.health_checks = list(health_checks)
        self.health_period_s = health_period_s
        self.status_period_s = status_period_s
        self._status = status or (lambda: "")
        self.period_s = period_s
        self.clock = clock

        self.first_frame = threading.Event()
        self.stop_requested = threading.Event()
        self.reload_requested = threading.Event()
        self.ready_sent = False
        self.health: dict[str, Health] = {}
        self.worker_problems: list[str] = []
        self.watchdog_pings = 0
        self._restarts: dict[str, deque[float]] = {w.name: deque() for w in self.workers}
        self._given_up: set[str] = set()
        self._next_ping = 0.0
        self._next_health = 0.0
        self._next_status = 0.0
        self._next_status_log = 0.0
        self._logged_banners: list[str] | None = None

    # --- checks --------------------------------------------------------------------------
    def check_workers(self, now: float) -> list[str]:
        """Restart dead workers within the rate limit; return what is wrong, one phrase each."""
        problems = []
        for w in self.workers:
            if not w.alive:
                if w.stopping:
                    continue
                times = self._restarts[w.name]
                while times and now - times[0] > self.restart_window_s:
                    times.popleft()
                if len(times) < self.restart_limit:
                    times.append(now)
                    log.warning("worker %s died (%s); restarting it (%d in the last %.0f s)",
                                w.name, w.error or "no error", len(times), self.restart_window_s)
                    w.start()
                else:
                    if w.name not in self._given_up:
                        log.error("worker %s died %d times within %.0f s (%s); no longer pinging the watchdog",
                                  w.name, len(times) + 1, self.restart_window_s, w.error)
                        self._given_up.add(w.name)
                    problems.append(f"{w.name} keeps crashing ({w.error})")
                    continue
            stall = w.stall_s(now)
            if stall > self.stall_timeout_s:
                problems.append(f"{w.name} hung for {stall:.1f} s")
        return problems

    def check_health(self) -> dict[str, Health]:
        results = {c.name: run_check(c) for c in self.health_checks}
        for name, h in results.items():
            before = self.health.get(name)
            if before is None or before.level != h.level or before.banner != h.banner:
                if h.level == Level.OK:
                    if before is not None and before.level != Level.OK:
                        log.info("%s recovered", name)
                else:
                    log.warning("%s: %s %s", name, h.banner, h.context or "")
        self.health = results
        return results

    def banners(self) -> list[str]:
        """What is wrong right now, for the screen: degraded modes first, then worker problems."""
        out = [h.banner for h in self.health.values() if h.level != Level.OK and h.banner]
        return out + self.worker_problems

    @property
    def healthy_workers(self) -> bool:
        return not self.worker_problems

    def status_line(self) -> str:
        parts = [self._status()]
        parts += self.banners()
        return "; ".join(p for p in parts if p)

    # --- the loop ------------------------------------------------------------------------
    def start(self) -> None:
        for w in self.workers:
            w.start()
        now = self.clock()
        self._next_ping = now
        self._next_health = now
        self._next_status = now

    def tick(self, now: float | None = None) -> None:
        now = self.clock() if now is None else now
        self.worker_problems = self.check_workers(now)
        if now >= self._next_health:
            self.check_health()
            self._next_health = now + self.health_period_s
        if not self.ready_sent and self.first_frame.is_set():
            self.notifier.ready(self.status_line())
            self.ready_sent = True
            log.info("first frame on screen; ready")
        interval = self.notifier.watchdog_interval_s
        if interval and now >= self._next_ping and self.healthy_workers:
            if self.notifier.watchdog():
                self.watchdog_pings += 1
            self._next_ping = now + interval
        if now >= self._next_status:
            line = self.status_line()
            self.notifier.status(line)
            # The log gets the line when what is wrong changes, and once a minute besides.
            banners = self.banners()
            if banners != self._logged_banners or now >= self._next_status_log:
                log.info("status: %s", line)
                self._logged_banners = banners
                self._next_status_log = now + STATUS_LOG_PERIOD_S
            self._next_status = now + self.status_period_s

    def install_signal_handlers(self) -> dict:
        """SIGTERM/SIGINT ask to stop, SIGHUP to reload (main thread only); returns the previous handlers."""
        previous = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
        signal.signal(signal.SIGTERM, lambda *_: self.stop_requested.set())
        signal.signal(signal.SIGINT, lambda *_: self.stop_requested.set())
        signal.signal(signal.SIGHUP, lambda *_: self.reload_requested.set())
        return previous

    def run(self, *, on_reload: Callable[[], None] | None = None, until: Callable[[], bool] | None = None,
            shutdown_s: float = 1.5, signals: bool = True) -> int:
        """Start the workers and supervise them until SIGTERM/SIGINT (or `until()` is true).

        Returns 0 after stopping the workers in order, waiting at most `shutdown_s` in all.
        """
        previous = self.install_signal_handlers() if signals else {}
        self.start()
        try:
            while not self.stop_requested.is_set():
                self.tick()
                if self.reload_requested.is_set():
                    self.reload_requested.clear()
                    if on_reload is not None:
                        self.notifier.reloading()
                        try:
                            on_reload()
                        finally:
                            self.notifier.ready(self.status_line())
                if until is not None and until():
                    break
                self.stop_requested.wait(self.period_s)
        finally:
            self.shutdown(shutdown_s)
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        return 0

    def shutdown(self, within_s: float = 1.5) -> list[str]:
        """Stop workers in the order given (producers before the ledger); names of any that did not end."""
        self.notifier.stopping()
        deadline = time.monotonic() + within_s
        stuck = []
        for i, w in enumerate(self.workers):
            w.stop()
            # A hung worker gets only its share of the time, so the ledger after it still flushes.
            share = max(0.0, deadline - time.monotonic()) / (len(self.workers) - i)
            if not w.join(share):
                stuck.append(w.name)
        if stuck:
            log.error("workers still running at exit: %s", ", ".join(stuck))
        return stuck
