"""Snapshots of key moments of a session, read back from the display, and a contact sheet of them.

The demo (and anyone checking the appliance) wants evidence of what was on screen: the
first live image, each zoom level, collimation, inversion, the +-90 degree rolls, a
saved image, the breath hold, the 5-minute alarm and its reset. Each moment is a
predicate over the frame just written; the first frame that satisfies it is read back
from the framebuffer (what the trainee saw, overlays and all) and written as a PNG.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..atomic_file import write_atomic
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


def key_moments() -> list[Moment]:
    """The moments the demo shows, in the order they appear on the contact sheet."""
    moments = [Moment("first-live", "first live image", _live)]
    for z in (1, 2, 3, 4):
        moments.append(Moment(f"zoom-{z}", f"zoom {z}", lambda f, z=z: _live(f) and f.state.zoom == z))  # type: ignore[misc]
    moments += [
        Moment("collimated", "collimator closed in", lambda f: _live(f) and _collimated(f)),
        Moment("inverted", "inverted", lambda f: _live(f) and bool(f.state.invert)),
        Moment("roll-plus-90", "roll +90 degrees", lambda f: _live(f) and (_pose_roll(f) or 0) > 75),
        Moment("roll-minus-90", "roll -90 degrees", lambda f: _live(f) and (_pose_roll(f) or 0) < -75),
        Moment("breath-hold", "breath hold", lambda f: _live(f) and bool(f.state.breath_hold)),
        Moment("saved", "image saved", lambda f: bool(f.saved_flash)),
        Moment("alarm", "5-minute alarm", lambda f: bool(f.state.alarm_sounding)),
        Moment("last-image-hold", "last-image hold", lambda f: not f.live and f.image is not None
               and not f.state.fluoro_on),
        Moment("tracking-lost", "tracking lost", lambda f: any("tracking lost" in b for b in f.banners)),
    ]
    return moments


class Snapshotter:
    """Called with each ShownFrame; writes `out_dir/NN-name.png` the first time each moment happens."""

    def __init__(self, out_dir: Path, moments: list[Moment]):
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.moments = moments
        self.taken: dict[str, Path] = {}
        self._alarm_seen = False

    def __call__(self, frame) -> None:
        for i, m in enumerate(self.moments):
            if m.name in self.taken:
                continue
            try:
                hit = m.when(frame)
            except (AttributeError, TypeError, IndexError):
                hit = False
            if hit:
                self._take(i, m, frame)
        # The alarm's reset is the first frame without it after it sounded.
        alarm = bool(getattr(frame.state, "alarm_sounding", False))
        if alarm:
            self._alarm_seen = True
        elif self._alarm_seen and "alarm-reset" not in self.taken:
            self._take(len(self.moments), Moment("alarm-reset", "alarm reset", lambda f: True), frame)

    def _take(self, index: int, moment: Moment, frame) -> None:
        rgb = frame.rgb_source()
        path = self.out_dir / f"{index:02d}-{moment.name}.png"
        write_png(path, rgb)
        self.taken[moment.name] = path
        log.info("snapshot %s: %s", moment.name, path)

    def captions(self) -> dict[str, str]:
        out = {m.name: m.caption for m in self.moments}
        out["alarm-reset"] = "alarm reset"
        return out


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
