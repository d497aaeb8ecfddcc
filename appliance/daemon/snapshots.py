"""Snapshots of key moments of a session, read back from the display, and a contact sheet of them.

The demo (and anyone checking the appliance) wants evidence of what was on screen: the
first live image, each zoom level, collimation, inversion, the +-90 degree rolls, a
saved image, the breath hold, the 5-minute alarm and its reset. Each moment is a
predicate over the frame just written; the first frame that satisfies it is read back
from the framebuffer (what the trainee saw, overlays and all) and written as a PNG.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..atomic_file import write_atomic
from ..errors import FluorosimError
from ..records.disk_reserve import check_reserve
from .handoff import ShownFrame

log = logging.getLogger(__name__)


def roll_deg(T_webcam_from_phantom: np.ndarray) -> float:
    """Roll of the box about its long (x) axis relative to the camera's view, in degrees.

    0 with the top face toward the camera; +-90 with a long side toward it. The sign follows
    the right-hand rule about the box's +x axis.
    """
    R = np.asarray(T_webcam_from_phantom, dtype=float)[:3, :3]
    x, n = R[:, 0], R[:, 2]
    toward_camera = np.array([0.0, 0.0, -1.0])
    v = toward_camera - np.dot(toward_camera, x) * x
    if np.linalg.norm(v) < 1e-9:
        return 0.0
    return math.degrees(math.atan2(float(np.dot(x, np.cross(v, n))), float(np.dot(v, n))))


@dataclass
class Moment:
    name: str
    caption: str
    when: Callable[[ShownFrame], bool]


def _live(f: ShownFrame) -> bool:
    return bool(f.live and f.image is not None)


def _pose_roll(f: ShownFrame) -> float | None:
    if f.pose is None or not f.pose.pose.ok or f.pose.pose.T_webcam_from_phantom is None:
        return None
    return roll_deg(f.pose.pose.T_webcam_from_phantom)


def _collimated(f: ShownFrame) -> bool:
    c = getattr(f.state, "collimation_mm", None)
    if c is None:
        return False
    return bool(np.min(np.atleast_1d(np.asarray(c, dtype=float))) < f.state.fov_mm - 1e-6)


#: The end-inspiration snapshot comes within this of the end-expiration one (wall s): the same
#: breathing exercise, even when a busy machine's paced clock stretches it.
BREATH_PAIR_S = 60.0
#: A pair or breath-hold image is taken once the breath has stood at one point, the C-arm
#: still, for more than this many live images, so the fluoroscope's recursive filter has settled
#: on the still anatomy instead of blending in the image before (the shipped profiles' weight
#: 0.5 leaves 0.5^5 = 3 % of it in the fifth image, a faint ghost beside a dome that moved 40 px).
#: Counted in images, not seconds: the filter works per image, whatever the clock.
BREATH_SETTLE_FRAMES = 4
#: "The same pose": the C-arm moved less than this between the two images of the pair (mm of the
#: box's origin, degrees), so the pair shows the breath and not the path.
PAIR_POSE_MM, PAIR_POSE_DEG = 1.0, 0.5
#: End-expiration is inspired below this, end-inspiration above 1 minus it.
BREATH_EXTREME = 0.03


def _pose_matrix(f: ShownFrame) -> np.ndarray | None:
    if f.pose is None or not f.pose.pose.ok or f.pose.pose.T_webcam_from_phantom is None:
        return None
    return np.asarray(f.pose.pose.T_webcam_from_phantom, dtype=float)


def same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two T_webcam_from_phantom are the same pose within PAIR_POSE_MM and PAIR_POSE_DEG."""
    moved = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    cos = (float(np.trace(a[:3, :3].T @ b[:3, :3])) - 1.0) / 2.0
    return moved <= PAIR_POSE_MM and math.degrees(math.acos(min(max(cos, -1.0), 1.0))) <= PAIR_POSE_DEG


class _Settled:
    """Whether the live images have shown one breath (None: a case without the breathing model)
    at one pose for more than BREATH_SETTLE_FRAMES images."""

    def __init__(self):
        self.inspired: float | None = None
        self.pose: np.ndarray | None = None
        self.frames = 0
        self._last: float | None = None       # the image counted last (asked once per moment per image)

    def __call__(self, f: ShownFrame) -> bool:
        T = _pose_matrix(f)
        same_breath = ((f.inspired is None) == (self.inspired is None)
                       and (f.inspired is None or abs(f.inspired - self.inspired) <= 1e-3))  # type: ignore[operator]
        if not _live(f) or T is None or self.pose is None or not same_breath or not same_pose(T, self.pose):
            self.inspired, self.pose, self.frames, self._last = f.inspired, T, 1, f.t_wall
            return False
        if f.t_wall != self._last:
            self.frames, self._last = self.frames + 1, f.t_wall
        return self.frames > BREATH_SETTLE_FRAMES


def _breath_moments() -> list[Moment]:
    """End-expiration, then end-inspiration within BREATH_PAIR_S at the same pose (the C-arm
    still), on a case breathing under the model; and a breath hold elsewhere. Each is taken once
    the breath (held, as a radiographer asks for) and the recursive filter have settled; the
    breath hold is not taken at the pair's pose, where it would show the pair's picture again."""
    taken: list[tuple[float, np.ndarray]] = []       # (wall time, pose) of the end-expiration image
    settled, held = _Settled(), _Settled()

    def expiration(f) -> bool:
        T = _pose_matrix(f)
        if T is None or not settled(f) or f.inspired is None or f.inspired >= BREATH_EXTREME:
            return False
        taken.append((f.t_wall, T))
        return True

    def inspiration(f) -> bool:
        if not taken or not settled(f) or f.inspired is None or f.inspired <= 1.0 - BREATH_EXTREME:
            return False
        T = _pose_matrix(f)
        t_expiration, pose = taken[-1]
        return f.t_wall - t_expiration <= BREATH_PAIR_S and T is not None and same_pose(T, pose)

    def breath_hold(f) -> bool:
        if not (_live(f) and bool(f.state.breath_hold) and held(f)):
            return False
        T = _pose_matrix(f)
        return T is not None and not (taken and same_pose(T, taken[-1][1]))
    # The pair first: on the frame both could take, the pair takes it.
    return [Moment("end-expiration", "end-expiration", expiration),
            Moment("end-inspiration", "end-inspiration", inspiration),
            Moment("breath-hold", "breath hold", breath_hold)]


def _back_to_zoom_1() -> Callable[[ShownFrame], bool]:
    """Zoom 1 after another zoom: the first live image is at zoom 1 too, and a second snapshot
    of that moment would show nothing new."""
    other = [False]

    def when(f) -> bool:
        if not _live(f):
            return False
        if f.state.zoom != 1:
            other[0] = True
            return False
        return other[0]
    return when


def key_moments() -> list[Moment]:
    """The moments the demo shows, in the order they appear on the contact sheet."""
    moments = [Moment("first-live", "first live image", _live)]
    moments.append(Moment("zoom-1", "back to zoom 1", _back_to_zoom_1()))
    for z in (2, 3, 4):
        moments.append(Moment(f"zoom-{z}", f"zoom {z}", lambda f, z=z: _live(f) and f.state.zoom == z))  # type: ignore[misc]
    moments += [
        Moment("collimated", "collimator closed in", lambda f: _live(f) and _collimated(f)),
        Moment("inverted", "inverted", lambda f: _live(f) and bool(f.state.invert)),
        Moment("roll-plus-90", "roll +90 degrees", lambda f: _live(f) and (_pose_roll(f) or 0) > 75),
        Moment("roll-minus-90", "roll -90 degrees", lambda f: _live(f) and (_pose_roll(f) or 0) < -75),
        *_breath_moments(),
        Moment("saved", "image saved", lambda f: bool(f.saved_flash)),
        Moment("alarm", "5-minute alarm", lambda f: bool(f.state.alarm_sounding) and alarm_banner_shown(f.rgb_source())),
        Moment("last-image-hold", "last-image hold", lambda f: not f.live and f.image is not None
               and not f.state.fluoro_on),
        Moment("tracking-lost", "tracking lost", lambda f: any("tracking lost" in b for b in f.banners)),
    ]
    return moments


#: Moments whose rendered frame the snapshotter keeps beside the PNG.
KEPT = ("end-expiration", "end-inspiration")


@dataclass(frozen=True)
class KeptFrame:
    """A snapshot's frame as rendered: the image in [0, 1] (detector rows x columns), the pose and the breath."""

    image: np.ndarray
    T_webcam_from_phantom: np.ndarray
    inspired: float | None
    zoom: int


class Snapshotter:
    """Called with each ShownFrame; writes `out_dir/NN-name.png` the first time each moment happens.

    A snapshot is a side task: it runs on the render worker, so a write the disk refuses
    (full, read-only) is logged once, counted in `failures`, and tried again at the next hit
    of that moment after `RETRY_S` - never raised into the renderer.

    With `background`, the render worker only picks the frame (and copies its pixels); the PNG
    is encoded and written on a thread of its own at a lower priority (`WRITER_NICE`), because
    the encoding (about 25 cpu ms for a 1280 x 1024 screen) and the fsync (30-110 ms in all on a
    busy two-core machine) would otherwise hold up the next live frame. A write refused there
    is handled as above: the moment is taken again at its next hit after `RETRY_S`. `flush()`
    waits for the writes still queued.
    """

    #: After a refused write, wait this long before writing a snapshot again (s).
    RETRY_S = 5.0
    #: The background writer runs this many nice steps below the render worker: a snapshot may
    #: be on disk a little later, a live frame must not be (nice steps).
    WRITER_NICE = 10

    def __init__(self, out_dir: Path, moments: list[Moment], reserve_mb: float = 0.0, *, background: bool = False):
        self.out_dir = Path(out_dir)
        #: Free space (MiB) below which no snapshot is written: it is the dose ledger's.
        self.reserve_mb = reserve_mb
        self.moments = moments
        self.taken: dict[str, Path] = {}
        self.failures = 0
        self.problem: str | None = None
        self._retry_at = 0.0
        self._alarm_seen = False
        self._digests: set[bytes] = set()
        #: The breathing pair's frames as rendered (image, pose, breath), for checking the dome's motion.
        self.kept: dict[str, KeptFrame] = {}
        self._lock = threading.Lock()       # taken, kept, the digests and the failure record, shared with the writer
        self._queue: queue.Queue | None = queue.Queue() if background else None
        self._writer: threading.Thread | None = None

    def __call__(self, frame) -> None:
        try:
            self._look(frame)
        except (OSError, FluorosimError, ValueError) as e:
            self._failed(e)

    def _failed(self, e: Exception) -> None:
        with self._lock:
            self.failures += 1
            self._retry_at = time.monotonic() + self.RETRY_S
            if self.problem is None:
                log.warning("snapshot not written (rendering and dose recording go on): %s", e)
            self.problem = str(e)

    def flush(self) -> None:
        """Wait until every snapshot taken so far is on disk (or has failed); ends the writer."""
        if self._queue is not None and self._writer is not None:
            self._queue.put(None)
            self._writer.join()
            self._writer = None

    def _write_queued(self) -> None:
        try:
            tid = threading.get_native_id()
            os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + self.WRITER_NICE)
        except (AttributeError, OSError):
            pass            # elsewhere than Linux the writer keeps the render worker's priority
        assert self._queue is not None
        while (item := self._queue.get()) is not None:
            name, path, rgb, digest = item
            try:
                write_png(path, rgb)
            except (OSError, FluorosimError, ValueError) as e:
                with self._lock:            # not taken after all: the moment's next frame is tried
                    self.taken.pop(name, None)
                    self.kept.pop(name, None)
                    self._digests.discard(digest)
                self._failed(e)
            else:
                with self._lock:
                    self.problem = None
                log.info("snapshot %s: %s", name, path)

    def _look(self, frame) -> None:
        if time.monotonic() < self._retry_at:
            return
        # One snapshot per frame, and never the same pixels twice: the first live frame is
        # also at zoom 1, and one inverted frame may also be the breath hold, but a contact
        # sheet showing one picture under two names shows neither moment. The next frame
        # that shows the moment is a frame later.
        alarm = bool(getattr(frame.state, "alarm_sounding", False))
        if alarm:
            self._alarm_seen = True
        elif self._alarm_seen and "alarm-reset" not in self.taken:
            # The alarm's reset is the first frame without it after it sounded.
            if self._take(len(self.moments), Moment("alarm-reset", "alarm reset", lambda f: True), frame):
                return
        for i, m in enumerate(self.moments):
            if m.name in self.taken:
                continue
            try:
                hit = m.when(frame)
            except (AttributeError, TypeError, IndexError):
                hit = False
            if hit and self._take(i, m, frame):
                return

    def _take(self, index: int, moment: Moment, frame) -> bool:
        rgb = np.ascontiguousarray(frame.rgb_source())
        digest = hashlib.sha256(rgb.tobytes()).digest()
        if digest in self._digests:
            return False
        path = self.out_dir / f"{index:02d}-{moment.name}.png"
        check_reserve(self.out_dir, self.reserve_mb, f"snapshot {path.name}")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if self._queue is None:
            write_png(path, rgb)
        T = _pose_matrix(frame) if moment.name in KEPT else None
        with self._lock:
            self.taken[moment.name] = path
            if T is not None and frame.image is not None:
                self.kept[moment.name] = KeptFrame(np.array(frame.image, dtype=np.float32), T, frame.inspired,
                                                   int(frame.state.zoom))
            self._digests.add(digest)
            if self._queue is None:
                self.problem = None
        if self._queue is None:
            log.info("snapshot %s: %s", moment.name, path)
            return True
        if self._writer is None:
            self._writer = threading.Thread(target=self._write_queued, name="fluorosim-snapshots", daemon=True)
            self._writer.start()
        # A copy: the screen the pixels came from is drawn over by the next frame.
        self._queue.put((moment.name, path, rgb.copy(), digest))
        return True

    def captions(self) -> dict[str, str]:
        out = {m.name: m.caption for m in self.moments}
        out["alarm-reset"] = "alarm reset"
        return out

    def missing(self) -> list[str]:
        """The moments never seen on screen, in contact-sheet order: a session too short, a
        machine too slow for a breath to settle, or a case without breathing. The demo names
        them, so an absent picture is never taken for one that was looked at."""
        return [name for name in self.captions() if name not in self.taken]


def alarm_banner_shown(rgb: np.ndarray) -> bool:
    """Whether the alarm's red banner is on screen: it flashes, and a snapshot named for the
    alarm taken in its dark half shows no alarm at all. Read from the pixels, as a person
    would, with room for a display's colour depth (at least 0.5 % of the lower third red)."""
    lower = np.asarray(rgb)[2 * rgb.shape[0] // 3:].astype(np.int16)
    red = (lower[..., 0] > 180) & (lower[..., 1] < 50) & (lower[..., 2] < 50)
    return bool(red.mean() > 0.005)


def write_png(path: Path, rgb: np.ndarray) -> Path:
    ok, data = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{path}: could not encode the image as PNG")
    return write_atomic(path, data.tobytes())


def contact_sheet(images: list[tuple[str, np.ndarray]], *, columns: int = 4, tile_width: int = 320,
                  label_height: int = 24) -> np.ndarray:
    """The images (RGB uint8) as a grid of tiles `tile_width` wide, each captioned below; RGB uint8."""
    if not images:
        raise ValueError("no images for a contact sheet")
    h0, w0 = images[0][1].shape[:2]
    tile_height = max(1, round(h0 * tile_width / w0))
    rows = math.ceil(len(images) / columns)
    cell_h = tile_height + label_height
    sheet = np.full((rows * cell_h, min(columns, len(images)) * tile_width, 3), 24, np.uint8)
    for k, (caption, rgb) in enumerate(images):
        r, c = divmod(k, columns)
        tile = cv2.resize(rgb, (tile_width, tile_height), interpolation=cv2.INTER_AREA)
        y, x = r * cell_h, c * tile_width
        sheet[y:y + tile_height, x:x + tile_width] = tile
        cv2.putText(sheet, caption[:40], (x + 6, y + tile_height + label_height - 7), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5, (235, 235, 235), 1, cv2.LINE_AA)
    return sheet


def read_png(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"{path}: not a readable image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
