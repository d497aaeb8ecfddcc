"""The content's outline: planes that bound what a prepared volume holds, closer than its box.

A patient is round, not square: of the adult chest's content box, a quarter of the voxels along
posterior-anterior or lateral lines lie outside the body, most of them toward its flanks and
corners; a field centred on the chest meets few of them, a field at the body's side many. A convex polytope with more face
directions than the box (a k-DOP) follows the body closer at the cost of a few operations per
ray, once: for each direction n (integer, in voxel-index space) the content's range [lo, hi] of
n.p over its voxel centres p gives each ray a t-interval, which the kernels intersect with the
box's (drr.cl's clip_planes).

The range follows the box's rule (casting.py's EMPTY_PLANE_MAX_VOXELS, SURE_CONTENT_HU): a plane
n.p = c belongs to the content where more than EMPTY_PLANE_MAX_VOXELS of its voxels are above
EMPTY_MAX_HU, or any is above SURE_CONTENT_HU. Each direction lies in one of the planes of two
index axes, so its planes' counts are sums along lines of the mask's projection onto those two
axes: the 3D mask is read once per pair, then only 2D maps are summed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The directions (a, b) of n = a e_u + b e_v in each pair (u, v) of index axes. Fraction of the
#: content box's voxels inside the polytope (each plane grown by its bilinear reach) on the adult
#: chest of frame_cost.bench_ct, axial pair alone: (1, +-1) 0.883; with (1, +-2), (2, +-1) 0.848;
#: with (1, +-3), (3, +-1) too 0.833, 1.5 % more for four more planes per pair, not taken. The
#: chest fills its z range, so the pairs with z add little to it (0.848 -> 0.836), but a volume
#: scanned in another orientation (a limb, a patient along x) gains there what the chest gains
#: in the axial pair; a plane costs a ray about ten operations, once.
PAIR_DIRECTIONS = ((1, 1), (1, -1), (1, 2), (1, -2), (2, 1), (2, -1))
#: The index-axis pairs (u, v) the directions are applied to, and the axis summed over for
#: each pair's 2D map of the (z, y, x) mask.
AXIS_PAIRS = ((0, 1), (0, 2), (1, 2))


@dataclass(frozen=True, eq=False)
class Outline:
    """Planes lo[j] <= normals[j] . p <= hi[j] that every content voxel centre p satisfies, in
    the padded voxel-index space of one prepared volume (its copies' in theirs)."""

    normals: np.ndarray     # (n, 3) float64
    lo: np.ndarray          # (n,) float64
    hi: np.ndarray          # (n,) float64

    def moved(self, T_new_from_old: np.ndarray, half_extent=(0.0, 0.0, 0.0)) -> Outline:
        """The outline in another grid of the same voxels, q = M p + m (T_new_from_old): the plane
        n.p = c is (M^-T n).q = c + n.M^-1 m there. `half_extent`: how far (old voxels, per axis)
        the old voxels a new voxel holds reach from its centre (a slab of t slices: (t - 1) / 2
        along its axis); each range grows by |n| . half_extent, so that a new voxel holding any
        content voxel stays inside (conservative, no longer tight)."""
        T = np.asarray(T_new_from_old, dtype=np.float64)
        M_inv = np.linalg.inv(T[:3, :3])
        normals = self.normals @ M_inv                  # rows: (M^-T n)^T = n^T M^-1
        shift = normals @ T[:3, 3]
        grow = np.abs(self.normals) @ np.asarray(half_extent, dtype=np.float64)
        return Outline(normals, self.lo + shift - grow, self.hi + shift + grow)

    def planes(self, reach: float, margin: float) -> np.ndarray:
        """The kernels' constant buffer (drr.cl's clip_planes): float32 [count, then per plane
        n.x, n.y, n.z, lo, hi], each range grown by `reach` x sum |n_i| (how far a sample's
        footprint reaches, in voxels along each axis) and `margin` (voxels of n.p, for the
        rounding of a ray's float parameters)."""
        grow = reach * np.abs(self.normals).sum(axis=1) + margin
        rows = np.column_stack([self.normals, self.lo - grow, self.hi + grow])
        return np.concatenate([[len(rows)], rows.ravel()]).astype(np.float32)


def projections(mask: np.ndarray, sure: np.ndarray) -> dict:
    """Per pair (u, v) of AXIS_PAIRS, the (z, y, x) volume's `mask` counted and `sure` or-ed
    along the third index axis: 2D maps with array axes (v, u), v the slower. The box's plane
    counts are their sums too (Caster.prepare), so the 3D arrays are read once per pair."""
    maps = {}
    for u, v in AXIS_PAIRS:
        summed = 2 - ({0, 1, 2} - {u, v}).pop()        # the array axis of the third index axis
        maps[(u, v)] = (np.count_nonzero(mask, axis=summed), sure.any(axis=summed))
    return maps


def content_outline(maps: dict, offset, max_voxels: int) -> Outline | None:
    """The outline of a volume's content from its `projections`: `max_voxels` the plane rule's
    count (EMPTY_PLANE_MAX_VOXELS), `offset` the padded index of voxel (0, 0, 0), along (x, y, z).
    None where no plane holds content."""
    normals, lo, hi = [], [], []
    for (u, v), (counts, anysure) in maps.items():
        iv, iu = np.indices(counts.shape)
        for a, b in PAIR_DIRECTIONS:
            value = (a * iu + b * iv).ravel()
            first = value.min()
            per_plane = np.bincount(value - first, weights=counts.ravel())
            per_plane_sure = np.bincount(value - first, weights=anysure.ravel())
            kept = np.flatnonzero((per_plane > max_voxels) | (per_plane_sure > 0))
            if not len(kept):
                return None
            n = np.zeros(3)
            n[u], n[v] = a, b
            shift = float(n @ np.asarray(offset, dtype=np.float64))
            normals.append(n)
            lo.append(kept[0] + first + shift)
            hi.append(kept[-1] + first + shift)
    return Outline(np.array(normals), np.array(lo, float), np.array(hi, float))


def union(outlines) -> Outline | None:
    """The outline holding all of `outlines` (one grid's: the same normals): each plane's widest
    range. None where one of them is None or their normals differ (then only the box clips)."""
    outlines = list(outlines)
    if not outlines or any(o is None for o in outlines):
        return None
    first = outlines[0]
    if any(o.normals.shape != first.normals.shape or not np.allclose(o.normals, first.normals, atol=1e-9)
           for o in outlines):
        return None
    return Outline(first.normals, np.min([o.lo for o in outlines], axis=0), np.max([o.hi for o in outlines], axis=0))


def cutting(planes: np.ndarray, T_index_from_xray: np.ndarray, rim: np.ndarray, lo, hi) -> np.ndarray:
    """The kernels' `planes` buffer (Outline.planes) with only the planes that cut a ray of the
    field within the box [lo, hi] (padded indices, as the kernels clip to it). `rim`: (n, 2), the
    rays (x, y, 1) in the xray frame of the detector's outer rows and columns, whose hull holds
    every pixel's ray. A linear n.p is extreme over the field's part of the box at a corner
    of it: where a rim ray enters or leaves the box, or a corner of the box within the field.
    A plane left out only widens a ray's interval, so leaving out one that cuts nothing drops no
    content and changes no integral, and a posterior-anterior view of a chest's middle, whose rays
    no plane cuts, pays nothing for them (2-3 % of that cast with all 18 planes)."""
    n = int(planes[0])
    if n == 0:
        return planes
    rows = planes[1:].reshape(n, 5).astype(np.float64)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    T = np.asarray(T_index_from_xray, np.float64)
    source, dirs = T[:3, 3], rim @ T[:3, :2].T + T[:3, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - source) / dirs, (hi - source) / dirs
    # A ray parallel to an axis: the whole line within that slab, or none of it.
    inside = (source >= lo) & (source <= hi)
    enter = np.where(dirs == 0, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    leave = np.where(dirs == 0, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    # The three axes' columns reduced pairwise, and the planes' values below with the points
    # along the rows: NumPy's reductions across short or strided axes cost most of this
    # function, which every moving frame runs (min and max are exact in any order).
    t_in = np.maximum(np.maximum(np.maximum(enter[:, 0], enter[:, 1]), enter[:, 2]), 0.0)
    t_out = np.minimum(np.minimum(leave[:, 0], leave[:, 1]), leave[:, 2])
    hit = t_out > t_in
    points = [source + t[hit, None] * dirs[hit] for t in (t_in, t_out)]
    # The box's corners within the field: in front of the focal spot, their direction within the
    # rim's extent (a rectangle holding its hull: a corner taken in too only keeps a plane more).
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    xray = (corners - source) @ np.linalg.inv(T[:3, :3]).T
    ahead = xray[:, 2] > 0
    d = xray[ahead, :2] / xray[ahead, 2:3]
    seen = np.all((d >= rim.min(axis=0)) & (d <= rim.max(axis=0)), axis=1)
    points.append(corners[ahead][seen])
    p = np.concatenate(points)
    v = rows[:, :3] @ p.T
    keep = (v.min(axis=1, initial=np.inf) < rows[:, 3]) | (v.max(axis=1, initial=-np.inf) > rows[:, 4])
    return np.concatenate([[keep.sum()], rows[keep].ravel()]).astype(np.float32)
