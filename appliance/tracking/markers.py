"""ArUco marker detection and single-marker poses.

Corners follow OpenCV's ArUco order: top-left, top-right, bottom-right, bottom-left of the
printed black square, which in the marker's own frame (x right, y up, z out of the print
toward the viewer, origin at the centre) sit at (-s/2, s/2), (s/2, s/2), (s/2, -s/2),
(-s/2, -s/2) for side s in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import FluorosimError
from ..geometry import make_transform


def marker_corners(size_mm: float) -> np.ndarray:
    """(4, 3) corners of a marker of side `size_mm` in its own frame (mm), in ArUco order."""
    h = size_mm / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def aruco_dictionary(name: str):
    if not hasattr(cv2.aruco, name):
        raise FluorosimError(f"ArUco dictionary {name!r} is not known to OpenCV; use one of DICT_4X4_50 ... DICT_7X7_1000")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def to_gray(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


#: Side of the adaptive-threshold window (pixels, odd).
THRESHOLD_WINDOW_PX = 11


class MarkerDetector:
    """Finds ArUco markers of one dictionary and refines their corners to subpixel accuracy.

    OpenCV's corner refinement (cornerSubPix on the outer corners of the black square) pulls
    blurred L-shaped corners inward by about a quarter pixel, which shrinks every marker and
    biases its depth by millimetres. With K and dist given, corners are instead the
    intersections of straight lines fitted to subpixel edge points along each side of the
    square, in undistorted coordinates (where perspective keeps the sides straight).
    """

    def __init__(self, dictionary: str, K: np.ndarray | None = None, dist: np.ndarray | None = None) -> None:
        d = aruco_dictionary(dictionary)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = 5
        # One adaptive-threshold pass instead of OpenCV's three (windows 3, 13, 23): it finds the
        # same markers at 400-700 mm on 1280x720 in about 40 % of the time (`fluorosim bench tracking`).
        params.adaptiveThreshWinSizeMin = THRESHOLD_WINDOW_PX
        params.adaptiveThreshWinSizeMax = THRESHOLD_WINDOW_PX
        self.detector = cv2.aruco.ArucoDetector(d, params)
        self.cells = d.markerSize + 2          # data bits plus the black border, per side
        self.K = None if K is None else np.asarray(K, dtype=np.float64)
        self.dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64).reshape(-1)

    def detect(self, image: np.ndarray, window: tuple[int, int, int, int] | None = None) -> dict[int, np.ndarray]:
        """{marker id: (4, 2) corner pixels} of every marker found; a repeated id is dropped as ambiguous.

        `window` = (x0, y0, x1, y1) searches only that part of the image (corners are still in
        whole-image pixels).
        """
        x0, y0 = 0, 0
        if window is not None:
            x0, y0, x1, y1 = window
            image = image[y0:y1, x0:x1]
        gray = np.ascontiguousarray(to_gray(image))
        corners, ids, _ = self.detector.detectMarkers(gray)
        out: dict[int, np.ndarray] = {}
        if ids is None:
            return out
        repeated = set()
        for c, raw_id in zip(corners, ids.ravel()):
            i = int(raw_id)
            if i in out:
                repeated.add(i)
            out[i] = c.reshape(4, 2).astype(np.float64)
        for i in repeated:
            del out[i]
        if self.K is not None and out:
            # In the window's own pixels the camera's principal point moves by the window's offset.
            K = self.K.copy()
            K[0, 2] -= x0
            K[1, 2] -= y0
            seen = list(out)
            for i, c in zip(seen, refine_markers_by_edges(gray, [out[i] for i in seen], self.cells, K, self.dist)):
                out[i] = c
        if x0 or y0:
            out = {i: c + [x0, y0] for i, c in out.items()}
        return out


#: Profiles across each edge: PROFILE_SAMPLES samples spanning +-reach along the normal, at
#: EDGE_SAMPLES places spread over the middle of the side (clear of the corners' rounding).
PROFILE_SAMPLES = 25
EDGE_SAMPLES = 16


def refine_markers_by_edges(gray: np.ndarray, markers: list[np.ndarray], cells: int, K: np.ndarray,
                            dist: np.ndarray) -> list[np.ndarray]:
    """Corners of each marker as intersections of lines fitted to the square's four edges (pixels).

    Along each side, intensity profiles across the edge are sampled between 20 % and 80 % of
    its length; the edge point is where the profile crosses halfway between the black and
    white levels (unbiased for any symmetric blur). The profile reaches at most 0.4 cell to
    either side, staying within the black border and the white margin, both one cell wide.
    The points are undistorted, where the sides are straight, fitted with lines, intersected,
    and distorted back. A marker whose fit fails or strays keeps its input corners.
    All markers are done in one pass of array operations: this runs on every frame.
    """
    if not markers:
        return []
    c = np.asarray(markers, dtype=np.float64)                      # (M, 4, 2)
    M = len(c)
    a, b = c, np.roll(c, -1, axis=1)                                # side k runs from corner k to k+1
    side = np.linalg.norm(b - a, axis=2)                            # (M, 4)
    cell_px = side.min(axis=1) / cells
    reach = np.minimum(3.0, 0.4 * cell_px)                          # (M,)
    n_off = PROFILE_SAMPLES
    frac_off = np.linspace(-1.0, 1.0, n_off)                        # times reach
    d = (b - a) / np.maximum(side, 1e-9)[..., None]
    normal = np.stack([d[..., 1], -d[..., 0]], axis=2)
    centre = c.mean(axis=1, keepdims=True)
    flip = np.sum(normal * (a - centre), axis=2) < 0
    normal[flip] *= -1                                              # outward, toward the white margin
    t = np.linspace(0.2, 0.8, EDGE_SAMPLES)
    along = a[:, :, None, :] + t[None, None, :, None] * (b - a)[:, :, None, :]          # (M, 4, S, 2)
    offs = frac_off[None, :] * reach[:, None]                                             # (M, O)
    pts = along[:, :, :, None, :] + offs[:, None, None, :, None] * normal[:, :, None, None, :]  # (M,4,S,O,2)
    flat = pts.reshape(-1, n_off, 2).astype(np.float32)
    prof = cv2.remap(gray, flat[..., 0], flat[..., 1], cv2.INTER_LINEAR).astype(np.float64)  # (M*4*S, O)
    k3 = 4
    lo, hi = prof[:, :k3].mean(axis=1), prof[:, -k3:].mean(axis=1)
    s = prof - ((lo + hi) / 2)[:, None]
    up = (s[:, :-1] < 0) & (s[:, 1:] >= 0)                          # dark -> bright steps
    grad = np.diff(prof, axis=1)
    # Of several crossings (noise), take the one at the steepest part of the profile.
    j = np.argmax(np.where(up, grad, -np.inf), axis=1)
    rows = np.arange(len(j))
    ok = up[rows, j] & (hi - lo > 20.0)
    s0, s1 = s[rows, j], s[rows, j + 1]
    step = (2.0 / (n_off - 1)) * np.repeat(reach, 4 * EDGE_SAMPLES)
    off = -np.repeat(reach, 4 * EDGE_SAMPLES) + step * (j + (-s0) / np.where(s1 - s0 == 0, 1, s1 - s0))
    edge = along.reshape(-1, 2) + off[:, None] * normal[:, :, None, :].repeat(EDGE_SAMPLES, axis=2).reshape(-1, 2)
    ideal = cv2.undistortPoints(edge.reshape(-1, 1, 2), K, dist).reshape(M, 4, EDGE_SAMPLES, 2)
    w = ok.reshape(M, 4, EDGE_SAMPLES).astype(np.float64)
    count = w.sum(axis=2)                                            # (M, 4)
    mean = (ideal * w[..., None]).sum(axis=2) / np.maximum(count, 1)[..., None]
    r = (ideal - mean[:, :, None, :]) * w[..., None]
    sxx, syy, sxy = (r[..., 0] ** 2).sum(2), (r[..., 1] ** 2).sum(2), (r[..., 0] * r[..., 1]).sum(2)
    # The line's normal is the covariance's eigenvector of the smaller eigenvalue.
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)                      # direction of the line
    ln = np.stack([-np.sin(theta), np.cos(theta)], axis=2)           # (M, 4, 2)
    lines = np.concatenate([ln, -np.sum(ln * mean, axis=2, keepdims=True)], axis=2)    # (M, 4, 3)
    p = np.cross(np.roll(lines, 1, axis=1), lines)                   # corner k joins side k-1 and side k
    good = (count >= 4).all(axis=1) & (np.abs(p[..., 2]) > 1e-12).all(axis=1)
    out = []
    for m in range(M):
        if not good[m]:
            out.append(markers[m])
            continue
        refined = distort(p[m, :, :2] / p[m, :, 2:3], K, dist)
        if np.max(np.linalg.norm(refined - c[m], axis=1)) > max(2.0, 0.5 * cell_px[m]) or reach[m] < 0.75:
            out.append(markers[m])                                   # too small, or the fit went astray
        else:
            out.append(refined)
    return out


def distort(normalized: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n, 2) pixels of (n, 2) normalized undistorted image coordinates, through K and k1 k2 p1 p2 k3."""
    x, y = normalized[:, 0], normalized[:, 1]
    k1, k2, p1, p2, k3 = (list(np.asarray(dist).reshape(-1)) + [0.0] * 5)[:5]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


#: IPPE's best solution reprojecting worse than this (RMS, pixels) is checked with another solver.
IPPE_SUSPECT_PX = 1.0


@dataclass
class MarkerPose:
    """One marker's pose from its four corners alone."""

    marker_id: int
    T_webcam_from_marker: np.ndarray     # the better of IPPE's two solutions (mm)
    alternative: np.ndarray | None       # the other solution (a flipped plane), if any
    reprojection_px: float               # RMS of the chosen solution (pixels)
    angle_deg: float                     # between the ray to the marker centre and the marker normal


def ray_to_normal_deg(T_webcam_from_marker: np.ndarray) -> float:
    """Angle between the ray from the camera to the marker centre and the marker's outward normal, seen
    from the marker (0 = viewed head-on; 90 = edge-on); the pose quality measure of the composite marker."""
    t = T_webcam_from_marker[:3, 3]
    n = T_webcam_from_marker[:3, 2]
    c = float(-t @ n / max(np.linalg.norm(t), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _transform(rvec, tvec) -> np.ndarray:
    return make_transform(cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0], np.asarray(tvec).reshape(3))


def marker_pose(marker_id: int, corners_px: np.ndarray, size_mm: float, K: np.ndarray, dist: np.ndarray,
                polish: bool = True) -> MarkerPose | None:
    """Pose of one square marker from its corners, or None if it cannot be solved.

    Candidates come from IPPE for squares (its two solutions: the plane and its mirror about the
    line of sight); when IPPE's best reprojects badly (it breaks down for a square seen almost
    exactly head-on with its sides along the image axes) SQPnP adds one. IPPE's closed form is
    not the least-squares pose (0.5 % off in depth even on exact corners), so each candidate is
    polished by Levenberg-Marquardt (unless `polish` is False: a caller that refines a joint pose
    only needs candidates). A print is seen from its front only, so a candidate with
    the normal turned away from the camera is impossible and dropped.
    """
    obj, img = marker_corners(size_mm), corners_px.reshape(4, 1, 2).astype(np.float64)
    # (rvec, tvec, RMS error in pixels or None when unknown)
    seeds: list[tuple[np.ndarray, np.ndarray, float | None]] = []
    try:
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        # OpenCV reports the RMS per coordinate; per corner (as everywhere here) it is sqrt(2) larger.
        errs = np.asarray(errs, dtype=np.float64).reshape(-1) * np.sqrt(2.0)
        seeds += [(r, t, float(e)) for r, t, e in zip(rvecs, tvecs, errs)]
        if n == 0 or not np.any(errs <= IPPE_SUSPECT_PX):      # (NaN counts as bad)
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                seeds.append((np.asarray(rvec), np.asarray(tvec), None))
    except cv2.error:
        return None
    found = []
    for rvec, tvec, err in seeds:
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            continue
        if polish:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec.copy(), tvec.copy())
            err = None
        T = _transform(rvec, tvec)
        if not np.all(np.isfinite(T)) or T[2, 3] <= 0 or ray_to_normal_deg(T) >= 90.0:
            continue
        if err is None:
            proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
            err = float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - img.reshape(4, 2)) ** 2, axis=1))))
        found.append((err, T))
    if not found:
        return None
    found.sort(key=lambda f: f[0])
    (err, T), alt = found[0], (found[1][1] if len(found) > 1 else None)
    return MarkerPose(marker_id, T, alt, err, ray_to_normal_deg(T))
