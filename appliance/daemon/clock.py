"""The appliance's simulated clock: wall-clock monotonic time, optionally running faster.

On a real appliance `rate` is 1 and this is `time.monotonic`. The demo runs the console,
the scripted keypad, the synthetic camera and the patient timeline at a higher rate so a
session with five minutes of fluoroscopy (and its alarm) fits in a minute or two.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class SimClock:
    """Seconds of simulated time; `rate` simulated seconds pass per wall-clock second."""

    def __init__(self, rate: float = 1.0, base: Callable[[], float] = time.monotonic):
        if not rate > 0:
            raise ValueError("clock rate must be greater than 0")
        self.rate = rate
        self._base = base
        self.origin = base()

    def __call__(self) -> float:
        return self.origin + (self._base() - self.origin) * self.rate

    def wall_s(self, sim_s: float) -> float:
        """A simulated duration in wall-clock seconds."""
        return sim_s / self.rate
