"""The geometric pieces of pairing shadows with balls: the large/small split, lines of
collinear blobs, gated mutual-nearest matching, and projection and pose with the nominal
intrinsics. `identification.py` combines them into the seed paper's steps 3a-3c.
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np
from scipy.spatial import cKDTree


def split_by_size(diameters: np.ndarray) -> tuple[np.ndarray, float]:
    """k-means with k = 2 on log diameter, solved exactly in 1-D: (large mask, ratio of class means)."""
    d = np.log(np.asarray(diameters, dtype=np.float64))
    if len(d) < 2:
        return np.zeros(len(d), bool), 1.0
    order = np.argsort(d)
    s = d[order]
    best, split = np.inf, 1
    for i in range(1, len(s)):
        cost = s[:i].var() * i + s[i:].var() * (len(s) - i)
        if cost < best:
            best, split = cost, i
    threshold = 0.5 * (s[split - 1] + s[split])
    large = d > threshold
    return large, float(np.exp(s[split:].mean() - s[:split].mean()))


def _line_through(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line: (point on it, unit direction)."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c)
    return c, vt[0]


def find_lines(points: np.ndarray, tolerance_px: float, iterations: int, min_points: int = 3,
               max_lines: int = 6, rng: np.random.Generator | None = None) -> list[np.ndarray]:
    """Greedy RANSAC: index arrays of collinear points, longest line first."""
    rng = rng or np.random.default_rng(0)
    remaining = np.arange(len(points))
    lines: list[np.ndarray] = []
    while len(remaining) >= min_points and len(lines) < max_lines:
        pts = points[remaining]
        pairs = list(itertools.combinations(range(len(pts)), 2))
        if len(pairs) > iterations:
            pairs = [tuple(rng.choice(len(pts), 2, replace=False)) for _ in range(iterations)]
        best, best_key = None, (0, 0.0)
        for i, j in pairs:
            d = pts[j] - pts[i]
            n = np.linalg.norm(d)
            if n == 0:
                continue
            normal = np.array([-d[1], d[0]]) / n
            dist = np.abs((pts - pts[i]) @ normal)
            inl = dist < tolerance_px
            key = (int(inl.sum()), -float(dist[inl].sum()))
            if key > best_key:
                best, best_key = inl, key
        if best is None or best_key[0] < min_points:
            break
        # Refit on the inliers and take the final inlier set from the refined line.
        c, direction = _line_through(pts[best])
        normal = np.array([-direction[1], direction[0]])
        inl = np.abs((pts - c) @ normal) < tolerance_px
        if inl.sum() < min_points:
            inl = best
        members = remaining[inl]
        along = (points[members] - c) @ direction
        lines.append(members[np.argsort(along)])
        remaining = remaining[~inl]
    return lines


def match_nearest(predicted: np.ndarray, observed: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours within `gate`: (predicted index, observed index) arrays."""
    if len(predicted) == 0 or len(observed) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    # k-d trees: a grid phantom has hundreds of balls and this runs for every hypothesis.
    d, nearest_obs = cKDTree(observed).query(predicted)
    _, nearest_pred = cKDTree(predicted).query(observed)
    p = np.arange(len(predicted))
    ok = (nearest_pred[nearest_obs] == p) & (d < gate)
    return p[ok], nearest_obs[ok]


def ball_spacing(points: np.ndarray) -> float:
    """Median nearest-neighbour distance of projected balls (pixels)."""
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def project(T: np.ndarray, points: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, T[:3, 3], K, dist)
    return uv.reshape(-1, 2)


def refine_pose(object_points: np.ndarray, image_points: np.ndarray, K: np.ndarray, dist: np.ndarray,
          guess: np.ndarray) -> np.ndarray | None:
    """Pose refined from `guess` by iterative PnP, or None."""
    obj = object_points.reshape(-1, 1, 3).astype(np.float64)
    img = image_points.reshape(-1, 1, 2).astype(np.float64)
    rvec0, _ = cv2.Rodrigues(guess[:3, :3])
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, rvec0.copy(), guess[:3, 3].reshape(3, 1).copy(),
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.reshape(3)
    return T


def plate_poses(object_points: np.ndarray, image_points: np.ndarray, K: np.ndarray, dist: np.ndarray) -> list[np.ndarray]:
    """Both IPPE poses of a planar set of balls that put it in front of the source."""
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(object_points.reshape(-1, 1, 3).astype(np.float64),
                                             image_points.reshape(-1, 1, 2).astype(np.float64), K, dist,
                                             flags=cv2.SOLVEPNP_IPPE)
    poses = []
    for r, t in zip(rvecs[:n], tvecs[:n]):
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(r)[0]
        T[:3, 3] = np.asarray(t).reshape(3)
        if T[2, 3] > 0:
            poses.append(T)
    return poses
