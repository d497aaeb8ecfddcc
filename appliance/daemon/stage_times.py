"""Where a live frame's motion-to-photon latency goes: the time of each stage from the camera
frame's timestamp to the framebuffer write.

    camera frame ─capture─> picked up ─tracking─> corners and pose ─pose filter─> pose put
      ─pose wait─> render begins ─render─> image ─overlay─> compose begins ─compose─> composed
      ─write─> on screen

The stages follow each other without gaps, so per frame they add up to the latency exactly
(`StageTimes.add` is given the time stamps, not durations). "capture" is the frame waiting for
the capture worker; "pose wait" the pose waiting for the renderer to take it (a render in
progress, or the worker's own poll); "overlay" what the render worker does between the image
and the compositor (the technique, the teaching view, banners, the overlay's values).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

STAGES = ("capture", "tracking", "pose filter", "pose wait", "render", "overlay", "compose", "write")


@dataclass(frozen=True)
class FrameStamps:
    """One live frame's time stamps (time.monotonic, s) and the pose filter's own time (s)."""

    t_frame: float          # the camera frame's timestamp
    t_picked: float         # the capture worker took the frame
    t_tracked: float        # the pose was put for the renderer (tracking and filter done)
    filter_s: float         # of t_picked..t_tracked, the time in the pose filter
    t_render: float         # the render worker began the frame
    t_rendered: float       # the renderer returned the image
    t_compose: float        # the compositor was called
    t_composed: float       # the compositor returned the screen image
    t_shown: float          # the display's write returned

    def durations(self) -> tuple[float, ...]:
        """Seconds per stage, in the order of STAGES; they sum to t_shown - t_frame."""
        return (self.t_picked - self.t_frame, self.t_tracked - self.t_picked - self.filter_s, self.filter_s,
                self.t_render - self.t_tracked, self.t_rendered - self.t_render, self.t_compose - self.t_rendered,
                self.t_composed - self.t_compose, self.t_shown - self.t_composed)


class StageTimes:
    """The stage durations of every live frame, with when it was shown, for a run's breakdown."""

    def __init__(self, keep: int = 100_000):
        self._lock = threading.Lock()
        self._shown: deque[float] = deque(maxlen=keep)
        self._rows: deque[tuple[float, ...]] = deque(maxlen=keep)

    def add(self, stamps: FrameStamps) -> None:
        with self._lock:
            self._shown.append(stamps.t_shown)
            self._rows.append(stamps.durations())

    def summary(self, since: float = -np.inf) -> dict[str, tuple[float, float]]:
        """{stage: (median ms, p99 ms)} over the frames shown at or after `since` (time.monotonic,
        s); empty when there are none."""
        with self._lock:
            shown = np.array(self._shown, dtype=float)
            rows = np.array(self._rows, dtype=float).reshape(-1, len(STAGES))
        rows = rows[shown >= since]
        if not len(rows):
            return {}
        med, p99 = np.median(rows, axis=0) * 1000, np.percentile(rows, 99, axis=0) * 1000
        return {s: (float(m), float(p)) for s, m, p in zip(STAGES, med, p99)}


def breakdown_text(summary: dict[str, tuple[float, float]]) -> str:
    """One line: each stage's median and p99 in ms ("capture 3/9 ms, tracking ...")."""
    return ", ".join(f"{s} {m:.1f}/{p:.0f}" for s, (m, p) in summary.items()) + " ms (median/p99)"
