"""The renderer's physics and detector model, each checked against an independent computation."""

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import spekpy
import xraylib

from appliance.config.case import Contrast, Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.errors import FluorosimError
from appliance.geometry import make_transform, rotation_about
from appliance.patient.volume import Volume
from appliance.xray.renderer import Renderer, View, at_resolution, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "fluoroscopes"


def profile(name, size=128, **updates):
    f = at_resolution(load_profile(CONFIGS / name, FluoroscopeProfile), size, size)
    for section, values in updates.items():
        f = f.model_copy(update={section: getattr(f, section).model_copy(update=values)})
    return f


@pytest.fixture(scope="module")
def flat():
    return Renderer(profile("generic-flat-detector.yaml"), Materials(), device="cpu")


@pytest.fixture(scope="module")
def slab(flat):
    """A 40 mm water slab (0 HU) filling the beam: 64 x 64 x 16 voxels of 6 x 6 x 2.5 mm."""
    vol, lo, hi = box_volume((16, 64, 64), (6.0, 6.0, 2.5), (0, 0, 0), (63, 63, 15))
    return flat.prepare(vol), lo, hi


POSE = make_transform(np.eye(3), [0.0, 0.0, 750.0])


def slab_path_mm(renderer, lo, hi):
    rows, cols = renderer.shape
    s, d = pixel_rays_ct(zoomed_K(renderer.fluoroscope, 1), POSE, rows, cols)
    return box_chords(s, d, lo, hi)


def test_monochromatic_intensity_is_beer_lambert_at_the_effective_energy(flat, slab):
    prepared, lo, hi = slab
    ref = spekpy.Spek(kvp=70, th=12)
    ref.filter("Al", 6.0)
    e_eff = ref.get_eeff()
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", e_eff) * 1.0 / 10.0      # 1/mm at 1 g/cm^3
    L = slab_path_mm(flat, lo, hi)
    img = flat.render(prepared, POSE, View(quantity="intensity", noise=False, polychromatic=False)).image
    c = slice(40, 88)                  # away from the slab's edges, where blur cannot reach
    np.testing.assert_allclose(img[c, c], np.exp(-mu * L[c, c]), rtol=2e-3)


def test_polychromatic_intensity_sums_the_spectrum(flat, slab):
    prepared, lo, hi = slab
    ref = spekpy.Spek(kvp=70, th=12)
    ref.filter("Al", 6.0)
    k, phi = ref.get_spectrum()
    mu = np.array([xraylib.CS_Total_CP("Tissue, Soft (ICRP)", float(e)) for e in k]) / 10.0
    L = slab_path_mm(flat, lo, hi)[64, 64]
    expected = np.sum(phi * k * np.exp(-mu * L)) / np.sum(phi * k)      # fine 0.5 keV spectrum, energy-integrating
    img = flat.render(prepared, POSE, View(quantity="intensity", noise=False)).image
    assert img[64, 64] == pytest.approx(expected, rel=0.01)
    mono = flat.render(prepared, POSE, View(quantity="intensity", noise=False, polychromatic=False)).image
    assert img[64, 64] > mono[64, 64]       # beam hardening: the spectrum's soft end is filtered out first


def knee(x, k):
    """The display's soft knee written out: identity on [k, 1-k], k^2 / (k + (k - x)) below, mirrored above."""
    x = np.asarray(x, float)
    return np.where(x < k, k * k / (2 * k - x), np.where(x > 1 - k, 1 - k * k / (k + x - (1 - k)), x))


def test_display_is_window_level_of_minus_log_through_a_soft_knee():
    flat = Renderer(profile("generic-flat-detector.yaml", abc={"enabled": False}), Materials(), device="cpu")
    prepared = flat.prepare(box_volume((16, 64, 64), (6.0, 6.0, 2.5), (0, 0, 0), (63, 63, 15))[0])
    I = flat.render(prepared, POSE, View(quantity="intensity", noise=False)).image
    disp = flat.render(prepared, POSE, View(quantity="display", noise=False)).image
    w, l = flat.fluoroscope.display.window, flat.fluoroscope.display.level
    k = flat.fluoroscope.image.display_knee
    np.testing.assert_allclose(disp, knee((-np.log(I) - l) / w + 0.5, k), atol=1e-5)
    assert disp.min() > 0 and disp.max() < 1                 # never clipped
    inv = flat.render(prepared, POSE, View(quantity="display", noise=False, invert=True)).image
    np.testing.assert_allclose(inv, 1 - disp, atol=1e-6)
    # The radiographer's window and level keys: half the width doubles the contrast about the centre.
    narrow = flat.render(prepared, POSE, View(quantity="display", noise=False, window_scale=0.5, level_shift=-0.1)).image
    np.testing.assert_allclose(narrow, knee((-np.log(I) - (l - 0.05 * w)) / (0.5 * w) + 0.5, k), atol=1e-5)


def test_automatic_brightness_shows_thin_and_thick_patients_equally_bright():
    """With ABC the middle of a uniform slab sits at mid-grey whatever its thickness (the window
    centre is the median attenuation there), and the tube output is exp(mu L - reference)
    within the profile's limits; with a fixed level a thicker slab is brighter by mu x L / window."""
    fixed = Renderer(profile("generic-flat-detector.yaml", abc={"enabled": False}), Materials(), device="cpu")
    # The control without a kV-mA curve (the shipped room has one: test_flat_detector_abc).
    abc = Renderer(profile("generic-flat-detector.yaml", abc={"enabled": True, "curve": []}), Materials(), device="cpu")
    limits = abc.fluoroscope.abc
    ref = spekpy.Spek(kvp=70, th=12)
    ref.filter("Al", 6.0)
    mu = xraylib.CS_Total_CP("Tissue, Soft (ICRP)", ref.get_eeff()) / 10.0      # 1/mm, water-like at 1 g/cm^3
    w, l = fixed.fluoroscope.display.window, fixed.fluoroscope.display.level
    c = 64
    factors = []
    for thickness_mm in (20.0, 100.0, 140.0, 400.0):
        vol, lo, hi = box_volume((8, 64, 64), (6.0, 6.0, thickness_mm / 8), (0, 0, 0), (63, 63, 7))
        view = View(quantity="display", noise=False, polychromatic=False)
        L = slab_path_mm(fixed, lo, hi)[c, c]
        assert L == pytest.approx(thickness_mm, rel=0.01)
        shown = fixed.render(fixed.prepare(vol), POSE, view)
        assert shown.image[c, c] == pytest.approx(float(knee((mu * L - l) / w + 0.5, fixed.fluoroscope.image.display_knee)), abs=2e-3)
        assert shown.exposure_factor == 1.0
        # The window sits on the measured attenuation: the middle of the slab is mid-grey, less
        # the centre's shorter path than the measuring field's median ray (< 0.3 % of 400 mm,
        # which the narrowest automatic window, 1.0, makes about a per cent of grey).
        frame = abc.render(abc.prepare(vol), POSE, view)
        assert frame.attenuation == pytest.approx(mu * L, rel=0.004)
        assert frame.window[0] == pytest.approx(frame.attenuation, rel=0.01)
        assert frame.image[c, c] == pytest.approx(0.5, abs=0.02)
        expected = min(max(math.exp(mu * L - limits.reference_attenuation), limits.min_factor), limits.max_factor)
        assert frame.exposure_factor == pytest.approx(expected, rel=0.01)
        factors.append(frame.exposure_factor)
    # The thinnest and thickest slabs reach the tube's limits; the two between do not.
    assert factors[0] == limits.min_factor and factors[-1] == limits.max_factor
    assert limits.min_factor < factors[1] < factors[2] < limits.max_factor


def test_quantum_noise_is_poisson_with_the_photon_count(flat, slab):
    prepared, _, _ = slab
    clean = flat.render(prepared, POSE, View(quantity="intensity", noise=False)).image
    noisy = flat.render(prepared, POSE, View(quantity="intensity", noise=True, seed=3)).image
    n0 = flat.photons_per_pixel(1)
    # Independent photon count: 6 mGy/min at the reference point (600 mm from the source) over
    # 30 frames/s, inverse square to the 1100 mm SID, spekpy's fluence per air kerma of the
    # beam after the reference patient (3 attenuation lengths of water), the pixel's area.
    ref = spekpy.Spek(kvp=70, th=12)
    ref.filter("Al", 6.0)
    mu_water = xraylib.CS_Total_CP("Water, Liquid", ref.get_eeff()) / 10.0
    ref.filter("Water, Liquid", 3.0 / mu_water)
    f = flat.fluoroscope
    kerma_ugy = 6.0 * 1000 / 60 / 30 * (600 / 1100) ** 2
    expected_n0 = kerma_ugy * ref.get_flu() / ref.get_kerma() / 100 * f.detector.pixel_pitch_mm ** 2
    assert n0 == pytest.approx(expected_n0, rel=0.02)
    c = slice(20, 108)
    ratio = noisy[c, c] / clean[c, c]
    assert ratio.mean() == pytest.approx(1.0, abs=0.01)
    expected_sd = 1 / math.sqrt(n0 * float(clean[c, c].mean()))
    assert ratio.std() == pytest.approx(expected_sd, rel=0.1)
    again = flat.render(prepared, POSE, View(quantity="intensity", noise=True, seed=3)).image
    np.testing.assert_array_equal(noisy, again)


def test_zoom_scales_the_focal_length_not_the_image(flat):
    vol, lo, hi = box_volume((16, 32, 32), (2.0, 2.0, 2.5), (10, 12, 4), (21, 19, 11))
    prepared = flat.prepare(vol)
    f = flat.fluoroscope
    for zoom in (1, 3):
        img = flat.render(prepared, POSE, View(quantity="line-integral", zoom=zoom)).image
        scale = f.zoom_levels[0].fov_mm / f.zoom_levels[zoom - 1].fov_mm
        K = np.array([[f.intrinsics.fx * scale, 0, f.intrinsics.cx], [0, f.intrinsics.fy * scale, f.intrinsics.cy], [0, 0, 1]])
        s, d = pixel_rays_ct(K, POSE, *flat.shape)
        truth = box_chords(s, d, lo, hi) * flat.mu_water_per_mm
        assert img.shape == flat.shape
        np.testing.assert_allclose(img, truth, atol=2e-4 * truth.max())
        width = (img.max(axis=0) > 0).sum()
        assert width == pytest.approx(24 * 1100 / 750 * scale / f.detector.pixel_pitch_mm, abs=2)


def test_collimation_and_intensifier_field():
    # Without veiling glare, whose halo also darkens the edge of the field (tests/test_image_chain.py).
    ii = Renderer(profile("generic-ii-carm.yaml", image={"veiling_glare": 0.0}), Materials(), device="cpu")
    vol, _, _ = box_volume((16, 64, 64), (6.0, 6.0, 2.5), (0, 0, 0), (63, 63, 15))
    prepared = ii.prepare(vol)
    T = make_transform(np.eye(3), [0.0, 0.0, 620.0])
    open_ = ii.render(prepared, T, View(noise=False)).image
    assert open_[0, 0] == 0 and open_[127, 127] == 0          # outside the intensifier's circle
    assert open_[64, 64] > 0 and open_[64, 2] > 0             # inside it
    pitch = ii.fluoroscope.detector.pixel_pitch_mm
    col = ii.render(prepared, T, View(noise=False, collimation_mm=(60.0, 30.0))).image
    # The blades' edges lie where the soft edge has fallen to half the field's grey.
    lit = col > 0.5 * col[64, 64]
    assert lit[64].sum() == pytest.approx(60.0 / pitch, abs=1.5)
    assert lit[:, 64].sum() == pytest.approx(30.0 / pitch, abs=1.5)
    # Collimated-out pixels beyond the edge's penumbra are never cast: their integrals are zero.
    lines = ii.material_integrals(prepared, T, View(collimation_mm=(60.0, 30.0)))
    exposed = col > 0
    assert np.all(lines[~exposed] == 0) and np.all(lines[lit].sum(-1) > 0)
    assert exposed.sum() - lit.sum() < 2 * (lit[64].sum() + lit[:, 64].sum()) * 2   # a thin penumbra only
    # Vignetting: the open-field signal falls toward the edge of the circle.
    air = ii.prepare(box_volume((4, 4, 4), (1.0, 1.0, 1.0), (0, 0, 0), (0, 0, 0), hu=-1000)[0])
    I = ii.render(air, T, View(quantity="intensity", noise=False)).image
    assert I[64, 64] == pytest.approx(1.0, abs=1e-4)
    r = ii.fluoroscope.zoom_levels[0].fov_mm / pitch / 2
    assert I[64, 64 + int(r * 0.7)] == pytest.approx(1 - ii.fluoroscope.detector.vignetting * (int(r * 0.7) + 0.5) ** 2 / r**2, abs=2e-3)


def test_distortion_moves_objects_where_opencv_projects_them():
    ii = Renderer(profile("generic-ii-carm.yaml"), Materials(), device="cpu")
    f = ii.fluoroscope
    # A dense 4 mm cube off-axis in an otherwise empty grid.
    vol, lo, hi = box_volume((41, 41, 41), (1.0, 1.0, 1.0), (26, 26, 20), (29, 29, 23), hu=3000)
    prepared = ii.prepare(vol)
    offset = np.array([40.0, 35.0, 620.0])         # far enough off-axis for the pincushion to show
    T = make_transform(np.eye(3), offset)
    I = ii.render(prepared, T, View(quantity="intensity", noise=False)).image
    air = ii.prepare(box_volume((4, 4, 4), (1.0, 1.0, 1.0), (0, 0, 0), (0, 0, 0), hu=-1000)[0])
    I_open = ii.render(air, T, View(quantity="intensity", noise=False)).image    # circle and vignetting alone
    w = np.where(I_open > 0, 1.0 - I / np.where(I_open > 0, I_open, 1.0), 0.0)
    w[w < 0.02] = 0
    v, u = np.indices(w.shape)
    centroid = np.array([(u * w).sum(), (v * w).sum()]) / w.sum()
    centre_ct = (lo + hi) / 2
    K = f.intrinsics.K()
    expected, _ = cv2.projectPoints(centre_ct.reshape(1, 3) + offset, np.zeros(3), np.zeros(3), K,
                                    f.intrinsics.distortion.coefficients())
    undistorted = K @ (centre_ct + offset)
    undistorted = undistorted[:2] / undistorted[2]
    assert np.linalg.norm(expected.ravel() - undistorted) > 1.0       # the distortion is visible here
    assert np.linalg.norm(centroid - expected.ravel()) < 0.3


def test_blend_interpolates_between_phases(flat):
    a = flat.prepare(box_volume((16, 32, 32), (2.0, 2.0, 2.5), (4, 4, 2), (27, 27, 13), hu=0)[0])
    b = flat.prepare(box_volume((16, 32, 32), (2.0, 2.0, 2.5), (4, 4, 2), (27, 27, 13), hu=-400)[0])
    la = flat.material_integrals(a, POSE, View()).sum(-1)
    lb = flat.material_integrals(b, POSE, View()).sum(-1)
    lm = flat.material_integrals(a, POSE, View(), blend=(b, 0.25)).sum(-1)
    # Density is linear in HU for soft tissue, so a quarter of the way is a quarter of the change.
    np.testing.assert_allclose(lm, 0.75 * la + 0.25 * lb, atol=1e-4 * la.max())
    assert la[64, 64] == pytest.approx(lb[64, 64] / 0.6, rel=1e-4)


def test_bad_pose_and_quantity_are_one_line_errors(flat, slab):
    prepared, _, _ = slab
    bad = POSE.copy()
    bad[0, 0] = 2.0
    with pytest.raises(FluorosimError, match="T_xray_from_ct"):
        flat.render(prepared, bad, View())
    with pytest.raises(FluorosimError, match="quantity"):
        flat.render(prepared, POSE, View(quantity="xray"))
    with pytest.raises(FluorosimError, match="zoom"):
        flat.render(prepared, POSE, View(zoom=5))


def test_volume_outside_the_beam_renders_open_field(flat, slab):
    prepared, _, _ = slab
    away = make_transform(rotation_about([1, 0, 0], 0.3), [0.0, 0.0, -750.0])   # volume behind the source
    I = flat.render(prepared, away, View(quantity="intensity", noise=False)).image
    np.testing.assert_allclose(I, 1.0, atol=1e-6)


def test_cpu_packet_kernel_matches_one_ray_per_work_item():
    f = profile("generic-ii-carm.yaml", size=100)      # not a multiple of the 16-pixel packet
    vol, _, _ = box_volume((30, 40, 36), (2.0, 1.5, 2.5), (5, 6, 4), (30, 33, 25), hu=500)
    hu = vol.hu.copy()
    hu[10:20, 10:30, 8:20] = 2600
    vol = type(vol)(hu=hu, T_ct_from_voxel=vol.T_ct_from_voxel)
    # (away from 45 degrees, where a packet may step along the other axis than a lone ray)
    T = make_transform(rotation_about([0.5, 1.0, 0.2], 0.35), [3.0, -4.0, 620.0])
    out, intensity = [], []
    for packet in (True, False):
        r = Renderer(f, Materials(contrast_min_hu=2500), Contrast(concentration_mg_per_ml=100), device="cpu", packet=packet)
        prepared = r.prepare(vol)
        out.append(r.material_integrals(prepared, T, View(collimation_mm=(150.0, 90.0))))
        intensity.append(r.render(prepared, T, View(quantity="intensity", noise=False, collimation_mm=(150.0, 90.0))).image)
    np.testing.assert_allclose(out[0], out[1], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(intensity[0], intensity[1], rtol=1e-5, atol=1e-6)
    assert intensity[0].min() < 0.5
    assert out[0][..., 2].max() > 10 and out[0][..., 3].max() > 10        # bone and contrast both seen


@pytest.mark.parametrize("lam", [0.3, 2.0, 12.0, 29.0])
def test_low_counts_are_poisson(flat, lam):
    image = np.full((200, 200), lam / 1000.0, dtype=np.float32)        # lam photons expected of 1000
    noisy = flat.quantum_noise(image, 1000.0, seed=5) * 1000.0
    np.testing.assert_allclose(noisy, np.rint(noisy), atol=1e-3)      # whole photons
    counts = np.rint(noisy).astype(int).ravel()
    assert counts.mean() == pytest.approx(lam, abs=4 * math.sqrt(lam / counts.size))
    assert counts.var() == pytest.approx(lam, rel=0.05)
    # The histogram against the Poisson probabilities lam^k e^-lam / k!, for every k it reaches.
    for k in range(int(lam + 4 * math.sqrt(lam)) + 1):
        expected = math.exp(k * math.log(lam) - lam - math.lgamma(k + 1))
        assert (counts == k).mean() == pytest.approx(expected, abs=4 * math.sqrt(expected / counts.size) + 1e-4)


def test_high_counts_are_gaussian_with_poisson_variance(flat):
    image = np.full((300, 300), 0.5, dtype=np.float32)
    noisy = flat.quantum_noise(image, 200.0, seed=9) * 200.0           # 100 photons expected
    assert noisy.mean() == pytest.approx(100.0, abs=0.1)
    assert noisy.std() == pytest.approx(10.0, rel=0.02)
    # Neighbouring pixels and two seeds are uncorrelated.
    assert abs(np.corrcoef(noisy[:, :-1].ravel(), noisy[:, 1:].ravel())[0, 1]) < 0.01
    other = flat.quantum_noise(image, 200.0, seed=10) * 200.0
    assert abs(np.corrcoef(noisy.ravel(), other.ravel())[0, 1]) < 0.01
    assert not np.array_equal(flat.quantum_noise(image, 200.0), flat.quantum_noise(image, 200.0))


def test_profile_reload_takes_the_new_tube(flat, slab):
    prepared, _, _ = slab
    before = flat.mu_water_per_mm
    f = flat.fluoroscope
    try:
        flat.set_fluoroscope(f.model_copy(update={"tube": f.tube.model_copy(update={"kvp": 110.0})}))
        assert flat.spectrum.effective_kev > 45
        assert flat.mu_water_per_mm < before
        assert flat.mu_water_per_mm == pytest.approx(xraylib.CS_Total_CP("Water, Liquid", flat.spectrum.effective_kev) / 10)
    finally:
        flat.set_fluoroscope(f)
    assert flat.mu_water_per_mm == before


# Posterior-anterior (rays along the volume's y, detector rows along its x) with the rows turned
# a degree across the slices, and a view 17 degrees off the volume's z.
PA_ROLLED = make_transform(rotation_about([0, 0, 1], np.radians(1.0)) @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
                           [1.0, 2.0, 750.0])
OFF_AXIS = make_transform(rotation_about([1, 0.2, 0], 0.3), [0.0, 0.0, 750.0])


def _cast_built_both_ways(hu: np.ndarray, T, option: str) -> tuple[np.ndarray, np.ndarray]:
    """The CPU packet kernel's material integrals of `hu` (2 x 2 x 2.5 mm voxels) at pose T, as
    built for this device and as built with `option` as well (a path turned off)."""
    import pyopencl as cl

    r = Renderer(profile("generic-flat-detector.yaml", size=64), Materials(), device="cpu")
    prepared = r.prepare(Volume(hu=hu, T_ct_from_voxel=np.diag([2.0, 2.0, 2.5, 1.0]), source="noise"))
    a = r.material_integrals(prepared, T, View())
    program = cl.Program(r.dev.ctx, r.dev.source).build(options=["-DUNALIGNED_PAIRS", option])
    r.caster._joseph = cl.Kernel(program, "joseph_packet")
    return a, r.material_integrals(prepared, T, View())


@pytest.mark.parametrize("T", [OFF_AXIS, PA_ROLLED])
def test_portable_pair_loads_match_hardware_gathers(T):
    """The packet kernel's hardware loads (row windows where a packet's samples lie in one or two
    rows of a slice, gathers elsewhere) against the portable 32-bit pair loads, on noise (every
    voxel differs from its neighbours): the same integrals to the bit."""
    hu = np.random.default_rng(3).integers(-900, 1500, size=(20, 24, 24)).astype(np.int16)
    a, b = _cast_built_both_ways(hu, T, "-DNO_HW_GATHER")
    assert a.max() > 40
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("T", [OFF_AXIS, PA_ROLLED])
def test_cast_is_the_same_to_the_bit_without_the_mask_register(T):
    """The packet kernel's tests of its masks through AVX-512's mask register against AVX's sign
    bits (test_packet_masks.py), on noise with bone in one half across x only, so that the test
    for a bone corner in the packet goes both ways, as do the row windows' tests."""
    hu = np.random.default_rng(8).integers(-900, 1500, size=(20, 24, 24)).astype(np.int16)
    hu[:, :, :12] = np.minimum(hu[:, :, :12], 100)
    a, b = _cast_built_both_ways(hu, T, "-DNO_MASK_REGISTERS")
    bone = a[..., 2][a[..., 1] > 1]
    assert (bone == 0).any() and (bone > 1).any()        # rays with bone and rays without
    np.testing.assert_array_equal(a, b)
