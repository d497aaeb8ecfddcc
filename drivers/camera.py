"""Camera sources: a V4L2 webcam, a video file or image folder, and a synthetic webcam.

Every source runs its own capture thread and keeps only the newest frame: `latest()`
never blocks and never hands back a frame the caller has already seen, so a slow
consumer drops stale frames instead of falling behind. A source never raises into its
caller once started; it reports trouble through `state` ("starting", "ok",
"camera lost") and `message`, and keeps trying to reopen the device.

The synthetic camera plays the scene of `camera_scene` (printed ArUco markers on a box,
with lighting, blur and noise) at the poses of a trajectory. It is what the demo and the
tests use in place of the webcam; it takes plain numbers (this package knows nothing of
the appliance's profiles).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import cv2
import numpy as np

from .camera_scene import RenderSettings, SceneRenderer, box_marker_quads

log = logging.getLogger(__name__)


class CaptureState(StrEnum):
    """A camera source's `state`, as the health check and the status line show it."""

    STARTING = "starting"
    OK = "ok"
    LOST = "camera lost"

# The service configures logging; a command-line tool reports `state` itself, on one line.
log.addHandler(logging.NullHandler())

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


@dataclass
class CameraFrame:
    image: np.ndarray             # uint8, BGR (or gray)
    t_monotonic: float            # time.monotonic() when captured (s)
    seq: int                      # increasing frame number
    truth: np.ndarray | None = None   # synthetic only: T_webcam_from_phantom it was rendered at (mm)


class CameraSource:
    """A capture thread that keeps the newest frame; subclasses implement `_run`.

    `state` also turns to "camera lost" on its own when no frame has come for
    `stall_timeout_s`, so a capture call that hangs inside the driver is reported even
    while the capture thread cannot report anything.
    """

    stall_timeout_s: float | None = None

    def __init__(self) -> None:
        self._state: str = CaptureState.STARTING
        self._message = ""
        self.frames_captured = 0
        self._lock = threading.Lock()
        self._frame: CameraFrame | None = None
        self._seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._guarded_run, name=type(self).__name__, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    @property
    def state(self) -> str:
        if self._state == CaptureState.OK and self._stalled():
            return CaptureState.LOST
        return self._state

    @property
    def message(self) -> str:
        frame = self._frame
        if self._state == CaptureState.OK and self._stalled() and frame is not None:
            return f"{self.name}: no frame for {time.monotonic() - frame.t_monotonic:.1f} s"
        return self._message

    @property
    def name(self) -> str:
        return type(self).__name__

    def _stalled(self) -> bool:
        frame = self._frame
        return (self.stall_timeout_s is not None and frame is not None
                and time.monotonic() - frame.t_monotonic > self.stall_timeout_s)

    def latest(self, after_seq: int = -1) -> CameraFrame | None:
        """The newest frame if its seq is greater than `after_seq`, else None; never blocks."""
        with self._lock:
            frame = self._frame
        if frame is None or frame.seq <= after_seq:
            return None
        return frame

    def wait(self, after_seq: int = -1, timeout_s: float = 1.0) -> CameraFrame | None:
        """The first frame newer than `after_seq` within `timeout_s` (s), for tools and tests."""
        deadline = time.monotonic() + timeout_s
        while True:
            frame = self.latest(after_seq)
            if frame is not None or time.monotonic() >= deadline:
                return frame
            time.sleep(0.002)

    def __enter__(self) -> CameraSource:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _publish(self, image: np.ndarray, t: float, truth: np.ndarray | None = None) -> None:
        self._seq += 1
        frame = CameraFrame(image=image, t_monotonic=t, seq=self._seq, truth=truth)
        with self._lock:
            self._frame = frame
        self.frames_captured += 1

    def _set_state(self, state: str, message: str = "") -> None:
        if state != self._state or message != self._message:
            if state == CaptureState.LOST:
                log.warning("%s", message)
            self._state, self._message = state, message

    def _guarded_run(self) -> None:
        # The capture thread must never die silently: a bug is reported as a lost camera.
        try:
            self._run()
        except Exception as e:  # noqa: BLE001 - reported through state, see above
            log.exception("camera thread failed")
            self._set_state(CaptureState.LOST, f"camera thread failed: {e}")

    def _run(self) -> None:
        raise NotImplementedError


class V4L2Camera(CameraSource):
    """A UVC webcam through OpenCV's V4L2 back end, reopened whenever it vanishes or stalls."""

    def __init__(self, device: str, width: int = 1280, height: int = 720, fps: float = 30.0,
                 fourcc: str = "MJPG", stall_timeout_s: float = 2.0, retry_interval_s: float = 1.0) -> None:
        super().__init__()
        self.device, self.width, self.height, self.fps, self.fourcc = device, width, height, fps, fourcc
        self.stall_timeout_s: float = stall_timeout_s
        self.retry_interval_s = retry_interval_s
        self.open_attempts = 0

    @property
    def name(self) -> str:
        return f"camera {self.device}"

    def _open(self) -> cv2.VideoCapture | None:
        self.open_attempts += 1
        if not os.path.exists(self.device):
            self._set_state(CaptureState.LOST, f"camera {self.device}: no such device; check the cable and the udev "
                                           f"rule, retrying every {self.retry_interval_s:g} s")
            return None
        cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            self._set_state(CaptureState.LOST, f"camera {self.device}: cannot be opened as a V4L2 capture device "
                                           f"(in use or not a camera?), retrying every {self.retry_interval_s:g} s")
            return None
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        cap.set(cv2.CAP_PROP_FPS, self.fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a queue of old ones
        return cap

    @staticmethod
    def _capture_time(cap: cv2.VideoCapture, now: float) -> float:
        """When the frame was captured (s, time.monotonic's clock).

        OpenCV's V4L2 back end reports the driver's buffer time stamp, which UVC drivers take
        from CLOCK_MONOTONIC when the frame arrives, so it excludes the time the frame waited
        in the queue; anything implausible falls back to the time grab() returned.
        """
        stamp = cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        return stamp if 0.0 <= now - stamp < 0.5 else now

    def _run(self) -> None:
        while not self._stop.is_set():
            cap = self._open()
            if cap is None:
                self._stop.wait(self.retry_interval_s)
                continue
            last_frame = time.monotonic()
            try:
                while not self._stop.is_set():
                    ok = cap.grab()
                    now = time.monotonic()
                    if not ok:
                        if now - last_frame > self.stall_timeout_s:
                            self._set_state(CaptureState.LOST, f"camera {self.device}: no frame for "
                                                           f"{now - last_frame:.1f} s; reopening")
                            break
                        self._stop.wait(0.01)
                        continue
                    ok, image = cap.retrieve()
                    if not ok or image is None:
                        continue
                    last_frame = now
                    self._publish(image, self._capture_time(cap, now))
                    self._set_state(CaptureState.OK)
            finally:
                cap.release()
            self._stop.wait(self.retry_interval_s)


def list_images(folder: str | Path) -> list[Path]:
    """Image files of `folder`, sorted by name."""
    return sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


class FileCamera(CameraSource):
    """Frames from a video file or a folder of images, played at `fps` (and looped if asked)."""

    def __init__(self, path: str | Path, fps: float = 30.0, loop: bool = True) -> None:
        super().__init__()
        self.path, self.fps, self.loop = Path(path), fps, loop
        self.finished = False

    def frames(self) -> Iterator[tuple[str, np.ndarray | None]]:
        """(name, image or None when unreadable) of every frame once, as fast as they decode."""
        if self.path.is_dir():
            for p in list_images(self.path):
                yield str(p), cv2.imread(str(p), cv2.IMREAD_COLOR)
            return
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                return
            i = 0
            while True:
                ok, image = cap.read()
                if not ok:
                    return
                yield f"{self.path}#{i}", image
                i += 1
        finally:
            cap.release()

    def _run(self) -> None:
        period = 1.0 / self.fps
        next_t = time.monotonic()
        while not self._stop.is_set():
            if not self.path.exists():
                self._set_state(CaptureState.LOST, f"{self.path}: no such video file or image folder; retrying")
                self._stop.wait(1.0)
                continue
            produced = 0
            for _, image in self.frames():
                if self._stop.is_set():
                    return
                if image is None:
                    continue
                self._stop.wait(max(0.0, next_t - time.monotonic()))
                next_t = max(next_t + period, time.monotonic() - period)
                self._publish(image, time.monotonic())
                self._set_state(CaptureState.OK)
                produced += 1
            if produced == 0:
                self._set_state(CaptureState.LOST, f"{self.path}: holds no readable frames; retrying")
                self._stop.wait(1.0)
            elif not self.loop:
                self.finished = True
                return


# --- synthetic camera -------------------------------------------------------------------

class SyntheticCamera(CameraSource):
    """A webcam stand-in: renders the box phantom at `trajectory(t)` (T_webcam_from_phantom, mm) at `fps`.

    `t` runs on `clock` (the appliance's clock, which the demo runs faster than the wall clock, so
    the path keeps time with the scripted console and the patient); frames are stamped in
    `time.monotonic` seconds."""

    def __init__(self, marker_ids: Sequence[int], T_phantom_from_marker: Sequence[np.ndarray], marker_size_mm: float,
                 dictionary: str, box_mm: tuple, K: np.ndarray, dist: np.ndarray | Sequence[float], width: int, height: int,
                 trajectory: Callable[[float], np.ndarray], clock: Callable[[], float] = time.monotonic,
                 fps: float = 30.0, settings: RenderSettings | None = None, seed: int | None = None,
                 nice: int = 0) -> None:
        """`nice`: run the drawing thread this many nice steps below its starter (a lower priority)."""
        super().__init__()
        self.settings = settings or RenderSettings()
        quads = box_marker_quads(marker_ids, T_phantom_from_marker, marker_size_mm, dictionary, self.settings)
        self.renderer = SceneRenderer(K, dist, width, height, box_mm, quads, self.settings, seed)
        self.trajectory, self.clock, self.fps = trajectory, clock, fps
        self.t0: float | None = None
        #: `wanted(draw_s)`: whether a frame drawn now, ready `draw_s` (s) from now, would be
        #: used; None: every frame is. Drawing the box costs CPU a real webcam does not, so the
        #: owner may skip the frames its consumer would throw away unseen.
        self.wanted: Callable[[float], bool] | None = None
        #: Frame times the camera did not draw because `wanted` said no (count).
        self.frames_skipped = 0
        self._draw_s = 0.0
        self.nice = nice
        #: The drawing thread's niceness once it runs (None before, or where it cannot be read).
        self.thread_nice: int | None = None

    def render_at(self, t: float, bgr: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(image, truth) for trajectory time `t` (s): the pose at mid-exposure, blurred over the exposure."""
        # The exposure is wall-clock time; on a clock running faster (the demo's) the path moves
        # that many times farther during it.
        exp = self.settings.exposure_s * float(getattr(self.clock, "rate", 1.0))
        T_mid = self.trajectory(t - exp / 2)
        T_start, T_end = self.trajectory(t - exp), self.trajectory(t)
        # The line kernel is centred on the mid-exposure pose, so the smear covers the whole exposure.
        gray = self.renderer.render(T_mid, None if exp <= 0 else (T_start, T_end))
        return (cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR) if bgr else gray), T_mid

    def _lower_priority(self) -> None:
        # Linux gives each thread its own nice value; lowering one's own priority needs no privilege.
        # Elsewhere the thread keeps its priority and `thread_nice` stays None.
        try:
            tid = threading.get_native_id()
            if self.nice:
                os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + self.nice)
            self.thread_nice = os.getpriority(os.PRIO_PROCESS, tid)
        except (AttributeError, OSError):
            pass

    def _run(self) -> None:
        self._lower_priority()
        period = 1.0 / self.fps
        if self.t0 is None:             # the path's time 0, unless the owner set it (a session's start)
            self.t0 = self.clock()
        next_t = time.monotonic()
        while not self._stop.is_set():
            wanted = self.wanted
            if wanted is None or self._frame is None or wanted(self._draw_s):
                t_draw = time.monotonic()
                image, truth = self.render_at(self.clock() - self.t0)
                # Stamped on the wall clock whatever clock the path runs on: latency is wall time.
                self._publish(image, time.monotonic(), truth)
                self._draw_s = time.monotonic() - t_draw
                self._set_state(CaptureState.OK)
            else:
                self.frames_skipped += 1
            next_t += period
            self._stop.wait(max(0.0, next_t - time.monotonic()))
            next_t = max(next_t, time.monotonic() - period)
