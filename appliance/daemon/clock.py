"""The appliance's simulated clock: wall-clock monotonic time, optionally running faster.

On a real appliance `rate` is 1 and this is `time.monotonic`. The demo runs the console,
the scripted keypad, the synthetic camera and the patient timeline at a higher rate so a
session with five minutes of fluoroscopy (and its alarm) fits in a minute or two.

An accelerated clock may also be paced by the screen (`pace_s`): it runs at most that many
simulated seconds past the last image shown, then waits for the next one. An exercise's
phase window lasts a few simulated seconds; at x6 on a renderer slowed to a frame a second
the whole window would pass between two images, and the trainee's scripted run would image
nothing of it. Paced, a slow machine makes the session longer in wall time, not emptier.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class SimClock:
    """Seconds of simulated time; `rate` simulated seconds pass per wall-clock second, and with
    `pace_s`, only while the last `shown()` is less than `pace_s / rate` wall seconds ago."""

    def __init__(self, rate: float = 1.0, base: Callable[[], float] = time.monotonic, pace_s: float | None = None):
        if not rate > 0:
            raise ValueError("clock rate must be greater than 0")
        if pace_s is not None and not pace_s > 0:
            raise ValueError("clock pace must be greater than 0 s")
        self.rate = rate
        self.pace_s = pace_s
        self._base = base
        self.origin = base()
        self._lock = threading.Lock()
        self._sim = self.origin           # simulated time at wall time _wall
        self._wall = self.origin
        self._shown = self.origin         # wall time of the last image shown

    def _advance(self, wall: float) -> None:
        until = wall if self.pace_s is None else min(wall, self._shown + self.pace_s / self.rate)
        if until > self._wall:
            self._sim += (until - self._wall) * self.rate
            self._wall = until

    def __call__(self) -> float:
        with self._lock:
            self._advance(self._base())
            return self._sim

    def shown(self) -> None:
        """An image reached the screen: a paced clock runs on from here (a paused stretch is skipped)."""
        with self._lock:
            now = self._base()
            self._advance(now)
            self._wall = max(self._wall, now)
            self._shown = now

    def wall_s(self, sim_s: float) -> float:
        """A simulated duration in wall-clock seconds (unpaced)."""
        return sim_s / self.rate
