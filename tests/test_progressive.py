"""Progressive resolution: the moving matrix while the pose changes, the full one at rest, the
switch faded in, and both matrices against the closed-form transmission of a box."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import xraylib

from appliance.config.case import Materials
from appliance.config.rendering import Rendering
from appliance.geometry import make_transform, rotation_about
from appliance.xray.bench import flat_profile
from appliance.xray.progressive import ProgressiveRenderer
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, ellipsoid_chords, ellipsoid_volume, pixel_rays_ct

POSE = make_transform(rotation_about([0.2, 1.0, 0.1], np.radians(20)), [0.0, 0.0, 700.0])
SETTINGS = Rendering(moving_matrix_px=64, settle_s=0.1, crossfade_s=0.2)


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(128), Materials(), device="cpu")


@pytest.fixture(scope="module")
def box(renderer):
    vol, lo, hi = box_volume((40, 48, 48), (1.5, 1.25, 2.0), (8, 10, 6), (36, 38, 30))
    return renderer.prepare(vol), lo, hi


def shifted(dx_mm):
    return make_transform(POSE[:3, :3], POSE[:3, 3] + [dx_mm, 0.0, 0.0])


def test_moving_frames_use_the_moving_matrix_and_rest_refines_to_the_full_one(renderer, box):
    prepared, _, _ = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, SETTINGS, clock=clock)
    view = View(seed=3)
    for i in range(6):                         # 2 mm a frame at 25 frames/s
        clock.t += 0.04
        image = pr.render(prepared, shifted(2.0 * i), view).image
        assert image.shape == (128, 128)
        assert pr.matrix == 64 or i == 0       # the very first frame has no motion before it
    # Every moving frame is cast at its new pose, once, into the moving matrix's cache.
    assert pr.moving_casts >= 5 and pr.cache(pr.moving).counts.casts == pr.moving_casts
    assert pr.cache(pr.moving).counts.hits == 0
    matrices = []
    for _ in range(10):                        # at rest for 0.4 s
        clock.t += 0.04
        pr.render(prepared, shifted(10.0), view)
        matrices.append(pr.matrix)
    # Still the moving matrix until settle_s has passed, then the full matrix for good.
    first_full = matrices.index(128)
    assert 0.1 <= 0.04 * (first_full + 1) <= 0.1 + 0.04 + 1e-9
    assert all(m == 128 for m in matrices[first_full:])
    assert pr.refined_after_s and pr.refined_after_s[-1] <= 0.5
    # Held: the full matrix was cast once and served from the cache afterwards.
    assert pr.cache().counts.casts == 1


def test_switch_is_faded_in_over_the_crossfade(renderer, box):
    prepared, _, _ = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, SETTINGS, clock=clock)
    view = View(noise=False)
    for i in range(3):
        clock.t += 0.04
        last_moving = pr.render(prepared, shifted(2.0 * i), view).image
    while pr.matrix != 128:
        clock.t += 0.04
        last_moving = first_full = pr.render(prepared, shifted(4.0), view).image
    # The first full-matrix frame is still the last moving one; the fade then runs to the full image.
    moving_only = cv2.resize(pr.cache(pr.moving).render(prepared, shifted(4.0), view).image, (128, 128),
                             interpolation=cv2.INTER_LINEAR)
    np.testing.assert_allclose(first_full, moving_only, atol=1e-6)
    full = pr.cache().render(prepared, shifted(4.0), view).image
    clock.t += 0.1
    half = pr.render(prepared, shifted(4.0), view).image
    np.testing.assert_allclose(half, 0.5 * moving_only + 0.5 * full, atol=0.02)
    clock.t += 0.2
    np.testing.assert_allclose(pr.render(prepared, shifted(4.0), view).image, full, atol=1e-6)
    del last_moving


def walk(pr, clock, prepared, poses, view, wait=False):
    """Render `poses` 0.04 s apart (25 frames/s); with `wait`, the cast beside the live frames a
    frame began ends before the next. The matrix of each frame."""
    matrices = []
    for T in poses:
        clock.t += 0.04
        pr.render(prepared, T, view)
        if wait:
            pr.wait_refined(30.0)
        matrices.append(pr.matrix)
    return matrices


def box_truth(renderer, box):
    """The box's chords at POSE (cm) for the full matrix's 128 x 128 pixels, the pixels well inside
    it (over 2 cm of tissue, 4 px from its edge) and mu of soft tissue from xraylib (1/cm)."""
    prepared, lo, hi = box
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), POSE, 128, 128)
    L_cm = box_chords(s, d, lo, hi) / 10.0
    inner = cv2.erode((L_cm > 2.0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert inner.sum() > 200
    return prepared, L_cm, inner, xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)


def test_both_matrices_show_the_closed_form_transmission(renderer, box):
    """Same brightness at either matrix: the transmission through the box's middle against
    exp(-mu L) with the chord L and mu of soft tissue from xraylib at the effective energy."""
    prepared, L_cm, inner, mu = box_truth(renderer, box)
    clock = Clock()
    pr = ProgressiveRenderer(renderer, SETTINGS, clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    clock.t += 0.04
    moving = pr.render(prepared, POSE, view).image
    assert pr.matrix == 64
    clock.t += 1.0
    pr.render(prepared, POSE, view)
    clock.t += 1.0
    full = pr.render(prepared, POSE, view).image
    assert pr.matrix == 128
    for image in (moving, full):
        implied = -np.log(image[inner]) / mu
        assert np.median(np.abs(implied - L_cm[inner]) / L_cm[inner]) < 0.01


def test_a_pose_come_to_rest_is_shown_from_its_last_moving_cast(renderer, box):
    """The frames of a pose that has just stopped (before settle_s) show the moving matrix from
    the integrals of the last moving frame's cast, kept in the moving matrix's cache: that pose
    is not cast again (the device is left to the full matrix's cast), and the frame is still
    the closed-form transmission exp(-mu L) of the box at that pose."""
    prepared, L_cm, inner, mu = box_truth(renderer, box)
    clock = Clock()
    pr = ProgressiveRenderer(renderer, SETTINGS, clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for dx in (-4.0, -2.0, 0.0):                # 2 mm a frame, stopping at POSE
        clock.t += 0.04
        pr.render(prepared, shifted(dx), view)
    counts = pr.cache(pr.moving).counts
    casts, hits = counts.casts, counts.hits
    clock.t += 0.04                             # at rest for less than settle_s (0.1 s)
    held = pr.render(prepared, POSE, view).image
    assert pr.matrix == 64
    assert (counts.casts, counts.hits) == (casts, hits + 1)
    implied = -np.log(held[inner]) / mu
    assert np.median(np.abs(implied - L_cm[inner]) / L_cm[inner]) < 0.01


def test_recursive_filter_carries_over_the_switch(renderer, box):
    """With the live recursive filter (weight w), the first full-matrix frame's detector signal
    is w x (the moving matrix's settled signal, resampled) + (1 - w) x the full matrix's own."""
    prepared, _, _ = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, crossfade_s=0), clock=clock)
    live, still = View(noise=False, temporal="live"), View(noise=False, temporal="settled")
    w = renderer.fluoroscope.image.recursive_weight
    assert 0 < w < 1
    clock.t += 0.04
    moving = pr.render(prepared, POSE, live)
    assert pr.matrix == 64
    moving_signal = pr.moving.lag._state.copy()       # one frame: the filter holds that frame
    clock.t += 0.2
    first_full = pr.render(prepared, POSE, live)
    assert pr.matrix == 128
    own = pr.full.render(prepared, POSE, still).signal   # the full matrix's unfiltered signal
    expected = w * cv2.resize(moving_signal, (128, 128), interpolation=cv2.INTER_LINEAR) + (1 - w) * own
    beam = own > 0
    np.testing.assert_allclose(first_full.signal[beam], expected[beam], rtol=1e-4, atol=1e-6)
    assert moving.image.shape == first_full.image.shape == (128, 128)



def test_a_moving_frame_at_a_smaller_matrix_puts_a_known_point_on_its_display_pixel(renderer):
    """A dense sphere off the principal ray, cast at the controller's second moving matrix (64
    of 128, after two slow frames) and scaled up: the centroid of its shadow on the full matrix
    is where the closed-form chords through the full matrix's pixel rays put it, within 0.15 px.
    Pixel centres misplaced by the scaling (cx' = cx * 64/128) would put it 0.5 px off."""
    centre, radius = (12.0, -8.0, 0.0), (13.0, 13.0, 13.0)
    prepared = renderer.prepare(ellipsoid_volume((40, 48, 48), (1.5, 1.25, 2.0), centre, radius, hu=1000))
    air = renderer.prepare(ellipsoid_volume((40, 48, 48), (1.5, 1.25, 2.0), centre, radius, hu=-1000))
    clock = Clock()
    ladder = Rendering(moving_matrix_px=96, moving_matrix_min_px=64, moving_matrix_step_px=32,
                       matrix_window_frames=2, settle_s=0.1)
    pr = ProgressiveRenderer(renderer, ladder, clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for dx in (3.0, 6.0):                      # two moving frames far over the 40 ms budget
        clock.t += 0.04
        pr.render(prepared, shifted(dx), view)
        assert pr.matrix == 96
        pr.frame_shown(1.0)
    assert pr.control.steps == [(96, 64)]
    clock.t += 0.04
    shadow = pr.render(prepared, POSE, view).image
    open_beam = pr.render(air, POSE, view).image
    assert pr.matrix == 64 and shadow.shape == (128, 128)
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), POSE, 128, 128)
    chords = ellipsoid_chords(s, d, centre, radius)
    rows, cols = np.mgrid[0:128, 0:128]
    expected = np.array([(chords * cols).sum(), (chords * rows).sum()]) / chords.sum()
    assert np.hypot(*(expected - 63.5)) > 7    # off the centre, where a scaling error shows
    weight = np.clip(-np.log(shadow / open_beam), 0.0, None)
    near = np.hypot(cols - expected[0], rows - expected[1]) < 20
    got = np.array([(weight * cols)[near].sum(), (weight * rows)[near].sum()]) / weight[near].sum()
    np.testing.assert_allclose(got, expected, atol=0.15)


def test_a_scaled_up_moving_frame_has_the_full_matrix_s_field_edge():
    """The intensifier's circle cut at 64 and scaled up steps in 2-pixel stairs; the moving frame
    shown has the full matrix's own edge instead: black wherever that edge is, the image wherever
    it is fully open, and around the circle nearer the full matrix's frame than a plain scaling."""
    from appliance.config.fluoroscope import FluoroscopeProfile
    from appliance.config.loading import load_profile
    from appliance.xray.renderer import at_resolution

    configs = Path(__file__).resolve().parents[1] / "configs"
    ii = load_profile(configs / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    full = Renderer(at_resolution(ii, 128, 128), Materials(), device="cpu")
    vol, _, _ = box_volume((40, 48, 48), (4.0, 4.0, 4.0), (0, 0, 0), (39, 47, 39))      # a slab of water filling the field
    prepared = full.prepare(vol)
    clock = Clock()
    pr = ProgressiveRenderer(full, Rendering(moving_matrix_px=64, settle_s=0.1), clock=clock)
    view = View(noise=False)
    clock.t += 0.04
    image = pr.render(prepared, make_transform(np.eye(3), [0.0, 0.0, 700.0]), view).image
    assert pr.matrix == 64
    edge = pr.full.display_edge(view)
    coarse = cv2.resize(pr.moving.display_edge(view), (128, 128), interpolation=cv2.INTER_LINEAR)
    beyond = edge < 0.01
    assert ((coarse > 0.15) & beyond).sum() > 20       # where the coarse circle spills past the fine one
    assert np.all(image[beyond] <= 0.01)
    inside = edge > 0.999
    assert image[inside].min() > 0.05
    # Around the circle the shown frame is nearer the full matrix's own than the plain scaled-up
    # coarse frame is: the stairs are gone (mean absolute grey over the band the two edges differ in).
    T = make_transform(np.eye(3), [0.0, 0.0, 700.0])
    own = pr.full.render(prepared, T, view).image
    plain = cv2.resize(pr.moving.render(prepared, T, view).image, (128, 128), interpolation=cv2.INTER_LINEAR)
    band = np.abs(edge - coarse) > 0.05
    assert band.sum() > 100
    shown_error, plain_error = np.abs(image - own)[band].mean(), np.abs(plain - own)[band].mean()
    assert shown_error < 0.5 * plain_error, (shown_error, plain_error)


def _implied_chord_error(image, L_cm, inner, mu):
    """Median relative error of the chord -ln(T)/mu implied by an intensity image against the box's."""
    return float(np.median(np.abs(-np.log(image[inner]) / mu - L_cm[inner]) / L_cm[inner]))


def test_at_rest_the_full_matrix_is_cast_beside_the_live_frames_and_then_shown(renderer, box):
    """With refine_bands the frames at rest keep the moving matrix while the full one is cast on
    its own thread; the first frame after that cast shows the full matrix without casting it
    again, and it is the closed-form transmission exp(-mu L) of the box (xraylib's soft tissue)."""
    prepared, lo, hi = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=4), clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for i in range(3):                          # moving
        clock.t += 0.04
        pr.render(prepared, shifted(2.0 * i), view)
    assert pr.refine is None
    cast_moving = pr.cache(pr.moving).counts.casts
    for _ in range(3):                          # at rest past settle_s: the cast begins, the moving matrix stays
        clock.t += 0.04
        pr.render(prepared, shifted(4.0), view)
    assert pr.refine is not None and pr.matrix == 64
    assert pr.wait_refined(30.0)
    assert pr.cache().counts.casts == 1 and pr.refine_fault is None
    clock.t += 0.04
    full = pr.render(prepared, shifted(4.0), view).image
    assert pr.matrix == 128 and pr.cache().counts.casts == 1      # served from what the thread cast
    assert pr.refined_after_s
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), shifted(4.0), 128, 128)
    L_cm = box_chords(s, d, lo, hi) / 10.0
    inner = cv2.erode((L_cm > 2.0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert inner.sum() > 200
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    assert _implied_chord_error(full, L_cm, inner, mu) < 0.01
    # The moving matrix at rest was served from what the last moving frame, at this pose, cast.
    assert pr.cache(pr.moving).counts.casts == cast_moving


def test_a_pose_that_moves_on_cancels_the_cast_and_never_shows_the_old_pose(renderer, box):
    """The C-arm moves on while the full matrix is cast: that cast is told to stop, and at the next
    rest the full matrix shown is the new pose's (closed-form chords at the new pose, not the old)."""
    prepared, lo, hi = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=64), clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    walk(pr, clock, prepared, [shifted(0.0)] * 4, view)
    first = pr.refine
    assert first is not None
    clock.t += 0.04
    pr.render(prepared, shifted(12.0), view)    # moved 12 mm: many pixels
    assert first.cancel and pr.matrix == 64
    assert pr.wait_refined(30.0)                # it ends at its next band: 64 bands take far longer
    assert pr.cache().counts.casts == 0         # nothing of the left pose is kept
    for _ in range(4):                          # at rest at the new pose: its own cast
        clock.t += 0.04
        pr.render(prepared, shifted(12.0), view)
    assert pr.refine is not first and pr.wait_refined(30.0)
    clock.t += 0.04
    full = pr.render(prepared, shifted(12.0), view).image
    assert pr.matrix == 128
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    errors = []
    for dx in (12.0, 0.0):
        s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), shifted(dx), 128, 128)
        L_cm = box_chords(s, d, lo, hi) / 10.0
        inner = cv2.erode((L_cm > 2.0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
        errors.append(_implied_chord_error(full, L_cm, inner, mu))
    assert errors[0] < 0.01 < errors[1], errors


def test_jitter_about_the_resting_pose_does_not_cancel_the_cast(renderer, box):
    """Two frames 0.4 px apart (the pose "moved") but each within the 0.25 px tolerance of the
    pose the cast began at: that cast goes on and is what the full matrix shows."""
    from appliance.xray.projection_cache import box_corners_ct, detector_shift_px

    prepared, _, _ = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=64), clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    px_per_mm = detector_shift_px(zoomed_K(renderer.fluoroscope, 1), box_corners_ct(prepared), shifted(0.0), shifted(1.0))
    jitter_mm = 0.2 / px_per_mm
    for _ in range(4):
        clock.t += 0.04
        pr.render(prepared, shifted(0.0), view)
    first = pr.refine
    assert first is not None
    for dx in (jitter_mm, -jitter_mm):
        clock.t += 0.04
        pr.render(prepared, shifted(dx), view)
    assert not first.cancel
    assert pr.wait_refined(30.0) and pr.refine is first and pr.cache().counts.casts == 1


def _chords(renderer, lo, hi, zoom: int, T=POSE):
    """The box's chord (cm) through each detector pixel at `zoom`, and the pixels well inside it."""
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, zoom), T, 128, 128)
    L_cm = box_chords(s, d, lo, hi) / 10.0
    return L_cm, cv2.erode((L_cm > 2.0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)


def test_a_new_zoom_at_the_resting_pose_cancels_the_cast_and_shows_its_own_field(renderer, box):
    """The zoom changes while the full matrix is cast, the C-arm still: that cast is told to stop
    and keeps nothing, and the full matrix then shown is zoom 2's: the box's closed-form chords
    through zoom 2's rays, and as many pixels behind more than 1 cm of it as zoom 2's rays give
    (zoom 1's give about half as many). With no cast begun, there is none to wait for."""
    prepared, lo, hi = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=64), clock=clock)
    assert pr.wait_refined(0.0)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for _ in range(4):
        clock.t += 0.04
        pr.render(prepared, POSE, view)
    first = pr.refine
    assert first is not None
    zoomed = View(zoom=2, quantity="intensity", noise=False, polychromatic=False)
    clock.t += 0.04
    pr.render(prepared, POSE, zoomed)
    assert first.cancel and pr.matrix == 64
    assert pr.wait_refined(30.0) and pr.cache().counts.casts == 0
    for _ in range(2):                          # zoom 2's own cast begins, and is waited for
        clock.t += 0.04
        pr.render(prepared, POSE, zoomed)
    assert pr.refine is not first and pr.wait_refined(30.0)
    clock.t += 0.04
    full = pr.render(prepared, POSE, zoomed).image
    assert pr.matrix == 128
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    assert _implied_chord_error(full, *_chords(renderer, lo, hi, 2), mu) < 0.01
    behind = {zoom: int((_chords(renderer, lo, hi, zoom)[0] > 1.0).sum()) for zoom in (1, 2)}
    shown = int(((full > 0) & (full < np.exp(-mu * 1.0))).sum())
    assert abs(shown - behind[2]) < 0.03 * behind[2] and behind[2] > 1.5 * behind[1], (shown, behind)


def test_a_blended_rest_has_both_phases_cast_beside_the_live_frames(renderer, box):
    """Between two phases (a box and a longer one on the same grid, half way) the cast beside the
    live frames casts both, so the full-matrix frame casts nothing within itself, and it is the
    projection-space blend: -ln T / mu = half of each box's closed-form chord."""
    prepared, lo, hi = box
    longer, lo_b, hi_b = box_volume((40, 48, 48), (1.5, 1.25, 2.0), (8, 10, 6), (36, 38, 38))
    other = renderer.prepare(longer)
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=4), clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for _ in range(4):
        clock.t += 0.04
        pr.render(prepared, POSE, view, blend=(other, 0.5))
    assert pr.refine is not None and pr.wait_refined(30.0)
    assert pr.cache().counts.casts == 2
    clock.t += 0.04
    full = pr.render(prepared, POSE, view, blend=(other, 0.5)).image
    assert pr.matrix == 128 and pr.cache().counts.casts == 2
    (L_a, inner), (L_b, _) = _chords(renderer, lo, hi, 1), _chords(renderer, lo_b, hi_b, 1)
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    assert _implied_chord_error(full, 0.5 * (L_a + L_b), inner, mu) < 0.01
    assert np.median(L_b[inner] - L_a[inner]) > 0.5          # the blend differs from either phase


def test_a_breathing_patient_at_rest_shows_the_moving_matrix_without_casting_it_again(renderer):
    """Moving between two phases (a box and a longer one on the same grid, breathing: the weight
    changes every frame), each moving frame keeps both phases' integrals in the moving matrix's
    cache, so the frames at rest that show the moving matrix while the full one is cast beside
    them cast nothing within themselves. Moving and resting frames are the projection-space
    blend of the boxes' closed-form chords, (1 - w) L_a + w L_b, at their weight. The boxes end
    within one crop block, so the two phases share a grid as a 4D CT's do."""
    shorter, lo, hi = box_volume((40, 48, 48), (1.5, 1.25, 2.0), (8, 10, 6), (36, 38, 33))
    longer, lo_b, hi_b = box_volume((40, 48, 48), (1.5, 1.25, 2.0), (8, 10, 6), (36, 38, 38))
    prepared, other = renderer.prepare(shorter), renderer.prepare(longer)
    assert prepared.same_grid(other)
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=64), clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    L_b, _ = _chords(renderer, lo_b, hi_b, 1, shifted(6.0))
    L_a, inner = _chords(renderer, lo, hi, 1, shifted(6.0))
    for i in range(4):                          # moving, breathing
        clock.t += 0.04
        w = 0.2 + 0.1 * i
        image = pr.render(prepared, shifted(2.0 * i), view, blend=(other, w)).image
    assert pr.matrix == 64 and pr.moving_casts == 4
    assert _implied_chord_error(image, (1 - w) * L_a + w * L_b, inner, mu) < 0.01
    casts = pr.cache(pr.moving).counts.casts
    assert casts == 8                           # both phases at each of the four poses
    for k in range(3):                          # at rest, still breathing: the full matrix is cast beside
        clock.t += 0.04
        w = 0.6 + 0.1 * k
        image = pr.render(prepared, shifted(6.0), view, blend=(other, w)).image
        if pr.matrix == 64:
            assert _implied_chord_error(image, (1 - w) * L_a + w * L_b, inner, mu) < 0.01
    assert pr.refine is not None
    assert pr.cache(pr.moving).counts.casts == casts        # nothing cast again at the moving matrix
    assert pr.wait_refined(30.0) and pr.refine_fault is None


def test_a_held_view_casts_the_upcoming_phase_beside_the_live_frames_before_breathing_brings_it(renderer):
    """At rest at the full matrix between two phases, the phase the timeline says comes next is
    cast beside the live frames; the frame that then blends it casts nothing within itself and is
    the projection-space blend of the closed-form chords. While the C-arm moves nothing is
    fetched ahead. The three boxes end within one crop block: one grid, as a 4D CT's phases."""
    phases, chords = [], []
    for top in (33, 35, 38):
        vol, lo, hi = box_volume((40, 48, 48), (1.5, 1.25, 2.0), (8, 10, 6), (36, 38, top))
        phases.append(renderer.prepare(vol))
        chords.append(_chords(renderer, lo, hi, 1, shifted(6.0)))
    a, b, c = phases
    assert a.same_grid(b) and b.same_grid(c)
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=4), clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for i in range(4):                          # moving: the look ahead is not acted on
        clock.t += 0.04
        pr.render(a, shifted(2.0 * i), view, blend=(b, 0.3), upcoming=(c,))
    assert pr.prefetched_at == []
    while pr.matrix != 128:                     # the rest's cast beside the live frames, then the full matrix
        clock.t += 0.04
        pr.wait_refined(30.0)
        pr.render(a, shifted(6.0), view, blend=(b, 0.5), upcoming=(c,))
        assert clock.t < 103.0
    assert len(pr.prefetched_at) == 1 and pr.wait_refined(30.0) and pr.refine_fault is None
    cache = pr.cache()
    assert cache.holds([a, b, c])
    casts = cache.counts.casts
    clock.t += 0.04
    image = pr.render(b, shifted(6.0), view, blend=(c, 0.5)).image
    assert pr.matrix == 128 and cache.counts.casts == casts        # nothing cast within the frame
    (L_b, inner), (L_c, _) = chords[1], chords[2]
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    assert _implied_chord_error(image, 0.5 * (L_b + L_c), inner, mu) < 0.01
    assert np.median(L_c[inner] - L_b[inner]) > 0.4
    clock.t += 0.04
    pr.render(b, shifted(6.0), view, blend=(c, 0.6), upcoming=(c,))
    assert len(pr.prefetched_at) == 1           # held already: nothing more to cast
    assert pr.held_casts == []                  # no held frame cast a phase itself
    unannounced = renderer.prepare(box_volume((40, 48, 48), (1.5, 1.25, 2.0), (8, 10, 6), (36, 38, 36))[0])
    clock.t += 0.04
    pr.render(c, shifted(6.0), view, blend=(unannounced, 0.5))
    assert [t for t, _ in pr.held_casts] == [clock.t]   # a phase nobody announced is cast within its frame


def test_after_a_fault_of_the_cast_beside_the_live_frames_rest_casts_the_full_matrix_within_the_frame(renderer, box):
    """The thread's cast fails (an OpenCL error, raised where the cast would run): the fault is
    kept, and the next frames at rest cast the full matrix themselves rather than start another
    thread that would fail again and hold the moving matrix for good; that frame is the closed form."""
    prepared, lo, hi = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=4), clock=clock)

    def out_of_resources(*args, **kwargs):
        raise RuntimeError("clEnqueueNDRangeKernel failed: OUT_OF_RESOURCES")
    pr.cache().fill = out_of_resources
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for _ in range(4):
        clock.t += 0.04
        pr.render(prepared, POSE, view)
    assert pr.refine is not None and pr.wait_refined(30.0)
    assert "OUT_OF_RESOURCES" in pr.refine_fault
    failed = pr.refine
    clock.t += 0.04
    full = pr.render(prepared, POSE, view).image
    assert pr.matrix == 128 and pr.refine is failed
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    assert _implied_chord_error(full, *_chords(renderer, lo, hi, 1), mu) < 0.01


HOLD = Rendering(moving_matrix_px=64, settle_s=0.1, rest_hold_px=1.0)       # cache tolerance 0.25 px


def _mm_for_px(renderer, prepared, px):
    """The shift along x (mm) that moves the box's farthest corner by `px` on the full matrix."""
    from appliance.xray.projection_cache import box_corners_ct, detector_shift_px

    per_mm = detector_shift_px(zoomed_K(renderer.fluoroscope, 1), box_corners_ct(prepared), POSE, shifted(1.0))
    return px / per_mm


def _stop_then_creep(pr, prepared, view, clock, creep_mm):
    """Two moving frames, 0.3 s at POSE, then the pose creeping on by `creep_mm` a frame:
    the matrix of each creeping frame and the full matrix's casts after each."""
    walk(pr, clock, prepared, [shifted(-4.0), shifted(-2.0)] + [POSE] * 8, view)
    assert pr.matrix == 128
    seen = []
    for i in range(1, 4):
        clock.t += 0.04
        image = pr.render(prepared, shifted(i * creep_mm), view).image
        seen.append((pr.matrix, pr.cache().counts.casts, image))
    return seen


def test_a_held_view_is_held_through_the_creep_after_a_stop(renderer, box):
    """A pose filter's output creeps on after the phantom stops, each step beyond the projection
    cache's tolerance (0.3 px a frame here against 0.25). With the hold (1 px) the view stays at
    the full matrix, cast once, and shows the pose it rested at: the closed-form transmission of
    the box there. Without the hold the same creep drops the view to the moving matrix or casts
    it again, which is what the hold is for."""
    prepared, L_cm, inner, mu = box_truth(renderer, box)
    step = _mm_for_px(renderer, prepared, 0.3)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    clock = Clock()
    held = _stop_then_creep(ProgressiveRenderer(renderer, HOLD, clock=clock), prepared, view, clock, step)
    assert [(m, casts) for m, casts, _ in held] == [(128, 1)] * 3
    for _, _, image in held:                     # 0.9 px from POSE in the end, shown at POSE
        implied = -np.log(image[inner]) / mu
        assert np.median(np.abs(implied - L_cm[inner]) / L_cm[inner]) < 0.01
    np.testing.assert_array_equal(held[0][2], held[-1][2])
    clock = Clock()
    unheld = _stop_then_creep(ProgressiveRenderer(renderer, SETTINGS.model_copy(update=dict(crossfade_s=0.0)),
                                                  clock=clock), prepared, view, clock, step)
    assert any(m != 128 or casts > 1 for m, casts, _ in unheld)


def test_a_move_beyond_the_hold_is_motion_again(renderer, box):
    prepared, _, _ = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, HOLD, clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    walk(pr, clock, prepared, [shifted(-2.0)] + [shifted(0.0)] * 5, view)
    assert pr.matrix == 128
    casts = pr.moving_casts
    clock.t += 0.04
    pr.render(prepared, shifted(_mm_for_px(renderer, prepared, 1.2)), view)
    assert pr.matrix == 64 and pr.moving_casts == casts + 1


def test_rest_begins_while_the_pose_still_creeps_within_the_hold(renderer, box):
    """After a stop the creep (0.3 px a frame, more than the cache's tolerance) counts as rest
    under the hold: the full matrix after settle_s (0.1 s) of it. Without the hold every
    creeping frame is motion and the view stays at the moving matrix."""
    prepared, _, _ = box
    step = _mm_for_px(renderer, prepared, 0.3)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for settings, full_after in ((HOLD, 3), (SETTINGS, None)):
        clock = Clock()
        pr = ProgressiveRenderer(renderer, settings, clock=clock)
        walk(pr, clock, prepared, [shifted(-4.0), shifted(-2.0)], view)
        # 0.9 px in all: within the hold of the first. The first creeping frame starts the rest;
        # 0.1 s on (the third, at +0.08 s, is short of it), so the full matrix comes with the next
        # frame at the last creeping pose.
        matrices = walk(pr, clock, prepared, [shifted(i * step) for i in range(3)] + [shifted(2 * step)], view)
        assert matrices == ([64] * full_after + [128] if full_after else [64] * 3 + [64])


FAST_CREEP = (3.0, 1.8, 0.9, 0.5, 0.3, 0.15, 0.08)


def _creep_after_stop(renderer, prepared, view, measured_px, creep_px=FAST_CREEP):
    """Two moving frames, then the stop: the filtered pose creeping in to POSE (`creep_px` short
    of it, frame by frame: a first-order filter's lag), the measured pose given as POSE shifted
    by `measured_px[i]` (None: no measured pose). The matrix of each frame after the stop, the
    full-matrix image of the first such frame and the progressive renderer."""
    clock = Clock()
    pr = ProgressiveRenderer(renderer, HOLD, clock=clock)
    for dx in (-4.0, -2.0):
        clock.t += 0.04
        pr.render(prepared, shifted(dx), view, measured=None if measured_px is None else shifted(dx))
    matrices, first = [], None
    for i, px in enumerate(creep_px):
        clock.t += 0.04
        measured = None if measured_px is None else shifted(_mm_for_px(renderer, prepared, measured_px[i]))
        frame = pr.render(prepared, shifted(-_mm_for_px(renderer, prepared, px)), view, measured=measured)
        matrices.append(pr.matrix)
        if pr.matrix == 128 and first is None:
            first = frame.image
    return matrices, first, pr


def test_a_stop_judged_on_the_measured_pose_rests_before_the_filter_s_creep_ends(renderer, box):
    """The measured pose stands at POSE from the stop; the filtered pose creeps on, each of its
    first steps beyond the hold. Rest comes settle_s (0.1 s: the fourth frame) after the measured
    pose stood still, where the filtered pose is within the hold of it (0.5 px), and the view is
    held at the measured pose: the full matrix's image there, the box's closed-form transmission.
    On the filtered pose alone rest waits for its creep to stay within the hold for settle_s."""
    prepared, lo, hi = box
    view = View(quantity="intensity", noise=False, polychromatic=False)
    matrices, first, pr = _creep_after_stop(renderer, prepared, view, [0.0] * 7)
    assert matrices == [64] * 3 + [128] * 4
    assert pr.full.shape == (128, 128) and pr.cache().counts.casts == 1          # cast once, at the held pose
    circle = renderer._circle(None)
    assert pr.cache().adopted(POSE, 1, None, True, circle)
    assert not pr.cache().adopted(shifted(-_mm_for_px(renderer, prepared, 0.5)), 1, None, True, circle)
    np.testing.assert_array_equal(first, renderer.render(prepared, POSE, view).image)
    assert _implied_ok(renderer, first, POSE, lo, hi) < 0.01
    matrices, _, _ = _creep_after_stop(renderer, prepared, view, None)
    assert matrices == [64] * 6 + [128]


def test_a_measured_stop_waits_for_the_filtered_pose_to_come_within_the_hold(renderer, box):
    """A slower creep (0.45 px a frame): settle_s after the measured pose stood still the filtered
    pose is still 1.65 px from it, beyond the hold, where a view held at the measured pose would
    be let go at the next frame. Rest comes once the filtered pose is within the hold (0.9 px),
    and the view stays held from there."""
    prepared, _, _ = box
    view = View(quantity="intensity", noise=False, polychromatic=False)
    slow = (3.0, 2.55, 2.1, 1.65, 1.2, 0.9, 0.6)
    matrices, _, _ = _creep_after_stop(renderer, prepared, view, [0.0] * 7, slow)
    assert matrices == [64] * 5 + [128] * 2
    matrices, _, _ = _creep_after_stop(renderer, prepared, view, None, slow)
    assert matrices == [64] * 7


def test_a_measured_pose_that_jitters_beyond_the_hold_leaves_rest_to_the_filtered_pose(renderer, box):
    """A camera whose measured pose jumps 1.5 px about POSE frame to frame (more than the hold)
    gives no earlier rest: the filtered pose's rule, as without a measured pose."""
    prepared, _, _ = box
    view = View(quantity="intensity", noise=False, polychromatic=False)
    matrices, _, _ = _creep_after_stop(renderer, prepared, view, [0.75, -0.75] * 3 + [0.75])
    assert matrices == [64] * 6 + [128]


def test_a_view_let_go_of_rests_again_only_after_settle_s(renderer, box):
    """Rest began at the start of a creep (0.6 px before the pose it was held at); a move back past
    that start, beyond the hold from the held pose but within it of where the rest began, is
    motion: the view rests again only after settle_s more."""
    prepared, _, _ = box
    step = _mm_for_px(renderer, prepared, 0.3)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    clock = Clock()
    pr = ProgressiveRenderer(renderer, HOLD, clock=clock)
    walk(pr, clock, prepared, [shifted(dx) for dx in (-4.0, -2.0, 0.0, step, 2 * step, 2 * step)], view)
    assert pr.matrix == 128                      # held at +0.6 px since 0.12 s after the creep began
    clock.t += 0.04
    pr.render(prepared, shifted(-1.5 * step), view)      # 1.05 px from the held pose, 0.45 px from the start
    assert pr.matrix == 64


TIERS = Rendering(moving_matrix_px=64, rest_matrix_px=96, settle_s=0.1, refine_bands=4)


def _implied_ok(renderer, image, T, lo, hi):
    """Median error of the chord implied by `image` (intensity) against the box's closed form at T."""
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), T, 128, 128)
    L_cm = box_chords(s, d, lo, hi) / 10.0
    inner = cv2.erode((L_cm > 2.0).astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", renderer.spectrum.effective_kev)
    return _implied_chord_error(image, L_cm, inner, mu)


def test_a_rest_shows_the_rest_matrix_and_then_the_full_one(renderer, box):
    """With rest_matrix_px the rest goes moving (64) -> rest matrix (96) -> full (128), each cast
    beside the live frames and then shown from its cache, each the box's closed-form transmission."""
    prepared, lo, hi = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, TIERS, clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    walk(pr, clock, prepared, [shifted(2.0 * i) for i in range(3)] + [shifted(4.0)] * 3, view)
    assert pr.matrix == 64 and pr.refine.target is pr.interim
    assert pr.wait_refined(30.0)
    clock.t += 0.04
    rest = pr.render(prepared, shifted(4.0), view).image
    assert pr.matrix == 96 and pr.refine.target is pr.full        # the full matrix begun as it is shown
    assert pr.wait_refined(30.0) and pr.refine_fault is None
    clock.t += 0.04
    full = pr.render(prepared, shifted(4.0), view).image
    assert pr.matrix == 128
    assert (pr.cache(pr.interim).counts.casts, pr.cache().counts.casts) == (1, 1)
    assert len(pr.interim_at) == len(pr.refined_at) == 1 and pr.interim_at[0] < pr.refined_at[0]
    for image in (rest, full):
        assert _implied_ok(renderer, image, shifted(4.0), lo, hi) < 0.01


def test_a_phase_new_to_a_held_full_view_is_shown_at_the_rest_matrix_while_the_full_one_casts_it(renderer, box):
    """Held at the full matrix, a new phase (a box 4 voxels longer) is shown at the rest matrix,
    cast within its frame there, while the full matrix casts it beside the live frames; then the
    full matrix shows it: the new box's closed form. Without a rest matrix the full matrix casts
    it within the frame and the view keeps its matrix."""
    prepared, _, _ = box
    vol, lo_b, hi_b = box_volume((40, 48, 48), (1.5, 1.25, 2.0), (8, 10, 6), (36, 38, 34))
    other = renderer.prepare(vol)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    for settings, shown in ((TIERS, 96), (Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=4), 128)):
        clock = Clock()
        pr = ProgressiveRenderer(renderer, settings, clock=clock)
        walk(pr, clock, prepared, [POSE] * 8, view, wait=True)    # at rest until the full matrix shows it
        assert pr.matrix == 128 and pr.refined_at
        clock.t += 0.04
        image = pr.render(other, POSE, view).image
        assert pr.matrix == shown
        assert _implied_ok(renderer, image, POSE, lo_b, hi_b) < 0.01
        if shown == 96:
            assert pr.refine.target is pr.full and pr.wait_refined(30.0)
            clock.t += 0.04
            image = pr.render(other, POSE, view).image
            assert pr.matrix == 128 and pr.cache().holds([other])
            assert _implied_ok(renderer, image, POSE, lo_b, hi_b) < 0.01
            assert len(pr.refined_at) == 1      # a held view's new phase is not a new rest


def test_a_rest_matrix_not_below_the_full_one_is_none(renderer):
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, rest_matrix_px=128, refine_bands=4))
    assert pr.interim is None


def test_a_view_back_at_its_held_pose_stops_the_cast_of_the_pose_it_left(renderer, box):
    """Held at A (the full matrix cached), moved to B and rested there long enough for B's cast
    to begin, then back at A before it ends: A is shown at the full matrix from the cache at
    once, B's cast is stopped, and it does not replace A's projections when it ends."""
    prepared, _, _ = box
    clock = Clock()
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, refine_bands=64), clock=clock)
    view = View(quantity="intensity", noise=False, polychromatic=False)
    walk(pr, clock, prepared, [shifted(0.0)] * 8, view, wait=True)
    assert pr.matrix == 128 and pr.cache().counts.casts == 1
    walk(pr, clock, prepared, [shifted(12.0)] * 4, view)     # at B past settle_s: B's cast begins
    b = pr.refine
    assert b is not None and not b.done.is_set()
    clock.t += 0.04
    pr.render(prepared, shifted(0.0), view)
    assert b.cancel
    assert pr.wait_refined(30.0)
    walk(pr, clock, prepared, [shifted(0.0)] * 4, view)
    assert pr.matrix == 128 and pr.cache().counts.casts == 1 and pr.refine is b
