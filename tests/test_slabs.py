"""Pre-integrated slabs: the device's pair averages against NumPy's, a cast through them against
the closed-form chords of a box and a sphere, the shift rule that keeps them off steep rays, and
moving frames cast through them, a held view only where the profile's rest rule allows."""

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.config.rendering import Rendering
from appliance.geometry import make_transform, rotation_about
from appliance.patient.adult_chest import SIZES, build_adult_chest
from appliance.patient.volume import Volume
from appliance.xray.bench import flat_profile
from appliance.xray.casting import PAD
from appliance.xray.progressive import ProgressiveRenderer
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.slabs import SlabCache, dominant_axis, in_slab_shift_px, slab_cast
from appliance.xray.truth.analytic import box_chords, box_volume, ellipsoid_chords, ellipsoid_volume, pixel_rays_ct

AXIAL = make_transform(np.eye(3), [4.0, -3.0, 700.0])          # rays along the volume's z
# Rays along the volume's x (a lateral view) and y (posterior-anterior): xray axes in ct rows.
ALONG_X = make_transform(np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), [-3.0, 4.0, 700.0])
ALONG_Y = make_transform(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]), [4.0, 2.0, 700.0])
OBLIQUE = make_transform(rotation_about([1.0, 0.4, -0.3], np.radians(25)), [-5.0, 6.0, 700.0])


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(128), Materials(), device="cpu")


def padded_hu(renderer, prepared) -> np.ndarray:
    """(z, y, x) HU of a prepared volume: the plain layout as it is; a slab copy's layout for rays
    along its axis a (rows along b, then a, then c) turned back."""
    nx, ny, nz = prepared.shape_xyz
    if prepared.slab_axis < 0:
        return renderer.dev.download(prepared.buffer, np.empty((nz, ny, nx), np.int16))
    a = prepared.slab_axis
    b, c = (1, 2) if a == 0 else (0, 2) if a == 1 else (0, 1)
    dims = prepared.shape_xyz
    rows = renderer.dev.download(prepared.buffer, np.empty((dims[c], dims[a], dims[b]), np.int16))
    # Axes (c, a, b) to (z, y, x): the array axis of x (index axis 0) is the last.
    return np.transpose(rows, [(c, a, b).index(2 - i) for i in range(3)])


@pytest.mark.parametrize("thickness", [2, 4])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_slabs_are_the_slices_averaged_and_rounded_half_to_even(renderer, axis, thickness):
    rng = np.random.default_rng(axis)
    # Lengths no multiple of the thickness: a last slab part air. Slabs along x (45 and 83 voxels)
    # are made in tiles of sixteen rows of y (19 and the padding) and the rest row by row; slabs
    # along y or z sixteen voxels of x at a time and the rest one by one.
    hu = rng.integers(-1000, 3000, size=(13, 19, 45 if thickness == 2 else 83)).astype(np.int16)
    hu[0, 0, :12] = hu[0, 0, -12:] = [-3, -1, 1, 3, 5, 0, -2, 4, 7, 8, -6, 9]   # sums ending in .5 both ways
    hu[1, 1, :8] = [-1, -2, -2, -1, 1, 0, 2, 3]                  # .5 of four both ways, .25 and .75
    T = np.diag([0.9, 1.1, 2.0, 1.0])
    prepared = renderer.prepare(Volume(hu=hu, T_ct_from_voxel=T, source="noise"))
    cache = SlabCache(renderer.dev, 2, thickness)
    slab = cache.get(prepared, axis)
    got = padded_hu(renderer, slab)
    src = padded_hu(renderer, prepared).astype(np.float64)
    inner = np.moveaxis(src, 2 - axis, 0)[PAD:-PAD]                         # this axis first, pads off
    missing = -len(inner) % thickness
    inner = np.concatenate([inner, np.full((missing, *inner.shape[1:]), -1000.0)])
    expected = np.round(sum(inner[j::thickness] for j in range(thickness)) / thickness)   # half to even
    expected = np.pad(expected, [(PAD, PAD), (0, 0), (0, 0)], constant_values=-1000)
    np.testing.assert_array_equal(np.moveaxis(got, 2 - axis, 0), expected)
    # Where each slab lies: the middle of slab q is between its middle two slices.
    ct_from_slab, ct_from_index = np.linalg.inv(slab.T_index_from_ct), np.linalg.inv(prepared.T_index_from_ct)
    q = np.array([3.0, 4.0, 5.0, 1.0])
    p = q.copy()
    p[axis] = thickness * (q[axis] - PAD) + PAD + (thickness - 1) / 2.0
    np.testing.assert_allclose(ct_from_slab @ q, ct_from_index @ p, atol=1e-9)
    assert cache.get(prepared, axis) is slab and cache.made == 1          # made once, then kept


def chord_error(renderer, lines, truth_mm, min_mm):
    sel = truth_mm > min_mm
    got = lines.sum(-1)
    return np.abs(got[sel] - truth_mm[sel]) / truth_mm[sel], sel.sum()


@pytest.mark.parametrize("thicker", [False, True])
@pytest.mark.parametrize("name, pose, axis", [("box", AXIAL, 2), ("box", ALONG_X, 0), ("box", ALONG_Y, 1),
                                              ("sphere", AXIAL, 2), ("sphere", ALONG_X, 0)])
def test_a_cast_through_slabs_keeps_the_display_paths_accuracy_bar(renderer, name, pose, axis, thicker):
    """Water density (HU 0) along each ray, cast through the slabs (laid out for rays along each
    of the three axes), against the closed-form chord: mean error within the 0.6 % bar of the
    display path where the shift rule lets it, and within 0.05 % of the full volume's own (over
    paths above 10 mm in the box, 20 mm in the sphere, whose grazing rays cross its
    partial-volume rim at a slant, as in bench drr); `thicker`: the field's middle through slabs
    of four slices as the appliance casts it, within 0.1 % of the full volume's."""
    K = zoomed_K(renderer.fluoroscope, 1)
    s, d = pixel_rays_ct(K, pose, 128, 128)
    if name == "box":
        vol, lo, hi = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 5), (52, 47, 40))
        truth, min_mm = box_chords(s, d, lo, hi), 10.0
    else:
        centre, axes = (3.0, -2.0, 4.0), (30.0, 30.0, 30.0)
        vol = ellipsoid_volume((48, 72, 64), (1.25, 1.0, 1.5), centre, axes)
        truth, min_mm = ellipsoid_chords(s, d, centre, axes), 20.0
    prepared = renderer.prepare(vol)
    assert dominant_axis(prepared, pose) == axis
    assert in_slab_shift_px(K, renderer.shape, prepared, pose, axis) < 1.0
    cache = SlabCache(renderer.dev, 2, thicker=thicker)
    cast = slab_cast(renderer.caster, cache, prepared, pose, 1, None, 1.0)
    assert cast is not None
    buf, _ = cast(prepared, pose, 1, None, None, False, False)
    lines = renderer.dev.download(buf, np.empty((128, 128, 4), np.float32))
    rel, n = chord_error(renderer, lines, truth, min_mm)
    assert n > 1000 and rel.mean() < 0.006
    full = renderer.material_integrals(prepared, pose, View(), distorted=False, circle=False)
    assert rel.mean() < chord_error(renderer, full, truth, min_mm)[0].mean() + (0.001 if thicker else 0.0005)
    assert (cache.thicker is not None and cache.thicker.made == 1) == thicker      # four-slice slabs cast


def test_steep_rays_are_cast_through_the_full_volume(renderer):
    """The oblique view of a thick-sliced grid shifts several pixels within a slab: no slabs."""
    vol, _, _ = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 6), (52, 47, 40))
    prepared = renderer.prepare(vol)
    K = zoomed_K(renderer.fluoroscope, 1)
    axis = dominant_axis(prepared, OBLIQUE)
    shift = in_slab_shift_px(K, renderer.shape, prepared, OBLIQUE, axis)
    assert shift > 2.0
    cache = SlabCache(renderer.dev, 2)
    assert slab_cast(renderer.caster, cache, prepared, OBLIQUE, 1, None, 1.0) is None and cache.made == 0
    assert slab_cast(renderer.caster, cache, prepared, OBLIQUE, 1, None, shift + 0.1) is not None


@pytest.fixture(scope="module")
def chest_phases(renderer):
    """The adult chest on the quick grid and a second phase on its grid (its slices shifted one
    down): ribs, vessels and lung, whose edges a packet's choice of grid would show."""
    hu, spacing, origin = build_adult_chest(*SIZES["small"], seed=2)
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    T[:3, 3] = origin
    return (renderer.prepare(Volume(hu=hu, T_ct_from_voxel=T, source="adult chest")),
            renderer.prepare(Volume(hu=np.roll(hu, 1, axis=0), T_ct_from_voxel=T, source="adult chest, moved")))


def ray_shift_px(K, pose, prepared, axis, shape):
    """Each pixel's ray's shift across `axis` within one slab (pixels), from first principles: the
    two points of the (undistorted) ray SLAB voxels apart along the axis, their offset across it
    in mm, seen at the depth of the content box's middle through the pinhole's focal length."""
    _, d = pixel_rays_ct(K, pose, *shape)
    index_from_ct = prepared.T_index_from_ct[:3, :3]
    step = d @ index_from_ct.T                                       # voxel indices per mm of ray
    step = step * (2.0 / np.abs(step[..., axis]))[..., None]         # across one slab, two slices
    step[..., axis] = 0.0
    across_mm = np.linalg.norm(step @ np.linalg.inv(index_from_ct).T, axis=-1)
    centre = np.append((np.asarray(prepared.box[0], float) + prepared.box[1]) / 2.0, 1.0)
    depth = (pose @ np.linalg.inv(prepared.T_index_from_ct) @ centre)[2]
    return across_mm * K[0, 0] / depth


#: A posterior-anterior view tilted 12 degrees: the quick chest's steepest ray shifts about twice
#: as far within a slab as its principal ray; and a lateral one (whose full volume the caster
#: reads through its copy laid out for rays along x).
TILTED = make_transform(rotation_about([1.0, 0.2, 0.0], np.radians(12)) @ ALONG_Y[:3, :3], [4.0, 2.0, 700.0])
TILTED_LATERAL = make_transform(rotation_about([0.2, 1.0, 0.0], np.radians(12)) @ ALONG_X[:3, :3], [-3.0, 4.0, 700.0])


def between_rays(renderer, prepared, pose) -> float:
    """A rule halfway between the principal ray's shift within a slab and the steepest ray's."""
    K = zoomed_K(renderer.fluoroscope, 1)
    axis = dominant_axis(prepared, pose)
    return (in_slab_shift_px(K, renderer.shape, prepared, pose, axis)
            + in_slab_shift_px(K, renderer.shape, prepared, pose, axis, principal=True)) / 2.0


def packet_plan(renderer, prepared, pose, limit, on=None, axis=None):
    """Pixel masks (thin, clear): the packets all of whose rays (on the beam `on`) shift at most
    `limit` within two voxels of `prepared` along `axis` (ray_shift_px; None: its dominant axis),
    and those not on the rule's edge in float32."""
    K = zoomed_K(renderer.fluoroscope, 1)
    shift = ray_shift_px(K, pose, prepared, dominant_axis(prepared, pose) if axis is None else axis, renderer.shape)
    if on is not None:
        shift = np.where(on, shift, 0.0)
    rows, cols = renderer.shape
    packets = shift.reshape(rows, cols // 16, 16).max(-1)
    clear = np.abs(packets - limit) > 1e-3 * limit
    return np.repeat(packets <= limit, 16, axis=1), np.repeat(clear, 16, axis=1)


def assert_packet_by_packet(got, slabs, full, thin, clear):
    assert 0.2 < thin.mean() < 0.8 and clear.mean() > 0.95
    np.testing.assert_array_equal(got[clear & thin], slabs[clear & thin])
    np.testing.assert_array_equal(got[clear & ~thin], full[clear & ~thin])
    assert not np.array_equal(slabs[thin], full[thin])               # the two grids do differ there


@pytest.mark.parametrize("pose", [TILTED, TILTED_LATERAL], ids=["pa", "lateral"])
@pytest.mark.parametrize("blended", [False, True])
def test_where_only_some_rays_allow_slabs_each_packet_takes_its_own_grid(renderer, chest_phases, blended, pose):
    """A moving frame whose field's steepest ray shifts more than the rule within a slab, but its
    principal ray less: each sixteen-pixel packet all of whose rays shift at most the rule's
    pixels (worked out ray by ray above) is the cast through the slabs to the bit, every other
    one the cast through the full volume to the bit, for a phase alone and for two blended."""
    a, b = chest_phases
    limit = between_rays(renderer, a, pose)
    blend = (b, 0.3) if blended else None
    if pose is TILTED_LATERAL:                   # every ray along x: the layout copy's rows
        assert renderer.caster.layouts is not None and renderer.caster.dominant_axis_of_field(a, pose, 1, False) == 0
    cache = SlabCache(renderer.dev, 2)
    mixed = slab_cast(renderer.caster, cache, a, pose, 1, blend, limit)
    assert mixed is not None

    def lines(cast):
        buf, _ = cast(a, pose, 1, None, blend, False, False)
        return renderer.dev.download(buf, np.empty(renderer.shape + (4,), np.float32))
    got = lines(mixed)
    slabs = lines(slab_cast(renderer.caster, cache, a, pose, 1, blend, np.inf))
    full = lines(renderer.caster.cast)
    assert_packet_by_packet(got, slabs, full, *packet_plan(renderer, a, pose, limit))


@pytest.mark.parametrize("blended", [False, True])
def test_a_field_every_ray_of_which_allows_slabs_takes_slabs_of_four_in_its_middle(renderer, chest_phases,
                                                                                    blended):
    """A moving frame whose every ray shifts less than the rule within a slab, and whose
    principal ray less within a slab of four slices (SlabCache's `thicker`): the packets all of
    whose rays do (worked out ray by ray on the slab copy's grid, whose two voxels are four
    slices) are the whole-field cast through slabs of four to the bit, the others the whole-field
    cast through slabs of two."""
    a, b = chest_phases
    pose = ALONG_Y
    K = zoomed_K(renderer.fluoroscope, 1)
    axis = dominant_axis(a, pose)
    cache = SlabCache(renderer.dev, 2, thicker=True)
    assert cache.thicker is not None
    two, four = cache.get(a, axis), cache.thicker.get(a, axis)
    steepest = in_slab_shift_px(K, renderer.shape, a, pose, axis)
    principal_four = in_slab_shift_px(K, renderer.shape, two, pose, axis, principal=True)
    limit = steepest + principal_four / 2.0              # every ray within two; the middle within four
    assert principal_four < limit < 2 * steepest
    blend = (b, 0.3) if blended else None

    def lines(volume, other=None, thin=None):
        buf, _ = renderer.caster.cast(volume, pose, 1, None, None if blend is None else (other, blend[1]),
                                      False, False, thin=thin)
        return renderer.dev.download(buf, np.empty(renderer.shape + (4,), np.float32))
    got = slab_cast(renderer.caster, cache, a, pose, 1, blend, limit)
    assert got is not None
    got_lines = renderer.dev.download(got(a, pose, 1, None, blend, False, False)[0],
                                      np.empty(renderer.shape + (4,), np.float32))
    others = (cache.get(b, axis), cache.thicker.get(b, axis)) if blended else (None, None)
    assert_packet_by_packet(got_lines, lines(four, others[1]), lines(two, others[0]),
                            *packet_plan(renderer, two, pose, limit, axis=axis))


def test_a_held_view_goes_through_the_slabs_packet_by_packet_too(renderer, chest_phases):
    """A held view under rendering.rest_slab_max_shift_px between the principal and the steepest
    ray's shift: its cached integrals, cast at once and in bands beside the live frames, and the
    pair of phases cast in one pass (SPLIT, each through its own slab copy), are packet by packet
    the whole-field casts through the slabs and through the full volume, to the bit."""
    a, b = chest_phases
    pose = TILTED
    limit = between_rays(renderer, a, pose)
    circle = renderer._circle(None)
    plan = packet_plan(renderer, a, pose, limit, renderer.caster.beam(1, None, circle).exposed)
    copies = SlabCache(renderer.dev, 2)

    def download(buf):
        return renderer.dev.download(buf, np.empty(renderer.shape + (4,), np.float32))

    def whole(p):                       # the whole field through the slabs, and through the full volume
        through = slab_cast(renderer.caster, copies, p, pose, 1, None, np.inf)
        return (download(through(p, pose, 1, None, None, True, circle)[0]),
                download(renderer.caster.cast(p, pose, 1, None, None, True, circle)[0]))
    pr = ProgressiveRenderer(renderer, Rendering(rest_slab_max_shift_px=limit))
    cache = pr.cache()
    assert_packet_by_packet(cache.material_integrals(a, pose, View()), *whole(a), *plan)
    cache.clear()
    assert cache.fill([a], pose, 1, None, True, circle, 3, lambda: False)
    assert_packet_by_packet(cache.material_integrals(a, pose, View()), *whole(a), *plan)
    through = pr._through(renderer, pr.settings.rest_slab_max_shift_px)
    assert through is not None
    pair = cache.cast_two(through(a, pose, 1), through(b, pose, 1), pose, 1, None, True, circle)
    for got, p in zip(pair, (a, b)):
        assert_packet_by_packet(download(got), *whole(p), *plan)
    cache.clear()                       # the pair at rest, in bands beside the live frames: one pass
    assert cache.fill([a, b], pose, 1, None, True, circle, 3, lambda: False) and cache.counts.paired == 1
    for p in (a, b):
        assert_packet_by_packet(cache.material_integrals(p, pose, View()), *whole(p), *plan)


def test_the_warm_up_builds_the_packet_by_packet_kernels(renderer, chest_phases):
    """A fresh build of the SLABBED kernels takes seconds: the renderer's warm-up makes them for
    every moving matrix, so no frame in a session waits for one."""
    a, _ = chest_phases
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, slab_max_shift_px=1.0))
    pr.warm(a, ALONG_Y)
    for r in (pr.full, *pr._movers.values()):
        assert set(r.caster._joseph_slabbed) == {"SLABBED", "SLABBED BLEND", "SLABBED SPLIT"}


def test_moving_frames_go_through_slabs_and_a_held_view_does_not(renderer):
    vol, _, _ = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 6), (52, 47, 40))
    prepared = renderer.prepare(vol)
    t = [100.0]
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, slab_max_shift_px=1.0),
                             clock=lambda: t[0])
    view = View(seed=1)
    for i in range(4):
        t[0] += 0.04
        pr.render(prepared, make_transform(np.eye(3), [4.0 + i, -3.0, 700.0]), view)
    assert pr.matrix == 64 and pr.slab_casts == 4 and pr.slabs is not None and pr.slabs.made == 1
    t[0] += 0.5
    pr.render(prepared, make_transform(np.eye(3), [7.0, -3.0, 700.0]), view)
    assert pr.matrix == 128 and pr.slab_casts == 4      # the held view: the full volume


@pytest.mark.parametrize("pose", [ALONG_Y, OBLIQUE])
def test_a_held_view_goes_through_the_slabs_only_where_the_rest_rule_allows(renderer, pose):
    """With rendering.rest_slab_max_shift_px, a held view's cached integrals (a phase's alone, and
    each of a pair cast in one pass) are its slab copy's where the field's steepest ray shifts
    less than that within a slab (ALONG_Y: a cast whose accuracy against the closed-form chords
    the test above holds to the display path's bar) and the full volume's, to the bit, where it
    shifts more (OBLIQUE, over 2 px)."""
    vol, _, _ = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 5), (52, 47, 40))
    a, b = renderer.prepare(vol), renderer.prepare(vol)
    shift = in_slab_shift_px(zoomed_K(renderer.fluoroscope, 1), renderer.shape, a, pose, dominant_axis(a, pose))
    assert shift < 1.0 if pose is ALONG_Y else shift > 2.0
    pr = ProgressiveRenderer(renderer, Rendering(rest_slab_max_shift_px=1.0))
    cache, view = pr.cache(), View()
    held = cache.material_integrals(a, pose, view)
    cache.clear()
    paired = cache.material_integrals(a, pose, view, blend=(b, 0.5))
    assert cache.counts.paired == 1
    full = renderer.material_integrals(a, pose, view)
    through = slab_cast(renderer.caster, SlabCache(renderer.dev, 1, thicker=True), a, pose, 1, None, 1.0)
    assert pr.slabs is not None
    if pose is ALONG_Y:
        assert through is not None and pr.slabs.made == 2           # a copy of each phase
        buf, _ = through(a, pose, 1, None, None, True, renderer._circle(None))
        expected = renderer.dev.download(buf, np.empty(renderer.shape + (4,), np.float32))
        assert not np.array_equal(expected, full)
    else:
        assert through is None and pr.slabs.made == 0
        expected = full
    np.testing.assert_array_equal(held, expected)
    np.testing.assert_array_equal(paired, expected)       # the same phase twice: both of the pair alike
    cache.clear()                                         # and cast in bands beside the live frames
    assert cache.fill([a], pose, 1, None, True, renderer._circle(None), 3, lambda: False)
    np.testing.assert_array_equal(cache.material_integrals(a, pose, view), expected)
    cache.clear()                                         # the pair so, in one pass
    assert cache.fill([a, b], pose, 1, None, True, renderer._circle(None), 3, lambda: False)
    assert cache.counts.paired == 2
    for p in (a, b):
        np.testing.assert_array_equal(cache.material_integrals(p, pose, view), expected)


def test_without_the_rest_rule_a_held_view_is_cast_through_the_full_volume(renderer):
    vol, _, _ = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 5), (52, 47, 40))
    a = renderer.prepare(vol)
    pr = ProgressiveRenderer(renderer, Rendering(slab_max_shift_px=1.0))
    np.testing.assert_array_equal(pr.cache().material_integrals(a, ALONG_Y, View()),
                                  renderer.material_integrals(a, ALONG_Y, View()))
    assert pr.slabs is not None and pr.slabs.made == 0


def test_a_phase_let_go_takes_its_slabs_with_it(renderer):
    import gc

    vol, _, _ = box_volume((16, 16, 16), (2.0, 2.0, 2.0), (4, 4, 4), (11, 11, 11))
    cache = SlabCache(renderer.dev, 4)
    kept, dropped = renderer.prepare(vol), renderer.prepare(vol)
    cache.get(kept, 2)
    cache.get(dropped, 2)
    assert cache.made == 2 and cache.nbytes > 0
    one = cache.nbytes // 2
    del dropped
    gc.collect()
    cache.get(kept, 2)                 # still there, and the other's slabs gone
    assert cache.made == 2 and cache.nbytes == one


def test_a_copy_evicted_lends_its_buffer_to_the_next_only_once_nothing_holds_it(renderer):
    """A breathing patient brings a new phase into the copies' cache every few tenths of a second:
    the copy it evicts gives its device buffer to the new one (no fresh pages to fault in), but
    not while a cast may still read it (a copy held elsewhere keeps its slabs)."""
    import gc

    rng = np.random.default_rng(7)
    phases = [renderer.prepare(Volume(hu=rng.integers(-1000, 3000, size=(12, 20, 24)).astype(np.int16),
                                      T_ct_from_voxel=np.diag([1.0, 1.0, 2.0, 1.0]), source=f"phase {i}"))
              for i in range(4)]

    def expected(phase):
        src = padded_hu(renderer, phase).astype(np.float64)[:, PAD:-PAD]     # y first of z, y, x
        return np.round((src[:, 0::2] + src[:, 1::2]) / 2.0)

    cache = SlabCache(renderer.dev, 2)
    held = cache.get(phases[0], 1)
    pointer = held.buffer.int_ptr
    second = cache.get(phases[1], 1).buffer.int_ptr
    third = cache.get(phases[2], 1)            # evicts phase 0's copy, still held here: a buffer of its own
    assert third.buffer.int_ptr != pointer
    np.testing.assert_array_equal(padded_hu(renderer, held)[:, PAD:-PAD], expected(phases[0]))
    del held, third
    gc.collect()
    fourth = cache.get(phases[3], 1)           # evicts phase 1's copy, held nowhere: its buffer reused
    assert cache.made == 4 and cache.nbytes == 2 * fourth.nbytes
    np.testing.assert_array_equal(padded_hu(renderer, fourth)[:, PAD:-PAD], expected(phases[3]))
    assert fourth.buffer.int_ptr == second
    cache.clear()
    assert cache.nbytes == 0


@pytest.mark.parametrize("pose, axis", [(AXIAL, 2), (ALONG_X, 0), (ALONG_Y, 1)])
def test_slab_samples_interpolate_a_linear_density_exactly_across_the_slice(renderer, pose, axis):
    """A box whose HU rises linearly along all three axes: a bilinear sample of a linear
    function is exact, and so is a slab's average along the ray, so through the slabs each
    ray's integral is its chord times the density at the chord's middle (closed form), for rays
    that enter and leave through the faces across the dominant axis, away from the side faces'
    step to air. The rise differs along each axis (1, 6 and 20 HU per voxel, within soft
    tissue's HU), so a sample that takes one in-slice neighbour for the other misses by a few
    HU, several tenths of a per cent."""
    shape, sp = (40, 48, 44), (1.5, 1.25, 2.0)
    lo_i, hi_i = np.array([6, 7, 5]), np.array([37, 40, 34])
    vol, lo, hi = box_volume(shape, sp, tuple(lo_i), tuple(hi_i))
    k, j, i = np.indices(shape)
    ramp = (-790 + 1 * i + 6 * j + 20 * k).astype(np.int16)
    inside = vol.hu > -1000
    vol.hu[inside] = ramp[inside]
    prepared = renderer.prepare(vol)
    assert dominant_axis(prepared, pose) == axis
    cast = slab_cast(renderer.caster, SlabCache(renderer.dev, 1), prepared, pose, 1, None, 1.0)
    assert cast is not None
    buf, _ = cast(prepared, pose, 1, None, None, False, False)
    got = renderer.dev.download(buf, np.empty((128, 128, 4), np.float32)).sum(-1)
    K = zoomed_K(renderer.fluoroscope, 1)
    s, d = pixel_rays_ct(K, pose, 128, 128)
    chord = box_chords(s, d, lo, hi)
    margin = 1.5 * np.array(sp)
    margin[axis] = 0.0
    away = np.abs(box_chords(s, d, lo + margin, hi - margin) - chord) < 1e-9
    sel = away & (chord > 10.0)
    # The chord's middle in voxel indices: t of entry along each ray from the slab method.
    with np.errstate(divide="ignore"):
        ta, tb = (lo - s) / d, (hi - s) / d
    t0 = np.minimum(ta, tb).max(-1)
    mid = s + d * (t0 + chord / 2)[..., None]
    index = (mid - vol.T_ct_from_voxel[:3, 3]) / np.array(sp)
    hu_mid = -790 + index @ np.array([1.0, 6.0, 20.0])
    truth = chord * (1 + hu_mid / 1000)
    rel = np.abs(got[sel] - truth[sel]) / truth[sel]
    assert sel.sum() > 500
    assert rel.mean() < 0.001 and rel.max() < 0.003


# ALONG_X with the detector's rows turned 4 degrees across the slices: a packet's rays cross
# from one row of a slice into the next.
ROLLED = make_transform(rotation_about([0.0, 0.0, 1.0], np.radians(4.0)) @ ALONG_X[:3, :3], ALONG_X[:3, 3])


@pytest.mark.parametrize("pose", [ALONG_X, ROLLED, OBLIQUE])
@pytest.mark.parametrize("shape, spacing", [((30, 34, 28), (1.5, 1.25, 2.0)),
                                            # voxels a third of a pixel at the depth: a packet's
                                            # sixteen rays span 30-50 of them, the wide window
                                            ((24, 90, 40), (0.5, 0.55, 2.0))])
def test_a_slab_copys_loads_agree_on_every_path(renderer, pose, shape, spacing):
    """A slab copy's casts by the hardware's loads (row windows where a packet's samples lie in
    one or two rows of a slice, else gathers of 32-bit pairs), by the portable 32-bit pair loads,
    by single voxels (no unaligned loads) and by the one-ray-per-work-item kernel (the GPU's)
    read the same four voxels per sample: the same integrals, the three packet paths to the bit.
    (The oblique view's rays cross the slabs at a slant: every sample's neighbours differ.)"""
    import pyopencl as cl

    rng = np.random.default_rng(5)
    hu = rng.integers(-900, 2000, size=shape).astype(np.int16)
    prepared = renderer.prepare(Volume(hu=hu, T_ct_from_voxel=np.diag([*spacing, 1.0]), source="noise"))
    cache = SlabCache(renderer.dev, 1)
    caster = renderer.caster
    fast = caster._joseph

    def cast() -> np.ndarray:
        buf, _ = slab_cast(caster, cache, prepared, pose, 1, None, np.inf)(prepared, pose, 1, None, None, False, False)
        return renderer.dev.download(buf, np.empty((128, 128, 4), np.float32))
    try:
        hardware = cast()
        results = []
        for options in (["-DUNALIGNED_PAIRS", "-DNO_HW_GATHER"], []):
            caster._joseph = cl.Kernel(cl.Program(renderer.dev.ctx, renderer.dev.source).build(options=options),
                                       "joseph_packet")
            results.append(cast())
        caster._joseph, caster.packet = renderer.dev.kernel("joseph_materials"), False
        per_ray = cast()
    finally:
        caster._joseph, caster.packet = fast, True
    assert hardware.max() > 20
    for other in results:
        np.testing.assert_array_equal(hardware, other)
    np.testing.assert_allclose(per_ray, hardware, rtol=1e-5, atol=1e-3)


# -- one-slice slabs: a phase laid out for rays along x ---------------------------------------
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_one_slice_copy_is_the_phase_itself_laid_out_for_its_axis(renderer, axis):
    rng = np.random.default_rng(10 + axis)
    hu = rng.integers(-1000, 3000, size=(13, 11, 45)).astype(np.int16)
    prepared = renderer.prepare(Volume(hu=hu, T_ct_from_voxel=np.diag([0.9, 1.1, 2.0, 1.0]), source="noise"))
    copy = SlabCache(renderer.dev, 1, thickness=1).get(prepared, axis)
    assert copy.shape_xyz == prepared.shape_xyz and copy.box == prepared.box and copy.slab_axis == axis
    np.testing.assert_array_equal(copy.T_index_from_ct, prepared.T_index_from_ct)
    np.testing.assert_array_equal(padded_hu(renderer, copy), padded_hu(renderer, prepared))


def every_rays_dominant_axis(renderer, prepared, pose) -> np.ndarray:
    """(rows, cols) index axis each pixel's ray steps along most, from every pixel's direction."""
    from appliance.geometry import invert
    from appliance.xray.pixel_geometry import ray_directions

    n = ray_directions(renderer.fluoroscope, 1, False).astype(np.float64)
    A = (prepared.T_index_from_ct @ invert(pose))[:3, :3]
    d = n[..., 0, None] * A[:, 0] + n[..., 1, None] * A[:, 1] + A[:, 2]
    return np.argmax(np.abs(d), axis=-1)


# A lateral view rotated 40 degrees toward posterior-anterior: some rays along x, some along y.
MIXED = make_transform(ALONG_X[:3, :3] @ rotation_about([0.0, 0.0, 1.0], np.radians(40.0)), ALONG_X[:3, 3])


@pytest.mark.parametrize("pose, expected", [(ALONG_X, 0), (ROLLED, 0), (ALONG_Y, 1), (AXIAL, 2), (MIXED, None)])
def test_the_fields_dominant_axis_is_every_pixels_own(renderer, pose, expected):
    vol, _, _ = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 5), (52, 47, 40))
    prepared = renderer.prepare(vol)
    axes = every_rays_dominant_axis(renderer, prepared, pose)
    got = renderer.caster.dominant_axis_of_field(prepared, pose, 1, False)
    assert got == expected
    if expected is None:
        assert len(np.unique(axes)) > 1
    else:
        assert np.all(axes == expected)


def cast_lines(renderer, prepared, pose, blend=None) -> np.ndarray:
    with renderer._lock:
        buf, _ = renderer.caster.cast(prepared, pose, 1, None, blend, False, False)
        return renderer.dev.download(buf, np.empty((128, 128, 4), np.float32))


@pytest.mark.parametrize("pose", [ALONG_X, ROLLED])
def test_a_lateral_view_is_cast_through_the_copy_with_the_plain_layouts_integrals(pose):
    """Water (HU 0) in a box, a view whose every ray runs along x: the cast goes through the phase
    laid out for such rays, its integrals are the plain layout's to float rounding and the
    closed-form chords' within the display path's 0.6 % bar."""
    renderer = Renderer(flat_profile(128), Materials(), device="cpu")
    vol, lo, hi = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 5), (52, 47, 40))
    prepared = renderer.prepare(vol)
    layouts = renderer.caster.layouts
    got = cast_lines(renderer, prepared, pose)
    assert layouts is not None and layouts.made == 1
    renderer.caster.layouts = None
    try:
        plain = cast_lines(renderer, prepared, pose)
    finally:
        renderer.caster.layouts = layouts
    np.testing.assert_allclose(got, plain, rtol=1e-5, atol=1e-4)
    # Water: soft tissue but for the faces' samples mixed with air, no bone, no contrast.
    assert got[..., 2:].max() == 0.0 and got[..., 1].sum() > 0.98 * got.sum()
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), pose, 128, 128)
    rel, n = chord_error(renderer, got, box_chords(s, d, lo, hi), 10.0)
    assert n > 1000 and rel.mean() < 0.006


def test_other_views_read_the_plain_layout_and_the_copies_follow_the_blended_pair(renderer):
    """A posterior-anterior view and one whose rays differ in their dominant axis make no copy; a
    lateral frame between two phases makes both phases' copies, the pair moving on one phase
    makes one more, and only the last pair is kept (LAYOUT_PHASES)."""
    from appliance.xray.slabs import LAYOUT_PHASES

    fresh = Renderer(flat_profile(128), Materials(), device="cpu")
    rng = np.random.default_rng(3)
    phases = [fresh.prepare(Volume(hu=rng.integers(-900, 2000, size=(30, 34, 28)).astype(np.int16),
                                   T_ct_from_voxel=np.diag([1.5, 1.25, 2.0, 1.0]), source="noise")) for _ in range(3)]
    layouts = fresh.caster.layouts
    for pose in (ALONG_Y, MIXED, AXIAL):
        cast_lines(fresh, phases[0], pose, (phases[1], 0.3))
    assert layouts.made == 0
    first = cast_lines(fresh, phases[0], ALONG_X, (phases[1], 0.3))
    assert layouts.made == 2
    cast_lines(fresh, phases[1], ALONG_X, (phases[2], 0.6))
    assert layouts.made == 3 and LAYOUT_PHASES == 2 and layouts.nbytes == 2 * phases[0].nbytes
    fresh.caster.layouts = None
    np.testing.assert_allclose(first, cast_lines(fresh, phases[0], ALONG_X, (phases[1], 0.3)), rtol=1e-5, atol=1e-3)
    # The one-ray-per-work-item kernel (a GPU's) keeps to the plain layout.
    assert Renderer(flat_profile(128), Materials(), device="cpu", packet=False).caster.layouts is None


def test_a_phase_let_go_frees_its_layout_copy_at_the_next_cast_whatever_its_view():
    import gc

    fresh = Renderer(flat_profile(128), Materials(), device="cpu")
    vol, _, _ = box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 5), (52, 47, 40))
    gone, kept = fresh.prepare(vol), fresh.prepare(vol)
    cast_lines(fresh, gone, ALONG_X)
    layouts = fresh.caster.layouts
    assert layouts.nbytes == gone.nbytes
    del gone
    gc.collect()
    cast_lines(fresh, kept, ALONG_Y)             # a view that makes no copy
    assert layouts.nbytes == 0 and layouts.made == 1
