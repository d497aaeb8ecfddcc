"""Which matrix a moving frame is cast at: the largest that keeps the frame budget.

A moving frame costs a new ray cast, which grows with the matrix's pixels, plus what does not
(the webcam, tracking, composing and showing the image at the full matrix). How much of the
machine the appliance gets varies (another process, the synthetic webcam's drawing, a hotter
CPU), so a fixed moving matrix either wastes time or misses the frame rate. The controller
holds a ladder of square matrices, from `rendering.moving_matrix_px` down to
`rendering.moving_matrix_min_px` in steps of `rendering.moving_matrix_step_px`, and moves one
rung at a time on the median of the last `rendering.matrix_window_frames` frame times (each
from the start of the render to the image on screen):

- one rung down when that median is over `rendering.frame_budget_ms`;
- one rung up when that median, scaled by the pixel ratio of the next larger rung, is within
  `rendering.matrix_step_up_margin` of the budget.

It does not hunt: a frame time is a part that scales with the pixels and a part that does not,
so scaling the whole of it by the pixel ratio overstates the larger rung's cost. A step up is
therefore taken only when the larger rung will be within the margin, so it is not then over the
budget; and after a step down the rung left behind, which was over the budget, is predicted at
least as slow as it was measured, so it is not taken again until the machine is faster. Each
step clears the window, so every decision rests on frames of the rung it leaves.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from ..config.rendering import Rendering


def matrix_ladder(settings: Rendering, full_px: int) -> list[int]:
    """The moving matrices, largest first (pixels): from `moving_matrix_px` down to
    `moving_matrix_min_px` by `moving_matrix_step_px`, the last rung the minimum itself; none
    reaching the full matrix, which is the resting one. Empty: no moving matrix."""
    top = settings.moving_matrix_px
    if top is None or top >= full_px:
        return []
    bottom = settings.moving_matrix_min_px if settings.moving_matrix_min_px is not None else top
    ladder = list(range(top, bottom, -settings.moving_matrix_step_px))
    return ladder + [bottom] if bottom not in ladder else ladder


class MatrixController:
    """The moving matrix now (`matrix`), updated by `observe` after each moving frame."""

    def __init__(self, settings: Rendering, full_px: int):
        self.ladder = matrix_ladder(settings, full_px)
        self.budget_s = settings.frame_budget_ms / 1000.0
        self.margin = settings.matrix_step_up_margin
        self._rung = 0
        self._times: deque[float] = deque(maxlen=settings.matrix_window_frames)
        #: (from, to) pixels of each step taken, in order: what the bench and the tests read.
        self.steps: list[tuple[int, int]] = []

    @property
    def matrix(self) -> int | None:
        """The square matrix moving frames are cast at now (pixels); None without a ladder."""
        return self.ladder[self._rung] if self.ladder else None

    def observe(self, matrix_px: int, frame_s: float) -> int | None:
        """A moving frame cast at `matrix_px` took `frame_s` (s, render start to screen). Frames
        of another rung (one begun before the last step) are not this rung's and are ignored.
        Returns the matrix for the next moving frame (pixels)."""
        if matrix_px != self.matrix:
            return self.matrix
        self._times.append(float(frame_s))
        if len(self._times) < (self._times.maxlen or 1):
            return self.matrix
        t = float(np.median(self._times))
        if t > self.budget_s and self._rung + 1 < len(self.ladder):
            self._step(+1)
        elif self._rung > 0:
            larger = self.ladder[self._rung - 1]
            if t * (larger / matrix_px) ** 2 <= self.margin * self.budget_s:
                self._step(-1)
        return self.matrix

    def _step(self, direction: int) -> None:
        before = self.ladder[self._rung]
        self._rung += direction
        self.steps.append((before, self.ladder[self._rung]))
        self._times.clear()
