"""The slab copies' rules beside their averaging (tests/test_slabs.py): which axis a view is
cast along, how many copies the cache keeps and which it lets go, and a moving frame between
two breathing phases cast through the slabs of both.

Ground truth: the axis a ray crosses most slices of, worked by hand from its direction and the
voxel spacing; the cache's order of use, kept by hand; the closed-form chords of two boxes,
blended by the phase weight (the blend of two water boxes in air is linear in density).
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.geometry import make_transform
from appliance.patient.volume import Volume
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer, zoomed_K
from appliance.xray.slabs import SlabCache, dominant_axis, slab_cast
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

AXIAL = make_transform(np.eye(3), [4.0, -3.0, 700.0])          # rays along the volume's +z


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(128), Materials(), device="cpu")


def looking_along(direction) -> np.ndarray:
    """T_xray_from_ct of a view whose principal ray runs along `direction` (ct frame)."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    R_ct_from_xray = np.column_stack([x, np.cross(z, x), z])
    return make_transform(R_ct_from_xray.T, [0.0, 0.0, 700.0])


def grid_volume(renderer, spacing_mm, hu_fill=0) -> object:
    hu = np.full((8, 8, 8), -1000, np.int16)
    hu[2:6, 2:6, 2:6] = hu_fill
    return renderer.prepare(Volume(hu=hu, T_ct_from_voxel=np.diag([*spacing_mm, 1.0]), source="cube"))


@pytest.mark.parametrize("direction, axis", [
    ((0.0, 0.0, 1.0), 2), ((0.0, 0.0, -1.0), 2),      # head to foot or foot to head: the same slices
    ((-1.0, 0.0, 0.0), 0), ((0.0, -1.0, 0.0), 1),     # lateral from the left, AP from behind
    ((0.3, 0.2, -0.9), 2),                            # mostly along -z: z, though x is the largest positive part
])
def test_the_dominant_axis_is_the_one_crossed_most_either_way(renderer, direction, axis):
    assert dominant_axis(grid_volume(renderer, (1.0, 1.0, 1.0)), looking_along(direction)) == axis


def test_the_dominant_axis_counts_slices_not_millimetres(renderer):
    """40 degrees from z toward x on 0.5 mm columns and 2.5 mm slices: per mm of the ray it
    crosses sin 40 / 0.5 = 1.29 columns and cos 40 / 2.5 = 0.31 slices, so x, though the ray
    runs farther along z (0.77 mm against 0.64 mm)."""
    a = np.radians(40.0)
    assert dominant_axis(grid_volume(renderer, (0.5, 1.0, 2.5)), looking_along((np.sin(a), 0.0, np.cos(a)))) == 0
    assert dominant_axis(grid_volume(renderer, (1.0, 1.0, 1.0)), looking_along((np.sin(a), 0.0, np.cos(a)))) == 2


def test_the_cache_keeps_the_last_used_copies_and_lets_the_oldest_go(renderer):
    a, b, c = (grid_volume(renderer, (2.0, 2.0, 2.0)) for _ in range(3))
    cache = SlabCache(renderer.dev, 2)
    slab_a, slab_b = cache.get(a, 2), cache.get(b, 2)
    assert cache.made == 2
    one = slab_a.nbytes
    # Two kept: both are still there (no copy made again), the cache holding both.
    assert cache.get(a, 2) is slab_a and cache.get(b, 2) is slab_b and cache.made == 2 and cache.nbytes == 2 * one
    # Order of use now: a, b. a used again, then c comes: b, the least recently used, goes.
    assert cache.get(a, 2) is slab_a
    cache.get(c, 2)
    assert cache.made == 3 and cache.nbytes == 2 * one
    assert cache.get(a, 2) is slab_a and cache.made == 3
    assert cache.get(b, 2) is not slab_b and cache.made == 4
    # Another axis of the same phase is a copy of its own.
    assert cache.get(b, 0) is not cache.get(b, 2) and cache.made == 5


def test_a_frame_between_two_phases_is_cast_through_the_slabs_of_both(renderer):
    """Two water boxes in air on one grid, the second 4 voxels (6 mm) further along x, blended
    with a weight of 1/4 on the second: each ray's water path is 3/4 of its chord through the
    first plus 1/4 of its chord through the second, within the display path's 0.6 % bar."""
    shape, spacing = (48, 64, 64), (1.5, 1.25, 2.5)
    vol_a, lo_a, hi_a = box_volume(shape, spacing, (9, 14, 5), (52, 47, 40))
    vol_b, lo_b, hi_b = box_volume(shape, spacing, (13, 14, 5), (56, 47, 40))
    first, second = renderer.prepare(vol_a), renderer.prepare(vol_b)
    K = zoomed_K(renderer.fluoroscope, 1)
    s, d = pixel_rays_ct(K, AXIAL, 128, 128)
    truth = 0.75 * box_chords(s, d, lo_a, hi_a) + 0.25 * box_chords(s, d, lo_b, hi_b)
    cache = SlabCache(renderer.dev, 2)
    cast = slab_cast(renderer.caster, cache, first, AXIAL, 1, (second, 0.25), 1.0)
    assert cast is not None
    buf, _ = cast(first, AXIAL, 1, None, (second, 0.25), False, False)
    assert cache.made == 2                       # a slab copy of each phase
    lines = renderer.dev.download(buf, np.empty((128, 128, 4), np.float32)).sum(-1)
    sel = truth > 10.0
    rel = np.abs(lines[sel] - truth[sel]) / truth[sel]
    assert sel.sum() > 1000 and rel.mean() < 0.006
    # Where only the first box lies (its first 4 columns of voxels) the path is 3/4 of its chord,
    # where only the second, 1/4: the weight is the second phase's.
    chord_a, chord_b = box_chords(s, d, lo_a, hi_a), box_chords(s, d, lo_b, hi_b)
    for only, weight in (((chord_b == 0) & (chord_a > 10.0), 0.75), ((chord_a == 0) & (chord_b > 10.0), 0.25)):
        assert only.sum() > 50
        assert np.median(lines[only] / (chord_a + chord_b)[only]) == pytest.approx(weight, rel=0.01)
