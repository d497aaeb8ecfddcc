"""Where the beam was for one image: the geometry a `view` record keeps, and what it shows.

A view record (ledger event kind `view`) holds the pose `T_xray_from_ct` of the image, the
zoom level and blade openings, the case time of the 4D phase shown, and the camera model
it was rendered with (intrinsics, distortion, detector size), so a verdict can be worked
out again from the ledger alone, whatever profiles are installed later.

The field model is the renderer's (appliance/xray/renderer.py): at zoom z the focal
lengths are scaled by fov[0]/fov[z-1]; the field is centred on the detector's centre
pixel; a point lies in it when it is between the focal spot and the detector and its projection (OpenCV's model, with the intensifier's
distortion) falls inside the blade rectangle (h x v mm at the detector plane) and, on an
image intensifier, inside the circle of diameter fov[z-1]. The central ray is the ray
through the detector's centre pixel; "centred within d mm" is the distance of the target's
centre from that ray, at the target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config.exercise import Target
from ..console import dose

#: Decimal places kept in a view record: 1e-6 of a rotation entry, 1 micrometre of translation.
ROUND_ROTATION = 6
ROUND_MM = 3


def camera_of(fluoroscope) -> dict:
    """The camera model of a (rendered) fluoroscope profile, as a view record keeps it."""
    i, det = fluoroscope.intrinsics, fluoroscope.detector
    return {"fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy, "distortion": [float(c) for c in i.distortion.coefficients()],
            "columns": det.columns, "rows": det.rows, "pixel_pitch_mm": det.pixel_pitch_mm,
            "circular": det.kind == "image_intensifier", "fovs_mm": [z.fov_mm for z in fluoroscope.zoom_levels],
            "sid_mm": fluoroscope.geometry.source_to_image_mm}


def view_detail(fluoroscope, T_xray_from_ct, zoom: int, collimation_mm, t_case_s: float | None, camera: dict | None = None) -> dict:
    """The detail of a `view` record for an image rendered with `fluoroscope` at this pose and
    these settings (`collimation_mm` = (h, v) blade openings at the detector, mm)."""
    T = np.asarray(T_xray_from_ct, dtype=float)
    rows = [[round(float(T[r, c]), ROUND_ROTATION if c < 3 else ROUND_MM) for c in range(4)] for r in range(3)]
    fov = fluoroscope.zoom_levels[zoom - 1].fov_mm
    h, v = (fov, fov) if collimation_mm is None else (min(collimation_mm[0], fov), min(collimation_mm[1], fov))
    return {"T_xray_from_ct": rows, "zoom": int(zoom), "fov_mm": fov, "collimation_h_mm": float(h), "collimation_v_mm": float(v),
            "field_area_cm2": dose.field_area_reference_cm2(fluoroscope, zoom, (h, v)),
            "t_case_s": None if t_case_s is None else round(float(t_case_s), 3), "camera": camera or camera_of(fluoroscope)}


@dataclass(frozen=True)
class Beam:
    """One view's geometry, ready to ask what it shows."""

    T_xray_from_ct: np.ndarray
    zoom: int
    fov_mm: float
    collimation_mm: tuple[float, float]
    field_area_cm2: float
    t_case_s: float | None
    camera: dict

    @classmethod
    def of(cls, detail: dict) -> Beam:
        T = np.eye(4)
        T[:3, :] = np.asarray(detail["T_xray_from_ct"], dtype=float)
        return cls(T, int(detail["zoom"]), float(detail["fov_mm"]),
                   (float(detail["collimation_h_mm"]), float(detail["collimation_v_mm"])),
                   float(detail["field_area_cm2"]), detail.get("t_case_s"), detail["camera"])

    @property
    def collimated(self) -> bool:
        return min(self.collimation_mm) < self.fov_mm - 1e-9

    def _centre_px(self) -> tuple[float, float]:
        c = self.camera
        return (c["columns"] - 1) / 2.0, (c["rows"] - 1) / 2.0

    def central_ray(self) -> np.ndarray:
        """Unit direction (xray frame) of the ray through the detector's centre pixel."""
        c = self.camera
        u0, v0 = self._centre_px()
        d = np.array([(u0 - c["cx"]) / c["fx"], (v0 - c["cy"]) / c["fy"], 1.0])
        return d / np.linalg.norm(d)

    def beam_direction_ct(self) -> np.ndarray:
        """The central ray's direction, focal spot toward the detector, in the CT frame (unit)."""
        return self.T_xray_from_ct[:3, :3].T @ self.central_ray()

    def angle_to_deg(self, direction) -> float:
        d = np.asarray(direction, dtype=float)
        d = d / np.linalg.norm(d)
        return float(np.degrees(np.arccos(np.clip(self.beam_direction_ct() @ d, -1.0, 1.0))))

    def off_axis_mm(self, point_ct) -> float:
        """Distance (mm) of a CT point from the central ray."""
        p = self.T_xray_from_ct[:3, :3] @ np.asarray(point_ct, dtype=float) + self.T_xray_from_ct[:3, 3]
        d = self.central_ray()
        return float(np.linalg.norm(p - (p @ d) * d))

    def detector_mm(self, points_ct) -> np.ndarray:
        """(n, 2) offsets (mm, at the detector plane, this zoom) of the points' images from the
        field centre; NaN for points not between the focal spot and the detector (only those are imaged)."""
        import cv2

        pts = np.atleast_2d(np.asarray(points_ct, dtype=float))
        p = pts @ self.T_xray_from_ct[:3, :3].T + self.T_xray_from_ct[:3, 3]
        c = self.camera
        s = c["fovs_mm"][0] / c["fovs_mm"][self.zoom - 1]
        K = np.array([[c["fx"] * s, 0, c["cx"]], [0, c["fy"] * s, c["cy"]], [0, 0, 1.0]])
        out = np.full((len(p), 2), np.nan)
        front = (p[:, 2] > 1e-6) & (p[:, 2] < c["sid_mm"])
        if front.any():
            uv, _ = cv2.projectPoints(p[front].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                      np.asarray(c["distortion"], dtype=float))
            u0, v0 = self._centre_px()
            pitch = c["pixel_pitch_mm"] * self.fov_mm / c["fovs_mm"][0]    # mm per pixel at this zoom
            out[front] = (uv.reshape(-1, 2) - [u0, v0]) * pitch
        return out

    def in_field(self, points_ct) -> np.ndarray:
        """(n,) bool: which points the collimated beam reaches on the detector."""
        d = self.detector_mm(points_ct)
        ok = np.isfinite(d).all(axis=1)
        dd = np.where(ok[:, None], d, 0.0)
        h, v = self.collimation_mm
        inside = (np.abs(dd[:, 0]) <= h / 2.0) & (np.abs(dd[:, 1]) <= v / 2.0)
        if self.camera["circular"]:
            inside &= np.hypot(dd[:, 0], dd[:, 1]) <= self.fov_mm / 2.0
        return ok & inside


def _box(target: Target) -> tuple[np.ndarray, np.ndarray]:
    box = target.box
    assert box is not None, "a target is a sphere or a box (ExerciseProfile.problems checks it)"
    return np.asarray(box.min_mm, dtype=float), np.asarray(box.max_mm, dtype=float)


def target_centre(target: Target) -> np.ndarray:
    if target.sphere is not None:
        return np.asarray(target.sphere.centre_mm, dtype=float)
    lo, hi = _box(target)
    return (lo + hi) / 2.0


#: Directions of the points on a sphere target that are checked besides its centre: the six
#: axis points and the eight diagonal ones.
_SPHERE_DIRECTIONS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
                              + [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
_SPHERE_DIRECTIONS /= np.linalg.norm(_SPHERE_DIRECTIONS, axis=1)[:, None]


def target_points(target: Target) -> np.ndarray:
    """Points standing for the target: its centre first, then the outline (a sphere's 14 surface
    points, a box's 8 corners and 6 face centres)."""
    c = target_centre(target)
    if target.sphere is not None:
        return np.vstack([c, c + target.sphere.radius_mm * _SPHERE_DIRECTIONS])
    lo, hi = _box(target)
    corners = [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    faces = []
    for axis in range(3):
        for end in (lo, hi):
            f = c.copy()
            f[axis] = end[axis]
            faces.append(f)
    return np.vstack([c, corners, faces])


@dataclass(frozen=True)
class Verdict:
    """What one image shows of one task's target, and whether it meets the task."""

    met: bool
    in_field: bool              # some of the target is in the field (not a blank image)
    whole_in_field: bool
    off_axis_mm: float
    angle_deg: float | None     # from the required beam direction; None when the task asks none
    reasons: tuple[str, ...]    # why it is not met, one short phrase each

    def as_dict(self) -> dict:
        return {"met": self.met, "in_field": self.in_field, "whole_in_field": self.whole_in_field,
                "off_axis_mm": round(self.off_axis_mm, 2),
                "angle_deg": None if self.angle_deg is None else round(self.angle_deg, 2), "reasons": list(self.reasons)}


def shows(beam: Beam, target: Target) -> bool:
    """Some of the target is in the field."""
    return bool(beam.in_field(target_points(target)).any())


def judge(task, beam: Beam) -> Verdict:
    """The verdict of one image (`beam`) on one task (appliance.config.exercise.Task)."""
    points = target_points(task.target)
    inside = beam.in_field(points)
    reasons = []
    in_field, whole = bool(inside.any()), bool(inside.all())
    if not in_field:
        reasons.append(f"{task.target.name} not in the field")
    req = task.field
    if req.whole_target and in_field and not whole:
        reasons.append(f"only part of the {task.target.name} in the field")
    off = beam.off_axis_mm(points[0])
    if req.centred_within_mm is not None and off > req.centred_within_mm:
        reasons.append(f"centre {off:.0f} mm off the central ray (at most {req.centred_within_mm:g})")
    if req.zoom is not None and beam.zoom not in req.zoom:
        reasons.append(f"zoom {beam.zoom} (use {', '.join(str(z) for z in req.zoom)})")
    if req.collimated and not beam.collimated:
        reasons.append("not collimated")
    if req.max_field_area_cm2 is not None and beam.field_area_cm2 > req.max_field_area_cm2:
        reasons.append(f"field {beam.field_area_cm2:.0f} cm2 (at most {req.max_field_area_cm2:g})")
    angle = None
    if task.projection is not None:
        angle = beam.angle_to_deg(task.projection.beam_direction)
        if angle > task.projection.within_deg:
            reasons.append(f"beam {angle:.0f} deg from the projection asked (at most {task.projection.within_deg:g})")
    ph = task.phase
    if ph is not None:
        t = beam.t_case_s
        if t is None or not ph.contains(t):
            when = "unknown" if t is None else f"{(t % ph.period_s) if ph.period_s else t:.1f} s"
            reasons.append(f"case time {when}, not {ph.label or 'the window'} ({ph.start_s:g}-{ph.end_s:g} s)")
    return Verdict(not reasons, in_field, whole, off, angle, tuple(reasons))

