"""Frame rate on screen and motion-to-photon latency, over a sliding window and over a whole run."""

from __future__ import annotations

import threading
from collections import deque

import numpy as np


def fps_text(fps: float | None) -> str:
    """A frame rate as the status lines print it ("-- fps" before there is one)."""
    return "  -- fps" if fps is None else f"{fps:4.1f} fps"


class FrameStats:
    """Records each live frame written to the display: when, and how old its camera frame was.

    Latency is motion-to-photon: the camera frame's timestamp to the framebuffer write,
    in wall-clock seconds.
    """

    def __init__(self, window_s: float = 2.0, keep: int = 100_000):
        self.window_s = window_s
        self._recent: deque[float] = deque()
        self._lock = threading.Lock()
        self.latencies_s: deque[float] = deque(maxlen=keep)
        self.shown_at: deque[float] = deque(maxlen=keep)
        #: (run, time shown) of the frames exposed in a continuous mode, by the console's run count
        self.continuous_at: deque[tuple[int, float]] = deque(maxlen=keep)
        self.frames = 0

    def add(self, t_shown: float, latency_s: float, continuous_run: int | None = None) -> None:
        """One live frame; `continuous_run`: the console's run it was exposed in, where that run is
        in a continuous mode (the rate on screen is then the appliance's; a pulsed mode shows its
        pulse rate), else None."""
        with self._lock:
            self.frames += 1
            self.latencies_s.append(latency_s)
            self.shown_at.append(t_shown)
            if continuous_run is not None:
                self.continuous_at.append((continuous_run, t_shown))
            self._recent.append(t_shown)
            while self._recent and t_shown - self._recent[0] > self.window_s:
                self._recent.popleft()

    def fps(self, now: float) -> float | None:
        """Live frames per second over the last `window_s` seconds: frame intervals over the time
        they span, so the first frames of a run read their true rate rather than a count over a
        window not yet filled. None until two frames are in the window (no rate to tell)."""
        with self._lock:
            recent = [t for t in self._recent if now - t <= self.window_s]
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return None
        return (len(recent) - 1) / (recent[-1] - recent[0])

    def summary(self) -> dict[str, float]:
        """frames, fps over the whole run (first to last frame), fps_exposing (within each run of
        a continuous mode, frame intervals over the time from its first frame to its last: the
        pedal's pauses between runs are not the appliance's), latency median and p99 (ms)."""
        with self._lock:
            lat = np.array(self.latencies_s, dtype=float)
            shown = np.array(self.shown_at, dtype=float)
            continuous = list(self.continuous_at)
        out = {"frames": float(self.frames), "fps": float("nan"), "fps_exposing": float("nan"),
               "latency_median_ms": float("nan"), "latency_p99_ms": float("nan")}
        if len(shown) >= 2 and shown[-1] > shown[0]:
            out["fps"] = (len(shown) - 1) / (shown[-1] - shown[0])
        spans: dict[int, list[float]] = {}
        for run, t in continuous:
            spans.setdefault(run, []).append(t)
        intervals = sum(len(ts) - 1 for ts in spans.values())
        seconds = sum(max(ts) - min(ts) for ts in spans.values())
        if intervals and seconds > 0:
            out["fps_exposing"] = intervals / seconds
        if len(lat):
            out["latency_median_ms"] = float(np.median(lat) * 1000)
            out["latency_p99_ms"] = float(np.percentile(lat, 99) * 1000)
        return out
