"""A 4D CT played against the clock: which phase (or pair of phases) to render at time t.

Phases are loaded and prepared on the device by one background thread, nearest-needed
first, so the renderer thread never waits for disk or copies: `at()` only looks up what is
ready. Once prepared, a phase stays on the device (a 10-phase 512x512x136 CT takes about
0.75 GB as int16), so looping never reloads.
"""

from __future__ import annotations

import bisect
import logging
import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from ..errors import FluorosimError
from ..patient.volume import Volume
from .heap import release_freed

log = logging.getLogger(__name__)


class Timeline(Protocol):
    """What the daemon asks of a case's timeline: a 4D CT's phases (PhaseTimeline), or a
    breathing model over one CT or over a 4D CT (patient/breathing_timeline.py, breathing_4d.py)."""

    def at(self, t_s: float, steer: bool = True) -> Any:
        """(phase, next phase or None, weight of the next in [0, 1)) to render at `t_s` (s).
        `steer` False: a look ahead, which leaves the loader's order as the last frame's wanted it."""

    def wait_ready(self, timeout_s: float | None = None, all_phases: bool = False) -> bool:
        """Whether the first phase (or every phase) is ready, waiting up to `timeout_s`."""

    @property
    def ready_count(self) -> int:
        """Phases prepared so far."""

    def close(self) -> None:
        """Stop the loading thread."""


class PhaseTimeline:
    """Phases of a case by time stamp, loaded and prepared in a background thread.

    `phases` are (time_s, loader) in increasing time; `loader()` returns the Volume. After
    the last phase the timeline loops (`at_end="loop"`, the cycle's length being the last
    stamp plus the mean phase interval) or holds the last phase (`"hold"`).
    """

    def __init__(self, phases: Sequence[tuple[float, Callable[[], Volume]]], renderer, at_end: str = "loop"):
        if not phases:
            raise FluorosimError("a case timeline needs at least one phase")
        times = [float(t) for t, _ in phases]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise FluorosimError(f"phase time stamps must increase, got {times}")
        if at_end not in ("loop", "hold"):
            raise FluorosimError(f"at_end must be 'loop' or 'hold', got '{at_end}'")
        self.times = times
        self.loaders = [loader for _, loader in phases]
        self.renderer = renderer
        self.at_end = at_end
        n = len(times)
        self.period_s = times[-1] + ((times[-1] - times[0]) / (n - 1) if n > 1 else 1.0) - times[0]
        self._prepared: list = [None] * n
        self._errors: list[str | None] = [None] * n
        self._wanted = 0
        self._cond = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._load_loop, name="phase-loader", daemon=True)
        self._thread.start()

    # -- background loading ----------------------------------------------------------
    def _next_to_load(self) -> int | None:
        n = len(self.times)
        for step in range(n):      # the wanted phase, then the ones after it (they come next)
            i = (self._wanted + step) % n
            if self._prepared[i] is None and self._errors[i] is None:
                return i
        return None

    def _load_loop(self) -> None:
        while True:
            with self._cond:
                i = self._next_to_load()
                while not self._stop and i is None:
                    self._cond.wait()
                    i = self._next_to_load()
                if self._stop or i is None:
                    return
            try:
                prepared = self.renderer.prepare(self.loaders[i]())
                prepared.time_s = self.times[i]
                error = None
            except FluorosimError as e:
                prepared, error = None, str(e)
                log.error("phase %d (t=%.2f s): %s", i, self.times[i], e)
            except Exception as e:  # a loader bug must not kill the thread silently
                prepared, error = None, f"{type(e).__name__}: {e}"
                log.exception("phase %d (t=%.2f s) failed to load", i, self.times[i])
            release_freed()         # the loaded CT and its temporaries are gone; their pages too
            with self._cond:
                self._prepared[i] = prepared
                self._errors[i] = error
                self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout=5)

    def wait_ready(self, timeout_s: float | None = None, all_phases: bool = False) -> bool:
        """Block until the first phase (or all of them) is prepared or failed; True when ready."""
        def done():
            if all_phases:
                return all(p is not None or e is not None for p, e in zip(self._prepared, self._errors))
            return self._prepared[0] is not None or self._errors[0] is not None
        with self._cond:
            self._cond.wait_for(done, timeout=timeout_s)
            if self._prepared[0] is None and self._errors[0] is not None:
                raise FluorosimError(f"first phase of the case cannot be loaded: {self._errors[0]}")
            return done()

    @property
    def ready_count(self) -> int:
        return sum(p is not None for p in self._prepared)

    # -- lookup ----------------------------------------------------------------------
    def _bracket(self, t_s: float) -> tuple[int, int | None, float]:
        """Phases i, j and the weight of j for time t (j None: phase i alone)."""
        times = self.times
        n = len(times)
        t = t_s - times[0]
        if self.at_end == "loop":
            t = t % self.period_s
        elif t >= times[-1] - times[0]:
            return n - 1, None, 0.0
        t = max(t, 0.0) + times[0]
        i = bisect.bisect_right(times, t) - 1
        if i == n - 1:           # between the last phase and the loop back to the first
            if n == 1:
                return 0, None, 0.0
            t_next, j = times[0] + self.period_s, 0
        else:
            t_next, j = times[i + 1], i + 1
        w = (t - times[i]) / (t_next - times[i])
        return i, j, w

    def at(self, t_s: float, steer: bool = True):
        """(phase, next phase or None, weight of the next in [0, 1)) for time `t_s` (s); with
        `steer` the loader prepares the nearer of the two next (the frame's), not with a look ahead.

        Never waits for loading once any phase is ready: a phase still loading is replaced by
        the nearest earlier ready one and no blend is offered. Raises FluorosimError only when
        no phase is ready yet.
        """
        i, j, w = self._bracket(t_s)
        with self._cond:
            wanted = i if j is None or w < 0.5 else j
            if steer and self._wanted != wanted:
                self._wanted = wanted
                self._cond.notify_all()
            a = self._prepared[i]
            b = self._prepared[j] if j is not None else None
            if a is None:
                ready = [k for k, p in enumerate(self._prepared) if p is not None]
                if not ready:
                    raise FluorosimError("no CT phase is ready yet; the phase loader is still working")
                earlier = [k for k in ready if k <= i]
                a = self._prepared[earlier[-1] if earlier else ready[-1]]
                return a, None, 0.0
        if b is None or w == 0.0 or not a.same_grid(b):
            return a, None, 0.0
        return a, b, float(w)
