"""The content's outline (outline.py): its planes against brute force over every voxel, its copies
in the slab and layout grids and the union of two phases keeping every content voxel, and casts
clipped to it against casts clipped to the box alone: the same tissue, bone and contrast on every
pixel in both kernels, only air dropped; a steel ball where a diagonal plane would cut it kept."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from synthetic_chest import chest

from appliance.config.case import Materials
from appliance.geometry import make_transform, rotation_about
from appliance.patient.volume import Volume
from appliance.xray.bench import flat_profile
from appliance.xray.casting import (
    EMPTY_MAX_HU,
    EMPTY_PLANE_MAX_VOXELS,
    JOSEPH_REACH,
    OUTLINE_MARGIN,
    PAD,
    SURE_CONTENT_HU,
    Caster,
)
from appliance.xray.projection_cache import ProjectionCache
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.slabs import SlabCache, Through, slab_cast
from appliance.xray.truth.analytic import ellipsoid_volume, pixel_rays_ct

SIZE = 128
#: Rays along the volume's y (posterior-anterior), x (lateral) and an oblique one (xray axes in ct rows).
PA = make_transform(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]), [4.0, 2.0, 700.0])
LATERAL = make_transform(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), [-3.0, 4.0, 700.0])
OBLIQUE = make_transform(rotation_about([1.0, 0.4, -0.3], np.radians(25)), [-5.0, 6.0, 700.0])


@pytest.fixture(scope="module", params=[True, False], ids=["packet", "per-ray"])
def renderer(request):
    """Both kernels: the CPU's 16-ray packets and the one ray per work-item that GPUs run."""
    return Renderer(flat_profile(SIZE), Materials(), device="cpu", packet=request.param)


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


def test_two_phases_are_clipped_to_the_union_of_their_planes():
    r = Renderer(flat_profile(32), Materials(), device="cpu")
    a_vol, b_vol = random_content(1, held_open=True), random_content(2, held_open=True)
    a, b = r.prepare(a_vol), r.prepare(b_vol)
    assert a.same_grid(b)
    normals = a.outline.normals
    ba = brute_force_bounds(a_vol.hu, index_from_voxel(a, a_vol), normals)[0]
    bb = brute_force_bounds(b_vol.hu, index_from_voxel(b, b_vol), normals)[0]
    lo, hi = np.minimum(ba[:, 0], bb[:, 0]), np.maximum(ba[:, 1], bb[:, 1])
    assert np.any(ba != bb)
    grow = JOSEPH_REACH * np.abs(normals).sum(axis=1) + OUTLINE_MARGIN
    planes = Caster._planes(a, b)
    assert planes[0] == len(normals)
    rows = planes[1:].reshape(-1, 5)
    np.testing.assert_allclose(rows[:, :3], normals)
    np.testing.assert_allclose(rows[:, 3], lo - grow, atol=1e-3)
    np.testing.assert_allclose(rows[:, 4], hi + grow, atol=1e-3)
    # A phase without an outline leaves the box alone to clip.
    assert Caster._planes(a, dataclasses.replace(b, outline=None)).tolist() == [0.0]


#: The air around a body as a scanner may read it, 0.04 g/cm^3, at or below EMPTY_MAX_HU (so no
#: content): what a cast clipped to the outline drops shows in the air channel (-1000 weighs 0).
HAZE_HU = -960


def hazy(hu: np.ndarray) -> np.ndarray:
    return np.where(hu == -1000, HAZE_HU, hu).astype(np.int16)


def chest_with_arms() -> Volume:
    """The synthetic chest (body, lungs, spine, ribs) widened by air along x, with an arm on each
    side: a soft cylinder with a bone in it along z, apart from the body by air."""
    vol = chest()
    widen = 16
    hu = np.pad(vol.hu, ((0, 0), (0, 0), (widen, widen)), constant_values=-1000)
    T = np.array(vol.T_ct_from_voxel, float)
    T[0, 3] -= widen * T[0, 0]
    z, y, x = np.indices(hu.shape)
    for centre in (8, hu.shape[2] - 9):
        r2 = (x - centre) ** 2 + (y - 30) ** 2
        hu[(r2 <= 36) & (z > 10)] = 40
        hu[(r2 <= 4) & (z > 10)] = 900
    return Volume(hu=hazy(hu), T_ct_from_voxel=T, source="chest with arms")


def oblique_ellipsoid() -> Volume:
    vol = ellipsoid_volume((30, 40, 36), (1.25, 1.0, 2.2), (3.0, -2.0, 4.0), (18.0, 16.0, 28.0), hu=40)
    T = make_transform(rotation_about([0.3, 1.0, 0.2], np.radians(35)), [2.0, 1.0, -3.0]) @ vol.T_ct_from_voxel
    return Volume(hu=hazy(vol.hu), T_ct_from_voxel=T, source="oblique ellipsoid")


def outline_against_box(renderer, prepared, pose, blend=None):
    view = View()
    got = renderer.material_integrals(prepared, pose, view, blend=blend)
    box_only = dataclasses.replace(prepared, outline=None)
    other = None if blend is None else (dataclasses.replace(blend[0], outline=None), blend[1])
    return got, renderer.material_integrals(box_only, pose, view, blend=other)


@pytest.mark.parametrize("pose", [PA, LATERAL, OBLIQUE], ids=["pa", "lateral", "oblique"])
@pytest.mark.parametrize("make", [chest_with_arms, oblique_ellipsoid], ids=["chest", "ellipsoid"])
def test_a_cast_clipped_to_the_outline_drops_only_air(renderer, make, pose):
    prepared = renderer.prepare(make())
    got, box = outline_against_box(renderer, prepared, pose)
    assert box[..., 1].max() > 20                        # tissue in the field
    # Soft tissue, bone, contrast: the samples dropped weigh no content voxel, and those kept
    # are weighed as the box-only cast weighs them.
    np.testing.assert_array_equal(got[..., 1:], box[..., 1:])
    # Air: never gained, and dropped along some rays (the outline cuts the box's corners).
    assert np.all(got[..., 0] <= box[..., 0] + 1e-6)
    assert np.any(got[..., 0] < box[..., 0] - 1e-3)


def test_two_phases_blended_drop_only_air(renderer):
    vol = chest_with_arms()
    hu = np.full_like(vol.hu, HAZE_HU)
    hu[:-4] = vol.hu[4:]
    a = renderer.prepare(vol)
    b = renderer.prepare(Volume(hu=hu, T_ct_from_voxel=vol.T_ct_from_voxel, source="next phase"))
    got, box = outline_against_box(renderer, a, OBLIQUE, blend=(b, 0.4))
    np.testing.assert_array_equal(got[..., 1:], box[..., 1:])
    assert np.all(got[..., 0] <= box[..., 0] + 1e-6) and np.any(got[..., 0] < box[..., 0] - 1e-3)


def test_a_steel_ball_where_a_diagonal_plane_would_cut_it_is_kept(renderer):
    """One voxel of +3000 HU in a corner of the box the body leaves empty: on a plane of its own
    along every diagonal, it is content by SURE_CONTENT_HU, and a ray through it reads its bone."""
    shape = (20, 48, 48)
    z, y, x = np.indices(shape)
    hu = np.where((x - 20) ** 2 + (y - 20) ** 2 <= 15 ** 2, 40, -1000).astype(np.int16)
    ball = (10, 44, 44)                                   # (k, j, i): beyond the disc's diagonal
    T = np.diag([8.0, 8.0, 2.0, 1.0])          # voxels five pixels wide: their footprint well sampled
    body = renderer.prepare(Volume(hu=hu, T_ct_from_voxel=T, source="disc"))
    hu[ball] = 3000
    vol = Volume(hu=hu, T_ct_from_voxel=T, source="disc and ball")
    prepared = renderer.prepare(vol)
    p = index_from_voxel(prepared, vol) @ np.array([ball[2], ball[1], ball[0], 1.0])
    # Where the ball is, the body's own outline (same grid) would not reach; with it, every plane does.
    assert body.same_grid(prepared)
    assert not voxels_inside(body.outline, p[None, :3])[0]
    assert voxels_inside(prepared.outline, p[None, :3])[0]
    pose = make_transform(np.eye(3), [-352.0, -352.0, 700.0])       # rays along z, the ball's on the axis
    got, box = outline_against_box(renderer, prepared, pose)
    np.testing.assert_array_equal(got[..., 1:], box[..., 1:])
    # Its bone over the pixels: density x voxel volume (its bilinear footprint integrates to one
    # voxel's area), each pixel's ray weighed by its footprint (mm^2) at the ball's depth.
    m = Materials()
    at_min = 1.0 + m.bone_min_hu / 1000.0
    density = at_min + (3000 - m.bone_min_hu) * (m.bone_density_at_1000_hu_g_per_cm3 - at_min) / (1000.0 - m.bone_min_hu)
    depth_mm = (pose @ np.asarray(T) @ np.array([ball[2], ball[1], ball[0], 1.0]))[2]
    fl = renderer.caster.fluoroscope
    pixel_mm = depth_mm * fl.detector.pixel_pitch_mm / fl.geometry.source_to_image_mm
    mass = got[..., 2].sum() * pixel_mm ** 2
    assert mass == pytest.approx(density * 8.0 * 8.0 * 2.0, rel=0.01)


def test_casts_through_slabs_and_the_two_phase_pass_drop_only_air():
    """The moving frames' cast through pre-integrated slabs (slab_cast) and the projection cache's
    one pass over two phases (SPLIT), each against the same cast of the phases without outline."""
    r = Renderer(flat_profile(SIZE), Materials(), device="cpu", packet=True)
    vol = chest_with_arms()
    hu = np.full_like(vol.hu, HAZE_HU)
    hu[:-4] = vol.hu[4:]
    a = r.prepare(vol)
    b = r.prepare(Volume(hu=hu, T_ct_from_voxel=vol.T_ct_from_voxel, source="next phase"))
    bare = [dataclasses.replace(p, outline=None) for p in (a, b)]
    rows, cols = r.caster.shape

    def download(buf) -> np.ndarray:
        return r.dev.download(buf, np.empty((rows, cols, 4), np.float32))

    cache = SlabCache(r.dev, 4)
    for pose in (PA, LATERAL):
        got, box = (download(slab_cast(r.caster, cache, p, pose, 1, None, np.inf)(p, pose, 1, None, None, False, False)[0])
                    for p in (a, bare[0]))
        np.testing.assert_array_equal(got[..., 1:], box[..., 1:])
        assert np.all(got[..., 0] <= box[..., 0] + 1e-6) and np.any(got[..., 0] < box[..., 0] - 1e-3)
    split = ProjectionCache(r)
    got = [download(x) for x in split.cast_two(Through(a), Through(b), OBLIQUE, 1, None, False, False)]
    box = [download(x) for x in split.cast_two(*map(Through, bare), OBLIQUE, 1, None, False, False)]
    for g, x in zip(got, box):
        assert x[..., 1].max() > 20
        np.testing.assert_array_equal(g[..., 1:], x[..., 1:])
        assert np.all(g[..., 0] <= x[..., 0] + 1e-6) and np.any(g[..., 0] < x[..., 0] - 1e-3)


@pytest.mark.parametrize("shift_mm", [0.0, 60.0, 110.0], ids=["middle", "side", "edge"])
def test_a_cast_takes_every_plane_that_cuts_a_ray_of_its_field_and_no_other(shift_mm):
    """The planes a cast is given (outline.cutting) against brute force: points along every
    pixel's ray within the box, each plane kept where some point lies beyond it."""
    r = Renderer(flat_profile(64), Materials(), device="cpu")
    prepared = r.prepare(chest_with_arms())
    pose = PA.copy()
    pose[0, 3] -= shift_mm                                  # the field moved toward the patient's left
    box = Caster._box(prepared)
    given = r.caster._field_planes((prepared,), box, pose, 1, True)[1:].reshape(-1, 5)
    every = Caster._planes(prepared)[1:].reshape(-1, 5)
    s, d = pixel_rays_ct(zoomed_K(r.fluoroscope, 1), pose, 64, 64)
    A = prepared.T_index_from_ct
    s, d = A[:3, :3] @ s + A[:3, 3], d.reshape(-1, 3) @ A[:3, :3].T
    lo, hi = box[:3] - 1.0, box[4:7] + 1.0
    ta, tb = (lo - s) / d, (hi - s) / d
    t0, t1 = np.minimum(ta, tb).max(axis=1), np.maximum(ta, tb).min(axis=1)
    f = np.linspace(0.0, 1.0, 200)
    points = (s + (t0[:, None] + f * (t1 - t0)[:, None])[..., None] * d[:, None, :])[t1 > t0].reshape(-1, 3)
    v = points @ every[:, :3].T
    cut = (v.min(axis=0) < every[:, 3] - 0.5) | (v.max(axis=0) > every[:, 4] + 0.5)
    kept = np.array([any(np.allclose(g, e) for g in given) for e in every])
    assert np.all(kept[cut]), "a plane that cuts a ray of the field was left out"
    # And none given that no point comes within half a voxel of; the z planes cut none of these.
    near = (v.min(axis=0) < every[:, 3] + 0.5) | (v.max(axis=0) > every[:, 4] - 0.5)
    assert not np.any(kept & ~near) and cut.any() and not kept.all()
