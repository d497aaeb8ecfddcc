"""When the render worker will want its next pose, so that poses it would never draw cost nothing.

The renderer always draws the newest pose; while it renders, every camera frame tracked (and,
for the synthetic webcam, drawn) before the last one that can still be ready in time is
thrown away unseen. `PoseDemand` holds the renderer's expected end of the frame in progress
(its start plus the recent median render time), and says whether a frame arriving now could
still be the pose it takes: the capture worker tracks, and the synthetic webcam draws, only
such frames. A real webcam delivers its frames at no cost to the appliance; the tracking of
the frames the renderer would skip is then the only saving.

No pose is staler for it: the last frame that arrives early enough before the renderer is free,
with a frame period, the tracking time and what the caller adds in hand, is still tracked.
While the renderer is idle (fluoroscopy off, a frame faster than the camera) every frame is.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

#: Recent render and tracking times kept for their medians (count).
WINDOW = 15


class PoseDemand:
    """Shared by the render worker (`rendering`, `rendered`), the capture worker (`tracked`,
    `wanted`) and the synthetic webcam (`wanted`)."""

    def __init__(self, frame_period_s: float, clock: Callable[[], float] = time.monotonic):
        self.frame_period_s = float(frame_period_s)
        self.clock = clock
        self._lock = threading.Lock()
        self._render_s: deque[float] = deque(maxlen=WINDOW)
        self._track_s: deque[float] = deque(maxlen=WINDOW)
        self._busy_until = -np.inf

    def rendering(self, t_start: float) -> None:
        """A frame's render began at `t_start` (s, `clock`)."""
        with self._lock:
            expected = float(np.median(self._render_s)) if self._render_s else 0.0
            self._busy_until = t_start + expected

    def rendered(self, t_start: float, t_end: float) -> None:
        """The frame begun at `t_start` is done: the renderer wants the newest pose from now."""
        with self._lock:
            self._render_s.append(max(0.0, t_end - t_start))
            self._busy_until = -np.inf

    def tracked(self, seconds: float) -> None:
        """One camera frame took the tracker `seconds` (s)."""
        with self._lock:
            self._track_s.append(max(0.0, seconds))

    def wanted(self, ahead_s: float = 0.0) -> bool:
        """Whether a frame arriving now, ready `ahead_s` (s) from now before tracking (the
        webcam's drawing time; 0 for a frame in hand), could still be the pose the renderer
        takes next: false only while a newer frame will come in time for it."""
        with self._lock:
            track = float(np.median(self._track_s)) if self._track_s else 0.0
            lead = self.frame_period_s + track + max(0.0, ahead_s)
            return self.clock() >= self._busy_until - lead
