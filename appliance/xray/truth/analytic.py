"""Closed-form line integrals of boxes and ellipsoids, and their voxelisations.

The ground truth of the renderer's accuracy tests and of `fluorosim bench drr`: chords are
computed from the shapes' equations in float64, never by the renderer.
"""

from __future__ import annotations

import numpy as np

from ...geometry import invert
from ...patient.volume import Volume


def pixel_rays_ct(K: np.ndarray, T_xray_from_ct: np.ndarray, rows: int, cols: int):
    """Focal spot (3,) and unit ray directions (rows, cols, 3) in the ct frame, through the
    undistorted pinhole pixel centres."""
    T = invert(np.asarray(T_xray_from_ct, dtype=np.float64))
    u, v = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    d = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    d = d @ T[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return T[:3, 3], d


def box_chords(source, dirs, lo, hi, T_ct_from_box=None) -> np.ndarray:
    """Length (mm) of each ray inside the box [lo, hi] (box frame, mm), the box placed in
    the ct frame by `T_ct_from_box` (identity: axis-aligned)."""
    s, d = np.asarray(source, float), np.asarray(dirs, float)
    if T_ct_from_box is not None:
        Tb = invert(np.asarray(T_ct_from_box, float))
        s = Tb[:3, :3] @ s + Tb[:3, 3]
        d = d @ Tb[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (np.asarray(lo, float) - s) / d
        tb = (np.asarray(hi, float) - s) / d
    tmin = np.where(d == 0, np.where((s >= lo) & (s <= hi), -np.inf, np.inf), np.minimum(ta, tb))
    tmax = np.where(d == 0, np.where((s >= lo) & (s <= hi), np.inf, -np.inf), np.maximum(ta, tb))
    t0 = np.maximum(tmin.max(axis=-1), 0.0)
    t1 = tmax.min(axis=-1)
    return np.maximum(t1 - t0, 0.0)


def ellipsoid_chords(source, dirs, centre, semi_axes) -> np.ndarray:
    """Length (mm) of each ray inside the axis-aligned ellipsoid (ct frame)."""
    a = np.asarray(semi_axes, float)
    s = (np.asarray(source, float) - np.asarray(centre, float)) / a
    d = np.asarray(dirs, float) / a
    A = np.sum(d * d, axis=-1)
    B = 2.0 * np.sum(d * s, axis=-1)
    C = np.sum(s * s) - 1.0
    disc = B * B - 4 * A * C
    root = np.sqrt(np.maximum(disc, 0.0))
    dt = np.where(disc > 0, root / A, 0.0)     # t1 - t0; |dirs| = 1 so t is mm
    return dt


def grid(shape_zyx, spacing_mm, T_ct_from_grid=None) -> np.ndarray:
    """T_ct_from_voxel of a grid centred on the ct origin, optionally moved by a rigid transform."""
    nz, ny, nx = shape_zyx
    sp = np.asarray(spacing_mm, float)
    T = np.diag([*sp, 1.0])
    T[:3, 3] = -(np.array([nx, ny, nz]) - 1) / 2.0 * sp
    if T_ct_from_grid is not None:
        T = np.asarray(T_ct_from_grid, float) @ T
    return T


def box_volume(shape_zyx, spacing_mm, lo_index, hi_index, hu=0, T_ct_from_grid=None):
    """A box of `hu` filling voxels lo_index..hi_index (i, j, k, inclusive) in air (-1000):
    its faces lie on voxel boundaries, so the voxelised box is exact. Returns the Volume and
    the box's corners (mm) in the grid's own frame, for `box_chords` with T_ct_from_grid."""
    arr = np.full(shape_zyx, -1000, dtype=np.int16)
    (i0, j0, k0), (i1, j1, k1) = lo_index, hi_index
    arr[k0:k1 + 1, j0:j1 + 1, i0:i1 + 1] = hu
    T0 = grid(shape_zyx, spacing_mm)
    sp = np.asarray(spacing_mm, float)
    lo = T0[:3, 3] + (np.array(lo_index, float) - 0.5) * sp
    hi = T0[:3, 3] + (np.array(hi_index, float) + 0.5) * sp
    T = grid(shape_zyx, spacing_mm, T_ct_from_grid)
    return Volume(hu=arr, T_ct_from_voxel=T, source="box"), lo, hi


def ellipsoid_volume(shape_zyx, spacing_mm, centre, semi_axes, hu=0, supersample=5):
    """An axis-aligned ellipsoid of `hu` in air, each voxel's HU set by the fraction of it
    inside (partial volume, `supersample`^3 points per voxel)."""
    nz, ny, nx = shape_zyx
    T = grid(shape_zyx, spacing_mm)
    sp = np.asarray(spacing_mm, float)
    off = (np.arange(supersample) + 0.5) / supersample - 0.5
    frac = np.zeros(shape_zyx)
    x = T[0, 3] + np.arange(nx) * sp[0]
    y = T[1, 3] + np.arange(ny) * sp[1]
    z = T[2, 3] + np.arange(nz) * sp[2]
    c, a = np.asarray(centre, float), np.asarray(semi_axes, float)
    for ox in off:
        qx = ((x + ox * sp[0] - c[0]) / a[0]) ** 2
        for oy in off:
            qy = ((y + oy * sp[1] - c[1]) / a[1]) ** 2
            for oz in off:
                qz = ((z + oz * sp[2] - c[2]) / a[2]) ** 2
                frac += (qz[:, None, None] + qy[None, :, None] + qx[None, None, :]) <= 1.0
    frac /= supersample ** 3
    arr = np.rint(-1000 + frac * (hu + 1000)).astype(np.int16)
    return Volume(hu=arr, T_ct_from_voxel=T, source="ellipsoid")
