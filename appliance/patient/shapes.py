"""Signed-distance shapes painted onto a voxel grid with partial-volume edges.

A shape is a signed distance in mm (negative inside) evaluated on open (broadcasting)
coordinate axes of a box of the grid, so a small organ costs only its own bounding box.
Painting blends the new HU over what is there with a coverage that ramps across one voxel
at the surface, which is what a CT scanner's partial-volume effect does to a sharp edge;
it keeps edges smooth in a radiograph instead of stair-stepped.

Coordinates are the `ct` frame of DESIGN.md (LPS, mm): x toward the patient's left,
y posterior, z superior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_EPS = 1e-6


@dataclass(frozen=True)
class Grid:
    """A regular grid of voxel centres: `shape` is (nz, ny, nx), `origin_mm` the (x, y, z) of voxel 0."""

    shape: tuple[int, int, int]
    spacing_mm: float
    origin_mm: tuple[float, float, float]

    @classmethod
    def centred(cls, shape_xyz: tuple[int, int, int], spacing_mm: float) -> Grid:
        """The grid of `shape_xyz` voxels whose middle lies at the origin (a voxel centre when the count is odd)."""
        ox, oy, oz = (-(n - 1) / 2 * spacing_mm for n in shape_xyz)
        return cls((shape_xyz[2], shape_xyz[1], shape_xyz[0]), spacing_mm, (ox, oy, oz))

    @property
    def spacing_xyz(self) -> tuple[float, float, float]:
        return (self.spacing_mm,) * 3

    def axis(self, which: int) -> np.ndarray:
        """Voxel-centre coordinates along x (0), y (1) or z (2), mm, float32."""
        return grid_axis(self, which)

    @property
    def T_ct_from_voxel(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] *= self.spacing_mm
        T[:3, 3] = self.origin_mm
        return T

    def box(self, lo, hi):
        """Index slices (z, y, x) and open axes X, Y, Z of the voxels inside [lo, hi] (mm), or None."""
        return grid_box(self, lo, hi)


def grid_axis(grid, which: int) -> np.ndarray:
    """Voxel-centre coordinates along x (0), y (1) or z (2) of any grid with `shape` (nz, ny, nx),
    `origin_mm` and `spacing_xyz` (mm), float32."""
    n = grid.shape[2 - which]
    return (grid.origin_mm[which] + grid.spacing_xyz[which] * np.arange(n)).astype(np.float32)


def grid_box(grid, lo, hi):
    """Index slices (z, y, x) and open axes X, Y, Z of the voxels of `grid` inside [lo, hi] (mm), or None."""
    slices, axes = [], []
    for which in range(3):
        n, s, o = grid.shape[2 - which], grid.spacing_xyz[which], grid.origin_mm[which]
        i0 = max(0, int(np.floor((lo[which] - o) / s)))
        i1 = min(n, int(np.ceil((hi[which] - o) / s)) + 1)
        if i1 <= i0:
            return None
        slices.append(slice(i0, i1))
        axes.append(grid_axis(grid, which)[i0:i1])
    sx, sy, sz = slices
    ax, ay, az = axes
    return (sz, sy, sx), ax[None, None, :], ay[None, :, None], az[:, None, None]


class Layer:
    """HU with coverage, premultiplied: painting covers what lies below, compositing stacks layers.

    A layer made with `opaque=True` is fully covered from the start (the body's background);
    otherwise it starts transparent (bones, painted once and laid over every phase).
    """

    def __init__(self, grid: Grid, background_hu: float = 0.0, opaque: bool = True):
        self.grid = grid
        self.value = np.full(grid.shape, background_hu if opaque else 0.0, np.float32)
        self.alpha = None if opaque else np.zeros(grid.shape, np.float32)

    def copy(self) -> Layer:
        other = Layer.__new__(Layer)
        other.grid = self.grid
        other.value = self.value.copy()
        other.alpha = None if self.alpha is None else self.alpha.copy()
        return other

    def coverage(self, d: np.ndarray) -> np.ndarray:
        """Fraction of a voxel inside a surface at signed distance `d` (mm) from its centre."""
        return np.clip(0.5 - d / self.grid.spacing_mm, 0.0, 1.0)

    def paint(self, sdf, hu, lo, hi) -> None:
        """Paint HU `hu` (a number, or an array over the box) where `sdf(X, Y, Z)` < 0 inside [lo, hi]."""
        region = self.grid.box(lo, hi)
        if region is None:
            return
        sl, X, Y, Z = region
        a = self.coverage(sdf(X, Y, Z))
        v = self.value[sl]
        # Opaque: v <- a*hu + (1-a)*v. Premultiplied transparent: the same, and coverage grows.
        v += a * (np.float32(hu) - v)
        if self.alpha is not None:
            al = self.alpha[sl]
            al += a * (1.0 - al)

    def over(self, below: np.ndarray, sl=(slice(None),) * 3) -> np.ndarray:
        """This (transparent) layer laid over the opaque HU `below` inside slices `sl`."""
        if self.alpha is None:      # an opaque layer hides what is below it
            return self.value[sl].copy()
        return self.value[sl] + (1.0 - self.alpha[sl]) * below


# --- distances (mm; negative inside). X, Y, Z are broadcasting coordinate arrays. ---

def rotation(axis: str, degrees: float) -> np.ndarray:
    """Right-handed rotation about the x, y or z axis of the ct frame."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _local(X, Y, Z, centre, R):
    dx, dy, dz = X - np.float32(centre[0]), Y - np.float32(centre[1]), Z - np.float32(centre[2])
    if R is None:
        return dx, dy, dz
    R = R.astype(np.float32)
    # q = R^T (p - c): coordinates along the shape's own axes.
    return (R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz,
            R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz,
            R[0, 2] * dx + R[1, 2] * dy + R[2, 2] * dz)


def ellipsoid(X, Y, Z, centre, radii, R=None):
    """Ellipsoid with semi-axes `radii` (mm) along its axes, rotated by R (columns = its axes in ct)."""
    qx, qy, qz = _local(X, Y, Z, centre, R)
    rx, ry, rz = (np.float32(r) for r in radii)
    k0 = np.sqrt((qx / rx) ** 2 + (qy / ry) ** 2 + (qz / rz) ** 2)
    k1 = np.sqrt((qx / rx ** 2) ** 2 + (qy / ry ** 2) ** 2 + (qz / rz ** 2) ** 2)
    # Quilez's bound: exact on the surface, within a few per cent near it.
    return k0 * (k0 - 1.0) / (k1 + _EPS)


def elliptic_prism(X, Y, Z, centre, a, b, half_height, power=2.0):
    """Superelliptic cylinder along z: semi-axes a (x) and b (y), |z - zc| <= half_height (mm)."""
    dx, dy, dz = X - np.float32(centre[0]), Y - np.float32(centre[1]), Z - np.float32(centre[2])
    rho = ((np.abs(dx) / a) ** power + (np.abs(dy) / b) ** power) ** (1.0 / power)
    return np.maximum((rho - 1.0) * np.float32(min(a, b)), np.abs(dz) - np.float32(half_height))


def segment(X, Y, Z, a, b, ra, rb):
    """Cone-capped tube from point a (radius ra) to point b (radius rb), mm."""
    a = np.asarray(a, np.float32)
    ba = np.asarray(b, np.float32) - a
    px, py, pz = X - a[0], Y - a[1], Z - a[2]
    t = np.clip((px * ba[0] + py * ba[1] + pz * ba[2]) / np.float32(ba @ ba + _EPS), 0.0, 1.0)
    dist = np.sqrt((px - t * ba[0]) ** 2 + (py - t * ba[1]) ** 2 + (pz - t * ba[2]) ** 2)
    return dist - (np.float32(ra) + t * np.float32(rb - ra))


def intersect(*distances):
    """Intersection of shapes: the largest distance (arrays may differ in shape and broadcast)."""
    out = distances[0]
    for d in distances[1:]:
        out = np.maximum(out, d)
    return out


def union(*distances):
    """Union of shapes: the smallest distance."""
    out = distances[0]
    for d in distances[1:]:
        out = np.minimum(out, d)
    return out


def smooth_min(a, b, k):
    """Union of two distances with a fillet of about k mm (polynomial smooth minimum)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def bounds(points, radius) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box (lo, hi) around `points` grown by `radius` (mm)."""
    p = np.atleast_2d(np.asarray(points, float))
    return p.min(axis=0) - radius, p.max(axis=0) + radius


def paint_tube(layer: Layer, points, radii, hu, clip=None) -> None:
    """Paint a polyline tube through `points` with per-point `radii`, one segment per box.

    `clip(X, Y, Z)`, if given, is a distance the tube is intersected with (e.g. the lungs).
    """
    points = np.asarray(points, float)
    radii = np.broadcast_to(np.asarray(radii, float), (len(points),))
    for p, q, r0, r1 in zip(points[:-1], points[1:], radii[:-1], radii[1:]):
        def sdf(X, Y, Z, p=p, q=q, r0=r0, r1=r1):
            d = segment(X, Y, Z, p, q, r0, r1)
            return d if clip is None else np.maximum(d, clip(X, Y, Z))
        lo, hi = bounds([p, q], max(r0, r1) + 2 * layer.grid.spacing_mm)
        layer.paint(sdf, hu, lo, hi)


def paint_bone(layer: Layer, sdf, lo, hi, cortex_mm: float, cortical_hu: float, trabecular_hu: float) -> None:
    """A bone: a cortical shell `cortex_mm` thick around trabecular (cancellous) bone."""
    layer.paint(sdf, cortical_hu, lo, hi)
    layer.paint(lambda X, Y, Z: sdf(X, Y, Z) + np.float32(cortex_mm), trabecular_hu, lo, hi)
