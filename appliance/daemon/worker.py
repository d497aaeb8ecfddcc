"""`Worker`: a long-lived thread that loops over one step and stamps a heartbeat each time.

The supervisor reads the stamps: a worker whose thread died is restarted, one whose stamp
has gone stale is hung (Python cannot kill a thread, so the watchdog ping stops and
systemd restarts the service). A step that knowingly takes long (building a patient,
compiling a kernel) says so with `grace()` instead of looking hung.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager

log = logging.getLogger(__name__)


class Worker:
    """Runs `step()` until stopped. `step` returns True when it did work (counted in `progress`).

    Pass `step` (and optionally `setup`, `teardown`) or override the methods. A step must
    not spin: when it has nothing to do it waits (on a LatestValue, or `self.sleep`) and
    returns False; the loop then waits `idle_s` more before the next step.
    """

    def __init__(self, name: str, step: Callable[[Worker], bool] | None = None, *,
                 setup: Callable[[Worker], None] | None = None,
                 teardown: Callable[[Worker], None] | None = None,
                 idle_s: float = 0.01, clock: Callable[[], float] = time.monotonic):
        self.name = name
        self._step, self._setup, self._teardown = step, setup, teardown
        self.idle_s = idle_s
        self.clock = clock
        self.heartbeat = clock()
        self.progress = 0
        self.starts = 0
        self.error: str | None = None
        self._grace_until = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- overridable parts -------------------------------------------------------------
    def setup(self) -> None:
        if self._setup is not None:
            self._setup(self)

    def step(self) -> bool:
        if self._step is None:
            raise NotImplementedError(f"worker {self.name} has no step")
        return bool(self._step(self))

    def teardown(self) -> None:
        if self._teardown is not None:
            self._teardown(self)

    # --- life cycle ----------------------------------------------------------------------
    def start(self) -> None:
        """Start (or restart, after the thread died) the worker's thread."""
        if self.alive:
            return
        self._stop = threading.Event()
        self.error = None
        self.heartbeat = self.clock()
        self.starts += 1
        # Daemon threads: a worker hung inside a C call must not keep the process from exiting.
        self._thread = threading.Thread(target=self._main, name=f"fluorosim-{self.name}", daemon=True)
        self._thread.start()

    def _main(self) -> None:
        stop = self._stop
        try:
            self.beat()
            self.setup()
            while not stop.is_set():
                self.beat()
                if self.step():
                    self.progress += 1
                elif self.idle_s > 0:
                    stop.wait(self.idle_s)
        except BaseException as e:  # noqa: BLE001 - a crash is reported to the supervisor, not lost
            self.error = f"{type(e).__name__}: {e}"
            log.exception("worker %s crashed", self.name)
        finally:
            try:
                self.teardown()
            except Exception:  # noqa: BLE001
                log.exception("worker %s failed while shutting down", self.name)

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout_s: float | None = None) -> bool:
        """Wait for the thread to end; True if it did."""
        if self._thread is not None:
            self._thread.join(timeout_s)
        return not self.alive

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def sleep(self, seconds: float) -> bool:
        """Wait `seconds` unless stopped first; True if stopped."""
        return self._stop.wait(seconds)

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # --- heartbeat -----------------------------------------------------------------------
    def beat(self) -> None:
        self.heartbeat = self.clock()

    @contextmanager
    def grace(self, seconds: float):
        """Within this block the worker may go `seconds` without a heartbeat and not count as hung."""
        self._grace_until = self.clock() + seconds
        try:
            yield
        finally:
            self._grace_until = 0.0
            self.beat()

    def stall_s(self, now: float | None = None) -> float:
        """Seconds since the last heartbeat, 0 while inside a `grace()` block that has not run out."""
        now = self.clock() if now is None else now
        if now < self._grace_until:
            return 0.0
        return max(0.0, now - max(self.heartbeat, self._grace_until))
