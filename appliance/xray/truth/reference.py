"""Plain NumPy reference renderer for tests: exact Siddon path lengths, one ray at a time.

Slow and simple on purpose: it shares no code with the OpenCL kernels, so the kernels can be
checked against it on the same voxel grid.
"""

from __future__ import annotations

import numpy as np

from ...geometry import invert


def path_lengths(hu_shape_zyx, T_ct_from_voxel, source_ct, target_ct):
    """Exact lengths (mm) of the segment source->target inside each voxel it crosses.

    Returns (flat voxel indices into the (nz, ny, nx) array, lengths in mm). The segment is
    taken as a ray from `source_ct` through `target_ct` and beyond, to the grid's far side.
    """
    nz, ny, nx = hu_shape_zyx
    T = invert_affine(np.asarray(T_ct_from_voxel, dtype=np.float64))
    s = T[:3, :3] @ np.asarray(source_ct, float) + T[:3, 3]
    e = T[:3, :3] @ np.asarray(target_ct, float) + T[:3, 3]
    d = e - s
    n = np.array([nx, ny, nz], dtype=float)
    # Parameter a along s + a*d at every voxel boundary plane (index -0.5 .. n-0.5) of each axis.
    alphas = [np.array([0.0])]
    with np.errstate(divide="ignore", invalid="ignore"):
        lo = np.where(d != 0, (-0.5 - s) / d, -np.inf)
        hi = np.where(d != 0, (n - 0.5 - s) / d, np.inf)
    a_min = np.max(np.where(d != 0, np.minimum(lo, hi), -np.inf))
    a_max = np.min(np.where(d != 0, np.maximum(lo, hi), np.inf))
    for ax in range(3):
        if d[ax] == 0:
            if not -0.5 <= s[ax] <= n[ax] - 0.5:
                return np.zeros(0, dtype=np.int64), np.zeros(0)
            continue
        planes = np.arange(n[ax] + 1) - 0.5
        alphas.append((planes - s[ax]) / d[ax])
    a_min = max(a_min, 0.0)
    if not a_max > a_min:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    a = np.concatenate(alphas)
    a = np.unique(np.clip(a[(a >= a_min) & (a <= a_max)], a_min, a_max))
    a = np.unique(np.concatenate([[a_min], a, [a_max]]))
    mid = (a[:-1] + a[1:]) / 2.0
    pts = s[None, :] + mid[:, None] * d[None, :]
    idx = np.floor(pts + 0.5).astype(np.int64)
    ok = np.all((idx >= 0) & (idx < n.astype(np.int64)), axis=1)
    mm_per_alpha = np.linalg.norm(np.asarray(target_ct, float) - np.asarray(source_ct, float))
    lengths = np.diff(a)[ok] * mm_per_alpha
    idx = idx[ok]
    flat = (idx[:, 2] * ny + idx[:, 1]) * nx + idx[:, 0]
    return flat, lengths


def invert_affine(T: np.ndarray) -> np.ndarray:
    """General inverse of a voxel-to-ct affine (it carries spacing, so it is not rigid)."""
    return np.linalg.inv(T)


def line_integral_image(hu: np.ndarray, T_ct_from_voxel: np.ndarray, T_xray_from_ct: np.ndarray,
                        K: np.ndarray, rows: int, cols: int, mu_water_per_mm: float) -> np.ndarray:
    """(rows, cols) line integrals of mu = mu_water (1 + HU/1000), clipped at 0, through each
    undistorted pinhole pixel centre."""
    T_ct_from_xray = invert(np.asarray(T_xray_from_ct, dtype=np.float64))
    src = T_ct_from_xray[:3, 3]
    Kinv = np.linalg.inv(K)
    mu = (mu_water_per_mm * np.maximum(1.0 + hu.astype(np.float64) / 1000.0, 0.0)).ravel()
    out = np.zeros((rows, cols))
    for v in range(rows):
        for u in range(cols):
            d_xray = Kinv @ np.array([u, v, 1.0])
            tgt = T_ct_from_xray[:3, :3] @ d_xray + src
            flat, lengths = path_lengths(hu.shape, T_ct_from_voxel, src, tgt)
            out[v, u] = float(np.dot(mu[flat], lengths))
    return out
