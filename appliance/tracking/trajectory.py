"""Scripted paths of the phantom as the webcam sees it: JSONL keyframes, interpolated with slerp.

One keyframe per line (blank lines and lines starting with # are skipped):

    {"t": 2.0, "position_mm": [0, 0, 550], "roll_deg": 45, "tilt_deg": 0, "yaw_deg": 10}

`position_mm` is the phantom origin in the webcam frame; the angles turn the phantom from
the home pose, where the webcam looks straight down at the box's top face with phantom x
along image columns: roll about phantom x (the box's long axis, patient rolled), tilt
about phantom y, yaw about the viewing direction. A keyframe may instead give
`T_webcam_from_phantom` (4x4, mm). Between keyframes the rotation is slerped and the
position interpolated linearly; the path loops after the last keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from drivers.jsonl import json_lines

from ..config import limits
from ..errors import FluorosimError
from ..geometry import make_transform, rigid_problem, rotation_about

#: Home orientation: the webcam looks down at the top face (phantom z toward the camera).
R_HOME = np.diag([1.0, -1.0, -1.0])


def pose_from_angles(position_mm, roll_deg: float = 0.0, tilt_deg: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """T_webcam_from_phantom for the phantom at `position_mm`, turned from the home pose (degrees)."""
    R = (rotation_about((0, 0, 1), np.radians(yaw_deg)) @ R_HOME
         @ rotation_about((0, 1, 0), np.radians(tilt_deg)) @ rotation_about((1, 0, 0), np.radians(roll_deg)))
    return make_transform(R, position_mm)


@dataclass
class Trajectory:
    """T_webcam_from_phantom as a function of time (s), looping over its keyframes."""

    times: np.ndarray
    positions: np.ndarray
    rotations: Rotation
    loop: bool = True

    @classmethod
    def from_poses(cls, times, poses, loop: bool = True) -> Trajectory:
        poses = np.asarray(poses, dtype=np.float64)
        return cls(np.asarray(times, dtype=np.float64), poses[:, :3, 3].copy(),
                   Rotation.from_matrix(poses[:, :3, :3]), loop)

    @classmethod
    def still(cls, T: np.ndarray) -> Trajectory:
        return cls.from_poses([0.0], [T])

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    def still_spans(self) -> list[tuple[float, float]]:
        """The spans of one pass (s, path time) where the phantom stands still: between two
        consecutive keyframes of the same pose (runs of them joined). What a benchmark takes
        for "the C-arm has come to rest", free of the tracker's filter and jitter."""
        spans: list[tuple[float, float]] = []
        Rm = self.rotations.as_matrix()
        for i in range(len(self.times) - 1):
            same = (np.allclose(self.positions[i], self.positions[i + 1], atol=1e-9)
                    and np.allclose(Rm[i], Rm[i + 1], atol=1e-12))
            if not same or self.times[i + 1] <= self.times[i]:
                continue
            if spans and spans[-1][1] == self.times[i]:
                spans[-1] = (spans[-1][0], float(self.times[i + 1]))
            else:
                spans.append((float(self.times[i]), float(self.times[i + 1])))
        return spans

    def __call__(self, t: float) -> np.ndarray:
        if len(self.times) == 1:
            return make_transform(self.rotations.as_matrix()[0], self.positions[0])
        t0 = self.times[0]
        if self.loop and self.duration > 0:
            t = t0 + (t - t0) % self.duration
        t = float(np.clip(t, t0, self.times[-1]))
        i = int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2))
        span = self.times[i + 1] - self.times[i]
        a = 0.0 if span <= 0 else (t - self.times[i]) / span
        R = Slerp([0.0, 1.0], self.rotations[i:i + 2])([a]).as_matrix()[0]
        p = (1 - a) * self.positions[i] + a * self.positions[i + 1]
        return make_transform(R, p)


def _finite_number(k: dict, field: str, where: str, low: float, high: float, unit: str) -> float:
    value = k.get(field, 0.0)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
        raise FluorosimError(f"{where}: '{field}' must be a number from {low:g} to {high:g} {unit} (got {value!r})")
    return float(value)


def load_trajectory(path: str | Path) -> Trajectory:
    """Read a JSONL keyframe file, or raise FluorosimError naming the file and line."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise FluorosimError(f"{path}: trajectory file does not exist; check devices.camera.trajectory") from None
    except OSError as e:
        raise FluorosimError(f"{path}: cannot read the trajectory ({e.strerror or e})") from None
    try:
        if b"\x00" in raw:
            raise UnicodeError("binary")
        lines = raw.decode("utf-8").splitlines()
    except UnicodeError:
        raise FluorosimError(f"{path}: is not UTF-8 text; a trajectory is JSONL, one keyframe object per line") from None
    times: list[float] = []
    poses: list[np.ndarray] = []
    for where, k in json_lines(lines, str(path), FluorosimError, "; write one keyframe object per line"):
        if not isinstance(k, dict) or isinstance(k.get("t"), bool) or not isinstance(k.get("t"), (int, float)):
            raise FluorosimError(f'{where}: a keyframe needs a number "t" (s), e.g. {{"t": 0, "position_mm": [0, 0, 550]}}')
        _finite_number(k, "t", where, -limits.MAX_SCRIPT_TIME_S, limits.MAX_SCRIPT_TIME_S, "s")
        unknown = set(k) - {"t", "position_mm", "roll_deg", "tilt_deg", "yaw_deg", "T_webcam_from_phantom"}
        if unknown:
            raise FluorosimError(f"{where}: unknown key(s) {', '.join(sorted(unknown))}; allowed: t, position_mm, "
                                 "roll_deg, tilt_deg, yaw_deg, T_webcam_from_phantom")
        try:
            if "T_webcam_from_phantom" in k:
                T = np.asarray(k["T_webcam_from_phantom"], dtype=np.float64)
                problem = rigid_problem(T)
                if problem:
                    raise ValueError(f"T_webcam_from_phantom {problem}")
            else:
                pos = np.asarray(k.get("position_mm"), dtype=np.float64)
                if pos.shape != (3,):
                    raise ValueError("position_mm must be three numbers (mm)")
                angles = [_finite_number(k, a, where, -360.0, 360.0, "degrees") for a in ("roll_deg", "tilt_deg", "yaw_deg")]
                T = pose_from_angles(pos, *angles)
        except (TypeError, ValueError) as e:
            raise FluorosimError(f"{where}: {e}") from None
        if not limits.finite(T) or np.linalg.norm(T[:3, 3]) > limits.MAX_WEBCAM_DISTANCE_MM:
            raise FluorosimError(f"{where}: the phantom must be within {limits.MAX_WEBCAM_DISTANCE_MM:g} mm of the webcam "
                                 "(every number finite)")
        if T[2, 3] <= 0:
            raise FluorosimError(f"{where}: the phantom must be in front of the webcam (z > 0 mm)")
        if times and k["t"] <= times[-1]:
            raise FluorosimError(f"{where}: t = {k['t']} s does not increase (previous keyframe t = {times[-1]} s)")
        times.append(float(k["t"]))
        poses.append(T)
    if not poses:
        raise FluorosimError(f"{path}: holds no keyframes")
    return Trajectory.from_poses(times, poses)


def random_poses(rng: np.random.Generator, n: int, distance_mm=(400.0, 700.0), roll_deg=(-90.0, 90.0),
                 tilt_deg=(-20.0, 20.0), yaw_deg=(-30.0, 30.0), offset_mm: float = 40.0) -> list[np.ndarray]:
    """`n` poses of the phantom in the range a trainee uses (uniform in each range)."""
    out = []
    for _ in range(n):
        z = rng.uniform(*distance_mm)
        out.append(pose_from_angles([rng.uniform(-offset_mm, offset_mm), rng.uniform(-offset_mm, offset_mm), z],
                                    rng.uniform(*roll_deg), rng.uniform(*tilt_deg), rng.uniform(*yaw_deg)))
    return out
