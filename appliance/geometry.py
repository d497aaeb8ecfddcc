"""Rigid transforms and the pinhole camera model shared by tracking, calibration and rendering.

Conventions (see DESIGN.md): lengths in mm; a transform is a 4x4 matrix named
`T_<to>_from_<from>`; the `xray` and `webcam` frames follow OpenCV's camera convention
(+z along the principal ray, +x along detector columns, +y along detector rows).
"""

from __future__ import annotations

import numpy as np

#: Tolerance for calling a matrix rigid: |R^T R - I| and |det R - 1| below this, and a last
#: row of exactly 0 0 0 1 within it. Profiles carry 6+ significant digits, so 1e-4 accepts
#: a rounded rotation and still rejects any real scale or shear (1e-4 is 0.01 %).
RIGID_TOLERANCE = 1e-4


def rigid_problem(matrix, tol: float = RIGID_TOLERANCE) -> str | None:
    """Why `matrix` is not a rigid 4x4 transform, or None when it is."""
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4):
        return f"must be a 4x4 matrix, got shape {m.shape}"
    if not np.all(np.isfinite(m)):
        return "must contain only finite numbers"
    if np.max(np.abs(m[3] - [0.0, 0.0, 0.0, 1.0])) > tol:
        return "last row must be 0 0 0 1"
    r = m[:3, :3]
    if np.max(np.abs(r.T @ r - np.eye(3))) > tol:
        return f"rotation part is not orthonormal (tolerance {tol:g})"
    if abs(np.linalg.det(r) - 1.0) > tol:
        return "rotation part must have determinant +1 (a mirror is not a rigid motion)"
    return None


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform, without a general matrix inverse."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def make_transform(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map an (..., 3) array of points through T."""
    p = np.asarray(points, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def rotation_about(axis, angle_rad: float) -> np.ndarray:
    """3x3 rotation by `angle_rad` about `axis` (right-handed, Rodrigues)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * (K @ K)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle in degrees of the rotation taking R_b to R_a (both 3x3 or 4x4)."""
    R = np.asarray(R_a)[:3, :3] @ np.asarray(R_b)[:3, :3].T
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def camera_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def project(K: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Undistorted pinhole projection of (..., 3) camera-frame points to (..., 2) pixels (u, v)."""
    p = np.asarray(points_cam, dtype=float)
    uvw = p @ np.asarray(K).T
    return uvw[..., :2] / uvw[..., 2:3]
