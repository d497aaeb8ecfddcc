"""The projection cache: phases blended in projection space against closed-form chords, casts
counted at an unchanged and a moved pose, contrast concentration against xraylib."""

import cv2
import numpy as np
import pytest
import xraylib

from appliance.config.case import Contrast, Materials
from appliance.geometry import make_transform, rotation_about
from appliance.xray.bench import flat_profile
from appliance.xray.projection_cache import ProjectionCache
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

SHAPE, SPACING = (40, 48, 48), (1.5, 1.25, 2.0)
POSE = make_transform(rotation_about([1.0, 0.4, -0.3], np.radians(25)), [-5.0, 6.0, 700.0])


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(96), Materials(contrast_min_hu=2500), Contrast(concentration_mg_per_ml=150),
                    device="cpu")


def two_phases(hu=0):
    """The same box at two places on one grid: a 'breath' moves its faces by 1-4 voxels (within
    the 16-voxel blocks the renderer crops by, so both phases keep one device grid)."""
    a, lo_a, hi_a = box_volume(SHAPE, SPACING, (8, 10, 6), (28, 36, 28), hu=hu)
    b, lo_b, hi_b = box_volume(SHAPE, SPACING, (12, 10, 8), (31, 35, 31), hu=hu)
    return (a, lo_a, hi_a), (b, lo_b, hi_b)


def chords(renderer, lo, hi, T=POSE):
    rows, cols = renderer.shape
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), T, rows, cols)
    return box_chords(s, d, lo, hi)


def test_blend_in_projection_space_is_the_blend_of_the_phases_chords(renderer):
    (a, lo_a, hi_a), (b, lo_b, hi_b) = two_phases()
    pa, pb = renderer.prepare(a), renderer.prepare(b)
    cache = ProjectionCache(renderer)
    ca, cb = chords(renderer, lo_a, hi_a), chords(renderer, lo_b, hi_b)
    for w in (0.3, 0.0, 0.75):
        soft = cache.material_integrals(pa, POSE, View(), blend=(pb, w))[..., 1]   # HU 0: soft tissue at 1 g/cm^3
        truth = (1 - w) * ca + w * cb
        sel = truth > 10.0
        assert sel.sum() > 300
        rel = np.abs(soft[sel] - truth[sel]) / truth[sel]
        # Joseph's bilinear samples smear the faces of this small box by a voxel: 1 % on average
        # (a blend of HU instead would classify the half-overlap as air and miss by far more).
        assert rel.mean() < 0.01, w
    assert (cache.counts.casts, cache.counts.paired) == (2, 1)     # both phases cast once, in one pass


def test_two_phase_pass_gives_each_phase_its_own_cast(renderer):
    (a, *_), (b, *_) = two_phases()
    pa, pb = renderer.prepare(a), renderer.prepare(b)
    together = ProjectionCache(renderer)
    assert pa.same_grid(pb)
    together.material_integrals(pa, POSE, View(), blend=(pb, 0.5))
    assert (together.counts.casts, together.counts.paired) == (2, 1)
    for phase in (pa, pb):
        alone = renderer.material_integrals(phase, POSE, View())
        cached = together.material_integrals(phase, POSE, View())
        np.testing.assert_allclose(cached, alone, rtol=1e-6, atol=1e-6)
    assert together.counts.casts == 2       # both were still cached


def test_the_caches_of_a_renderers_matrices_share_one_build_of_the_paired_kernel(renderer):
    """Each matrix's cache casts its pairs through a kernel of its own (arguments set per
    thread) from the device's one SPLIT build of drr.cl, made once, not once per cache; the
    second matrix's pass is still each phase's own cast."""
    (a, *_), (b, *_) = two_phases()
    pa, pb = renderer.prepare(a), renderer.prepare(b)
    other = renderer.at_matrix(64, 64)
    caches = [ProjectionCache(renderer), ProjectionCache(other)]
    for cache in caches:
        cache.material_integrals(pa, POSE, View(), blend=(pb, 0.5))
        assert cache.counts.paired == 1
    first, second = (c._split for c in caches)
    assert first is not second and first.program.int_ptr == second.program.int_ptr
    np.testing.assert_allclose(caches[1].material_integrals(pb, POSE, View()),
                               other.material_integrals(pb, POSE, View()), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="no build 'SPLITS'"):
        renderer.dev.kernel("joseph_packet", "SPLITS")


def test_phases_on_different_grids_blend_in_projection_space(renderer):
    # Content boxes in different 16-voxel blocks: the phases are cropped to different grids,
    # which a blend of HU cannot mix, but their projections can.
    a, lo_a, hi_a = box_volume(SHAPE, SPACING, (8, 10, 6), (28, 36, 28))
    b, lo_b, hi_b = box_volume(SHAPE, SPACING, (20, 10, 6), (40, 36, 28))
    pa, pb = renderer.prepare(a), renderer.prepare(b)
    assert not pa.same_grid(pb)
    cache = ProjectionCache(renderer)
    soft = cache.material_integrals(pa, POSE, View(), blend=(pb, 0.5))[..., 1]
    truth = 0.5 * chords(renderer, lo_a, hi_a) + 0.5 * chords(renderer, lo_b, hi_b)
    sel = truth > 10.0
    assert np.mean(np.abs(soft[sel] - truth[sel]) / truth[sel]) < 0.01
    assert (cache.counts.casts, cache.counts.paired) == (2, 0)


def test_unchanged_pose_casts_nothing_and_a_moved_one_recasts(renderer):
    (a, *_), (b, *_) = two_phases()
    pa, pb = renderer.prepare(a), renderer.prepare(b)
    cache = ProjectionCache(renderer, pose_tolerance_px=0.25)
    view = View(seed=1)
    for i in range(10):                       # breathing at a still C-arm
        cache.render(pa, POSE, view, blend=(pb, i / 10))
    # w = 0 needs phase a alone, w = 0.1 adds b, and the eight frames after reuse both.
    assert (cache.counts.casts, cache.counts.hits) == (2, 1 + 8 * 2)
    # 1 um sideways at 700 mm moves the image by about 0.0001 px: still the same pose.
    cache.render(pa, make_transform(POSE[:3, :3], POSE[:3, 3] + [0.001, 0, 0]), view, blend=(pb, 0.5))
    assert cache.counts.casts == 2
    # 5 mm sideways moves it by several pixels: both phases are cast again.
    cache.render(pa, make_transform(POSE[:3, :3], POSE[:3, 3] + [5.0, 0, 0]), view, blend=(pb, 0.5))
    assert cache.counts.casts == 4
    # Collimating changes which rays are cast.
    cache.render(pa, make_transform(POSE[:3, :3], POSE[:3, 3] + [5.0, 0, 0]),
                 View(seed=1, collimation_mm=(80.0, 60.0)), blend=(pb, 0.5))
    assert cache.counts.casts == 6


def test_contrast_concentration_changes_without_a_cast(renderer):
    """A box of iodinated contrast: transmitted intensity at the effective energy against
    exp(-L (mu/rho_water + c mu/rho_iodine)), L the box's chord and the coefficients from
    xraylib, at half and full concentration."""
    vol, lo, hi = box_volume(SHAPE, SPACING, (8, 10, 6), (30, 36, 30), hu=3000)
    p = renderer.prepare(vol)
    cache = ProjectionCache(renderer)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    L_cm = chords(renderer, lo, hi) / 10.0
    e = renderer.spectrum.effective_kev
    # Interior rays only: the focal-spot blur averages neighbours, which matters at edges.
    inner = cv2.erode((L_cm > 1.5).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert inner.sum() > 200
    for factor in (0.5, 1.0):
        image = cache.render(p, POSE, view, concentration_factor=factor).image
        mu = xraylib.CS_Total_CP("Water, Liquid", e) + factor * 0.150 * xraylib.CS_Total(53, e)
        # The path the image implies at this attenuation coefficient, against the chord: 1 %
        # of path is 2-6 % of intensity here, and half the concentration would be 40 % off.
        implied = -np.log(image[inner]) / mu
        rel = np.abs(implied - L_cm[inner]) / L_cm[inner]
        # (median: a ray that grazes a face sees interpolated HU below the contrast threshold)
        assert np.median(rel) < 0.01, factor
    assert cache.counts.casts == 1
