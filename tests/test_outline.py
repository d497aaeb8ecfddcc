"""The content's outline (outline.py): its planes against brute force over every voxel, and its
copies in the slab and layout grids keeping every content voxel."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.patient.volume import Volume
from appliance.xray.bench import flat_profile
from appliance.xray.casting import EMPTY_MAX_HU, EMPTY_PLANE_MAX_VOXELS, PAD, SURE_CONTENT_HU
from appliance.xray.renderer import Renderer
from appliance.xray.slabs import SlabCache


def brute_force_bounds(hu: np.ndarray, T_index_from_voxel: np.ndarray, normals: np.ndarray):
    """Per normal, (lo, hi) of n.p over the planes n.p = c that hold more than
    EMPTY_PLANE_MAX_VOXELS voxels above EMPTY_MAX_HU or any above SURE_CONTENT_HU, p each voxel's
    padded index, voxel by voxel; the voxels above EMPTY_MAX_HU (p), and per normal which of
    them lie on those planes (voxels, normals)."""
    k, j, i = np.nonzero(hu > EMPTY_MAX_HU)
    p = (T_index_from_voxel @ np.stack([i, j, k, np.ones_like(i)]).astype(float))[:3].T
    sure = hu[k, j, i] > SURE_CONTENT_HU
    bounds, kept = [], []
    for n in normals:
        value = np.rint(p @ n).astype(int)
        planes = {c: (np.count_nonzero(value == c), bool(sure[value == c].any())) for c in np.unique(value)}
        good = [c for c, (count, any_sure) in planes.items() if count > EMPTY_PLANE_MAX_VOXELS or any_sure]
        bounds.append((min(good), max(good)))
        kept.append(np.isin(value, good))
    return np.array(bounds, float), p, np.array(kept).T


def index_from_voxel(prepared, volume: Volume) -> np.ndarray:
    return prepared.T_index_from_ct @ np.asarray(volume.T_ct_from_voxel, float)


def random_content(seed: int, held_open: bool = False) -> Volume:
    """Air with a blob of soft tissue and lung, scattered lung-density specks (a plane with few
    of them is not content) and a few sure voxels (always content), on a cropped grid;
    `held_open`: with bone at two opposite corners, so that the box (hence the grid) is the whole."""
    rng = np.random.default_rng(seed)
    shape = (14, 37, 41)
    hu = np.full(shape, -1000, np.int16)
    z, y, x = np.indices(shape)
    c = rng.uniform([4, 10, 12], [10, 27, 29])
    blob = ((z - c[0]) / 4.0) ** 2 + ((y - c[1]) / 9.0) ** 2 + ((x - c[2]) / 11.0) ** 2 <= 1.0
    hu[blob] = rng.choice([-850, 40], size=blob.sum())
    specks = rng.random(shape) < 0.004
    hu[specks] = -700
    hu[tuple(rng.integers(0, shape, size=(2, 3)).T)] = 1500
    if held_open:
        hu[0, 0, 0] = hu[-1, -1, -1] = 1500
    return Volume(hu=hu, T_ct_from_voxel=np.diag([0.9, 1.1, 2.0, 1.0]), source=f"random {seed}")


@pytest.mark.parametrize("seed", range(4))
def test_planes_are_the_plane_rule_over_every_voxel_and_each_bound_is_reached(seed):
    r = Renderer(flat_profile(32), Materials(), device="cpu")
    vol = random_content(seed)
    prepared = r.prepare(vol)
    outline = prepared.outline
    assert len(outline.normals) == 18
    bounds, p, on_planes = brute_force_bounds(vol.hu, index_from_voxel(prepared, vol), outline.normals)
    np.testing.assert_array_equal(outline.lo, bounds[:, 0])
    np.testing.assert_array_equal(outline.hi, bounds[:, 1])
    values = p @ outline.normals.T                              # (voxels, normals)
    # Every voxel on content planes of every normal lies within every plane.
    kept = on_planes.all(axis=1)
    inside = values[kept]
    assert np.all(inside >= outline.lo - 1e-9) and np.all(inside <= outline.hi + 1e-9)
    # Tight: each bound is reached by a voxel above EMPTY_MAX_HU on that normal's content planes
    # (it may be a speck another normal's rule leaves out, so not always one of `kept`).
    for j in range(len(outline.normals)):
        assert values[on_planes[:, j], j].min() == outline.lo[j] and values[on_planes[:, j], j].max() == outline.hi[j]
    # The specks make the rule matter: some lie outside a plane (a speck on a plane of its own);
    # a voxel above SURE_CONTENT_HU never does.
    sure = vol.hu[tuple(np.nonzero(vol.hu > EMPTY_MAX_HU))] > SURE_CONTENT_HU
    assert np.all(kept[sure]) and not np.all(kept)


def voxels_inside(outline, q: np.ndarray) -> np.ndarray:
    v = q @ outline.normals.T
    return np.all((v >= outline.lo - 1e-6) & (v <= outline.hi + 1e-6), axis=1)


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("thickness", [2, 1], ids=["slabs", "layout"])
def test_slab_and_layout_copies_keep_every_content_voxel_in_their_grid(axis, thickness):
    r = Renderer(flat_profile(32), Materials(), device="cpu")
    vol = random_content(7)
    prepared = r.prepare(vol)
    _, p, on_planes = brute_force_bounds(vol.hu, index_from_voxel(prepared, vol), prepared.outline.normals)
    kept = on_planes.all(axis=1)
    copy = SlabCache(r.dev, 2, thickness).get(prepared, axis)
    # Slab q >= PAD along the axis holds padded slices thickness * (q - PAD) + PAD on (slabs.py).
    q = np.rint(p[kept]).astype(int)
    q[:, axis] = (q[:, axis] - PAD) // thickness + PAD
    assert np.all(voxels_inside(copy.outline, q.astype(float)))
    if thickness == 1:           # the same voxels, the same grid: the same planes
        np.testing.assert_allclose(copy.outline.lo, prepared.outline.lo)
        np.testing.assert_allclose(copy.outline.hi, prepared.outline.hi)
