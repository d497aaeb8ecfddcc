"""Levenberg-Marquardt fit of fx, fy, cx, cy, (k1, k2, p1, p2, k3) and one phantom pose per image.

All images are fitted jointly on reprojection error with scipy's `least_squares`
(method 'lm'); residuals and their exact Jacobian come from `cv2.projectPoints`, the same
projection model the renderer uses. One-sigma uncertainties come from the Jacobian at the
solution, cov = s^2 (J^T J)^-1 with s^2 the residual variance. A detection farther than
`final_gate_px` from its ball's reprojection is dropped and the fit repeated, so one bad
pairing cannot pull the result; an image left with too few balls is rejected with its
reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from ..errors import FluorosimError

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass
class View:
    """The identified balls of one image."""

    name: str
    object_points: np.ndarray  # (m, 3) ball centres, phantom frame (mm)
    image_points: np.ndarray   # (m, 2) blob centres (pixels)
    sphere_index: np.ndarray   # (m,)
    T_start: np.ndarray        # pose guess, 4x4
    radii_mm: np.ndarray | None = None  # (m,) ball radii, to model where a shadow's centroid falls


@dataclass
class ViewResult:
    name: str
    T_xray_from_phantom: np.ndarray
    used: int                  # balls in the final fit
    dropped: int               # detections refused as outliers
    rms_px: float
    worst_px: float
    residuals_px: np.ndarray   # (used, 2)
    sphere_index: np.ndarray   # (used,) the balls kept


@dataclass
class Fit:
    K: np.ndarray
    dist: np.ndarray
    sigma: dict[str, float]     # one-sigma uncertainty of each intrinsic (pixels or dimensionless)
    views: list[ViewResult]
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (image, reason)
    fixed: frozenset[str] = frozenset()  # intrinsics held at their starting value
    ssr: float = 0.0          # sum of squared residuals (pixels^2)
    n_residuals: int = 0      # residual components (2 per ball)
    n_params: int = 0         # fitted parameters

    @property
    def rms_px(self) -> float:
        r = np.concatenate([v.residuals_px for v in self.views])
        return float(np.sqrt((r ** 2).sum(axis=1).mean()))

    @property
    def worst_px(self) -> float:
        return max(v.worst_px for v in self.views)


def centroid_offsets(K: np.ndarray, dist: np.ndarray, T_xray_from_phantom: np.ndarray, centres: np.ndarray,
                     radii_mm: np.ndarray, samples: int = 15) -> np.ndarray:
    """(m, 2) attenuation-weighted centroid of each ball's distorted shadow minus the projection
    of its centre (pixels).

    A sphere seen off the axis casts an ellipse whose centroid is not the projected centre,
    and the distortion stretches its outer side more than its inner one. Both are integrated
    exactly: the undistorted image plane around each ball is sampled on a grid wide enough
    for the ellipse, each sample weighted by the true chord its ray cuts through the ball,
    2 sqrt(R^2 - |C|^2 + (d.C)^2) for the unit ray d and centre C, and by the local area
    scale of the distortion (a pixel sees a stretched patch of the undistorted plane as a
    smaller one); the centroid is taken of the distorted sample positions.
    """
    P = centres @ T_xray_from_phantom[:3, :3].T + T_xray_from_phantom[:3, 3]
    x0, y0 = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2]
    # Half-width of the silhouette in the undistorted plane, with room for its radial stretch
    # (1 / cos^2 of the off-axis angle) and the cone's half-angle.
    reach = 1.1 * radii_mm / P[:, 2] * (1.0 + x0 ** 2 + y0 ** 2)
    a = (np.arange(samples) + 0.5) / samples * 2.0 - 1.0
    ax, ay = (g.reshape(-1) for g in np.meshgrid(a, a))
    qx = x0[:, None] + reach[:, None] * ax[None]
    qy = y0[:, None] + reach[:, None] * ay[None]
    norm = np.sqrt(qx ** 2 + qy ** 2 + 1.0)
    along = (qx * P[:, 0:1] + qy * P[:, 1:2] + P[:, 2:3]) / norm
    chord = 2.0 * np.sqrt(np.clip(radii_mm[:, None] ** 2 - (P ** 2).sum(axis=1)[:, None] + along ** 2, 0.0, None))
    flat = np.stack([qx.reshape(-1), qy.reshape(-1), np.ones(qx.size)], axis=1)
    img, _ = cv2.projectPoints(flat, np.zeros(3), np.zeros(3), K, dist)
    img = img.reshape(len(P), samples, samples, 2)
    # The samples form a regular grid in the undistorted plane, so the distortion's local
    # area scale is the cross product of the grid's steps in the image (one projection, not
    # three: a grid phantom sends thousands of balls through here at every fit).
    du = np.gradient(img, axis=2)
    dv = np.gradient(img, axis=1)
    area = np.abs(du[..., 0] * dv[..., 1] - du[..., 1] * dv[..., 0]).reshape(len(P), -1)
    img = img.reshape(len(P), -1, 2)
    weight = chord * area
    centroid = (img * weight[..., None]).sum(axis=1) / weight.sum(axis=1)[:, None]
    centre, _ = cv2.projectPoints(np.concatenate([x0[:, None], y0[:, None], np.ones((len(P), 1))], axis=1),
                                  np.zeros(3), np.zeros(3), K, dist)
    return centroid - centre.reshape(-1, 2)


def _pack(K, dist, poses) -> np.ndarray:
    head = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]
    tail = []
    for T in poses:
        tail.extend(cv2.Rodrigues(T[:3, :3])[0].reshape(3))
        tail.extend(T[:3, 3])
    return np.array(head + tail, dtype=np.float64)


def _unpack(p, n_views):
    K = np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]])
    dist = p[4:9].copy()
    poses = []
    for i in range(n_views):
        r, t = p[9 + 6 * i: 12 + 6 * i], p[12 + 6 * i: 15 + 6 * i]
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(r)[0]
        T[:3, 3] = t
        poses.append(T)
    return K, dist, poses


def _residuals_and_jacobian(p, views):
    n = len(views)
    K, dist, _ = _unpack(p, n)
    rows = sum(2 * len(v.object_points) for v in views)
    res = np.empty(rows)
    jac = np.zeros((rows, 9 + 6 * n))
    at = 0
    for i, v in enumerate(views):
        r, t = p[9 + 6 * i: 12 + 6 * i], p[12 + 6 * i: 15 + 6 * i]
        uv, J = cv2.projectPoints(v.object_points.reshape(-1, 1, 3), r, t, K, dist)
        m = 2 * len(v.object_points)
        res[at:at + m] = (uv.reshape(-1, 2) - v.image_points).reshape(-1)
        # projectPoints' Jacobian columns: rvec(3), tvec(3), fx, fy, cx, cy, dist(5).
        jac[at:at + m, 0:4] = J[:, 6:10]
        jac[at:at + m, 4:9] = J[:, 10:15]
        jac[at:at + m, 9 + 6 * i: 15 + 6 * i] = J[:, 0:6]
        at += m
    return res, jac


def _solve(views, K, dist, poses, fixed: frozenset[str]):
    full0 = _pack(K, dist, poses)
    free = np.array([i for i in range(len(full0)) if i >= len(INTRINSIC_NAMES) or INTRINSIC_NAMES[i] not in fixed])
    cache = {}

    def full(x):
        p = full0.copy()
        p[free] = x
        return p

    def fun(x):
        cache["r"], J = _residuals_and_jacobian(full(x), views)
        cache["J"] = J[:, free]
        cache["x"] = x.copy()
        return cache["r"]

    def jac(x):
        if "x" not in cache or not np.array_equal(cache["x"], x):
            fun(x)
        return cache["J"]

    sol = least_squares(fun, full0[free], jac=jac, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
    return full(sol.x), sol.fun, free


def fit_views(views: list[View], K0: np.ndarray, dist0: np.ndarray, final_gate_px: float,
              min_spheres: int, fixed: frozenset[str] = frozenset()) -> Fit:
    """Fit intrinsics, distortion and poses to `views`; drop outliers and starved views.

    Intrinsics named in `fixed` (of INTRINSIC_NAMES) keep their value from K0 / dist0.
    """
    views = [View(v.name, v.object_points.copy(), v.image_points.copy(), v.sphere_index.copy(), v.T_start,
                  None if v.radii_mm is None else v.radii_mm.copy()) for v in views]
    dropped = {v.name: 0 for v in views}
    rejected: list[tuple[str, str]] = []
    K, dist, poses = K0.copy(), np.asarray(dist0, float).copy(), [v.T_start for v in views]
    # At most one pair per view goes per round, so every pair may need its own round.
    for _ in range(sum(len(v.object_points) for v in views) + 1):
        if not views:
            break
        x, fun, free = _solve(views, K, dist, poses, fixed)
        K, dist, poses = _unpack(x, len(views))
        res = fun.reshape(-1, 2)
        norms = np.hypot(res[:, 0], res[:, 1])
        changed = False
        at, keep_views, keep_poses = 0, [], []
        for v, T in zip(views, poses):
            m = len(v.object_points)
            bad = norms[at:at + m] > final_gate_px
            at += m
            if bad.any():
                # Drop only the worst per round: one wrong pairing inflates its neighbours' residuals too.
                worst = np.argmax(norms[at - m:at])
                keep = np.ones(m, bool)
                keep[worst] = False
                v.object_points, v.image_points, v.sphere_index = v.object_points[keep], v.image_points[keep], v.sphere_index[keep]
                if v.radii_mm is not None:
                    v.radii_mm = v.radii_mm[keep]
                dropped[v.name] += 1
                changed = True
            if len(v.object_points) < min_spheres:
                rejected.append((v.name, f"only {len(v.object_points)} balls agree with the fit (need {min_spheres})"))
                changed = True
                continue
            keep_views.append(v)
            keep_poses.append(T)
        views, poses = keep_views, keep_poses
        if not changed:
            break
    else:
        raise FluorosimError("the calibration fit did not settle while removing outliers; check the images")
    if not views:
        return Fit(K0, np.asarray(dist0, float), {}, [], rejected, fixed)
    if all(v.radii_mm is not None for v in views):
        # The distortion stretches a shadow more on its outer side, so its centroid lies a
        # little outside the projected centre, more for big balls than small ones. The two
        # plates' balls differ in size, and the depth (hence fx) rests on the tiny difference
        # in magnification between the plates, so this bias of hundredths of a pixel costs
        # a tenth of a percent of fx unless it is modelled: twice, remove the offset the
        # current fit predicts from each detection and fit again.
        measured = [v.image_points.copy() for v in views]
        for _ in range(2):
            for v, T, uv in zip(views, poses, measured):
                if v.radii_mm is not None:      # every view has them (checked above)
                    v.image_points = uv - centroid_offsets(K, dist, T, v.object_points, v.radii_mm)
            x, _, _ = _solve(views, K, dist, poses, fixed)
            K, dist, poses = _unpack(x, len(views))

    x = _pack(K, dist, poses)
    res, J = _residuals_and_jacobian(x, views)
    free = np.array([i for i in range(len(x)) if i >= len(INTRINSIC_NAMES) or INTRINSIC_NAMES[i] not in fixed])
    J = J[:, free]
    dof = max(len(res) - J.shape[1], 1)
    s2 = float(res @ res) / dof
    try:
        cov = np.linalg.inv(J.T @ J) * s2
        where = {int(k): j for j, k in enumerate(free)}
        sigma = {name: (float(np.sqrt(max(cov[where[i], where[i]], 0.0))) if i in where else 0.0)
                 for i, name in enumerate(INTRINSIC_NAMES)}
    except np.linalg.LinAlgError:
        sigma = {name: float("inf") for name in INTRINSIC_NAMES}
    results, at = [], 0
    for v, T in zip(views, poses):
        m = len(v.object_points)
        r = res[2 * at: 2 * (at + m)].reshape(-1, 2)
        at += m
        n = np.hypot(r[:, 0], r[:, 1])
        results.append(ViewResult(v.name, T, m, dropped[v.name], float(np.sqrt((n ** 2).mean())), float(n.max()), r,
                                  v.sphere_index.copy()))
    return Fit(K, dist, sigma, results, rejected, fixed, float(res @ res), len(res), J.shape[1])
