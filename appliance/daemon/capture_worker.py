"""The capture worker: camera frames -> tracker -> the newest pose of the box."""

from __future__ import annotations

import time

from drivers.camera import CameraSource

from ..tracking.tracker import Tracker
from .handoff import LatestValue, TrackedPose
from .pose_demand import PoseDemand
from .worker import Worker

#: How often the worker asks the camera for a newer frame (s); `latest()` never blocks, so
#: this polls well above any webcam's frame rate.
FRAME_POLL_S = 0.002


class CaptureWorker(Worker):
    """camera.latest() -> Tracker.track() -> `poses`, one pose per camera frame."""

    def __init__(self, camera: CameraSource, tracker: Tracker, poses: LatestValue[TrackedPose],
                 demand: PoseDemand | None = None):
        """`demand`: track only the frames the renderer could still take (see pose_demand.py)."""
        super().__init__("capture")
        self.camera, self.tracker, self.poses, self.demand = camera, tracker, poses, demand
        #: Frames left untracked because a newer one would come before the renderer wanted a pose.
        self.skipped = 0
        self._frame_seq = -1
        #: Whether the last frame gave a pose (None before the first), for the tracking health check.
        self.pose_ok: bool | None = None

    def step(self) -> bool:
        frame = self.camera.latest(after_seq=self._frame_seq)
        if frame is None:
            self.sleep(FRAME_POLL_S)
            return False
        self._frame_seq = frame.seq
        if self.demand is not None and not self.demand.wanted():
            self.skipped += 1
            return True
        t0 = time.monotonic()
        pose = self.tracker.track(frame.image, frame.t_monotonic)
        t1 = time.monotonic()
        if self.demand is not None:
            self.demand.tracked(t1 - t0)
        self.pose_ok = bool(pose.ok)
        self.poses.put(TrackedPose(pose, frame.t_monotonic, frame.seq, t0, t1, self.tracker.filter_s))
        return True
