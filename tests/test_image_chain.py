"""The image chain after the physics, each stage against a closed form or photon statistics.

Ground truth: the Gaussian MTF at the profile's limiting resolution, the recursive filter's
step response w^k, a Gaussian glare halo's value inside a lead disc, photon statistics from
spekpy's fluence per air kerma and the inverse-square law, the 21 CFR 1020.32 dose-rate
limit, 8-bit inversion p -> 255 - p, and clinical acceptance limits (<= 1 % clipped, >= 50 %
grey range) on a synthetic adult chest CT.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.display.compositor import Compositor, Overlay
from appliance.patient import adult_pelvis
from appliance.patient.adult_chest import SIZES, build_adult_chest
from appliance.patient.volume import Volume
from appliance.xray import acceptance, bar_pattern
from appliance.xray.casting import CastCancelled
from appliance.xray.detector import Detector, RecursiveFilter
from appliance.xray.display_lut import soft_knee
from appliance.xray.renderer import Renderer, View, at_resolution
from appliance.xray.truth import photon_statistics
from appliance.xray.truth.analytic import box_volume
from drivers.framebuffer import open_display

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "fluoroscopes"
II = load_profile(CONFIGS / "generic-ii-carm.yaml", FluoroscopeProfile)


def with_chain(fl, **values):
    return fl.model_copy(update={"image": fl.image.model_copy(update=values)})


@pytest.fixture(scope="module")
def adult():
    # The adult chest on the quick grid (5 x 3.2 x 3.2 mm): coarser slices stair-step the
    # exact line integral the detail figure is measured against.
    hu, spacing, origin = build_adult_chest(*SIZES["small"], seed=1)
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    T[:3, 3] = origin
    return Volume(hu=hu, T_ct_from_voxel=T, source="adult chest")


@pytest.fixture(scope="module")
def ii128():
    return Renderer(at_resolution(II, 128, 128), Materials(), device="cpu")


def test_soft_knee_is_identity_in_the_middle_and_never_reaches_the_ends():
    x = np.linspace(-3, 4, 7001)
    y = soft_knee(x, 0.15)
    middle = (x >= 0.15) & (x <= 0.85)
    np.testing.assert_allclose(y[middle], x[middle], atol=1e-6)
    assert y.min() > 0 and y.max() < 1
    assert np.all(np.diff(y) >= 0)                      # monotonic: gradation kept, order kept
    slope = np.gradient(y, x)
    assert slope[np.argmin(abs(x - 0.15))] == pytest.approx(1.0, abs=0.01)    # no kink at the join


def test_point_spread_has_the_profiles_limiting_resolution():
    """A sine at the stated limiting frequency keeps MTF_AT_LIMIT (4 %) of its modulation."""
    fl = with_chain(II, veiling_glare=0.0)
    det = Detector(fl, 0.02)
    rows, cols = fl.detector.rows, fl.detector.columns
    mask = np.ones((rows, cols), bool)
    for zoom in (1, 4):
        pitch = fl.detector.pixel_pitch_mm * fl.zoom_levels[zoom - 1].fov_mm / fl.zoom_levels[0].fov_mm
        f = fl.image.limiting_resolution_lp_per_mm[zoom - 1] * pitch          # cycles per pixel
        half = fl.image.limiting_resolution_lp_per_mm[zoom - 1] * pitch * 0.5  # half the limit
        for freq, expected in ((f, 0.04), (half, 0.04 ** 0.25)):
            u = np.arange(cols)
            img = np.tile((1.0 + 0.5 * np.sin(2 * np.pi * freq * u)).astype(np.float32), (rows, 1))
            out = det.spread(img, mask, zoom)[rows // 2, 100:-100]
            basis = np.stack([np.sin(2 * np.pi * freq * u[100:-100]), np.cos(2 * np.pi * freq * u[100:-100]),
                              np.ones(cols - 200)], 1)
            a, b, _ = np.linalg.lstsq(basis, out - 0.0, rcond=None)[0]
            gain = det.gain(zoom)[rows // 2, 100:-100].mean()
            assert math.hypot(a, b) / 0.5 / gain == pytest.approx(expected, rel=0.15, abs=0.004), (zoom, freq)


def test_veiling_glare_fills_a_lead_disc_as_a_gaussian_halo_would():
    """Inside a lead disc of radius R in an open field, the halo of a fraction g spread as a
    Gaussian of sigma s leaves g exp(-R^2 / 2 s^2) at the centre; far from it the signal is 1."""
    fl = with_chain(II.model_copy(update={"detector": II.detector.model_copy(update={"vignetting": 0.0})}),
                    veiling_glare=0.1, glare_sigma_mm=20.0, limiting_resolution_lp_per_mm=[20.0, 20, 20, 20])
    det = Detector(fl, 0.02)
    rows, cols = fl.detector.rows, fl.detector.columns
    v, u = np.ogrid[:rows, :cols]
    r_mm = np.hypot(v - (rows - 1) / 2, u - (cols - 1) / 2) * fl.detector.pixel_pitch_mm
    for radius_mm in (10.0, 25.0):
        img = np.where(r_mm <= radius_mm, 0.0, 1.0).astype(np.float32)
        out = det.spread(img, np.ones((rows, cols), bool), 1)
        centre = out[rows // 2 - 2:rows // 2 + 2, cols // 2 - 2:cols // 2 + 2].mean()
        assert centre == pytest.approx(0.1 * math.exp(-radius_mm ** 2 / (2 * 20.0 ** 2)), rel=0.15)
        far = out[(r_mm > radius_mm + 90) & (r_mm < radius_mm + 100)].mean()
        assert far == pytest.approx(1.0, abs=0.01)


def test_recursive_filter_step_response_is_w_to_the_k():
    for w in (0.25, 0.5, 0.75):
        lag = RecursiveFilter(w)
        for _ in range(3):
            lag.step(np.zeros((4, 4), np.float32), "field")
        for k in range(1, 8):
            out = lag.step(np.ones((4, 4), np.float32), "field")
            assert out[0, 0] == pytest.approx(1 - w ** k, abs=1e-6)
        # A new field (zoom, collimation) starts afresh instead of trailing the old one.
        assert lag.step(np.full((4, 4), 5.0, np.float32), "zoom 2")[0, 0] == 5.0


@pytest.mark.parametrize("name", ["generic-ii-carm.yaml", "generic-flat-detector.yaml"])
def test_water_slab_snr_matches_photon_statistics_and_holds_across_zoom(name):
    """The displayed SNR of a 150 mm water slab against sqrt(N): N from the profile's air-kerma
    rate, inverse-square law and spekpy's fluence per air kerma (photon_statistics.expected_slab_snr),
    with the settled recursive filter and the point-spread's variance reduction. On both rooms
    (intensifier and flat panel) the SNR holds within 25 % across the four zooms."""
    r = Renderer(at_resolution(load_profile(CONFIGS / name, FluoroscopeProfile), 128, 128), Materials(), device="cpu")
    prepared = r.prepare(acceptance._water_slab(150.0))
    T = acceptance.ap_pose(r.fluoroscope.geometry.source_to_isocentre_mm)
    centre, roi = acceptance._disc(r.shape, 0.1), acceptance._disc(r.shape, 0.3)
    snrs = []
    for zoom in (1, 2, 3, 4):
        # The slab's transmission at the kV the exposure control set, from the noise-free signal.
        clean_frame = r.render(prepared, T, View(zoom=zoom, noise=False))
        vignetting = r.detector.gain(zoom)           # None on the flat panel: it has none
        transmission = float(np.median(clean_frame.signal[centre])) / (
            1.0 if vignetting is None else float(np.median(vignetting[centre])))
        clean = clean_frame.signal[roi]
        measured = []
        for seed in range(4):
            frame = r.render(prepared, T, View(zoom=zoom, seed=seed))
            measured.append(1.0 / np.std(frame.signal[roi] / clean))
        expected = photon_statistics.expected_slab_snr(r.fluoroscope, zoom, transmission, frame.exposure_factor,
                                                r.mu_water_per_mm, r.detector.psf_sigma_px(zoom), settled=True,
                                                kvp=frame.kvp)
        assert np.median(measured) == pytest.approx(expected, rel=0.10), zoom
        snrs.append(np.median(measured))
    assert max(snrs) / min(snrs) < 1.25


def test_exposure_control_stays_within_the_dose_rate_limit(ii128):
    """400 mm of water at zoom 4 asks for far more than the tube may give: the output stops
    where the reference point's air-kerma rate reaches 88 mGy/min."""
    prepared = ii128.prepare(box_volume((8, 64, 64), (8.0, 8.0, 50.0), (0, 0, 0), (63, 63, 7))[0])
    T = np.eye(4)                      # the beam along the box's 400 mm z axis
    T[2, 3] = 620.0
    frame = ii128.render(prepared, T, View(zoom=4, noise=False))
    rate = II.zoom_levels[3].air_kerma_rate_mgy_per_min["continuous"]
    assert frame.limited
    assert frame.exposure_factor * rate == pytest.approx(88.0, rel=1e-6)
    # Pulsed at 7.5/s the limit is far away: the generator runs to the top of its curve, and the
    # rate follows spekpy's air kerma per mAs there and at the reference technique.
    pulsed = ii128.render(prepared, T, View(zoom=4, noise=False, mode="pulsed-7.5"))
    top = II.abc.curve[-1]
    assert pulsed.limited and (pulsed.kvp, pulsed.ma) == (top.kvp, top.ma)
    expected = top.ma * spekpy_kerma(top.kvp) / (II.tube.ma * spekpy_kerma(II.tube.kvp))
    assert pulsed.exposure_factor == pytest.approx(expected, rel=1e-6)
    rate_pulsed = II.zoom_levels[3].air_kerma_rate_mgy_per_min["pulsed-7.5"]
    assert pulsed.exposure_factor * rate_pulsed < 88.0


@functools.lru_cache(maxsize=16)
def _spek(kvp: float, filtration_mm_al: float):
    """spekpy's own spectrum of the tube (12 degree anode, 0.5 keV steps): (energies keV,
    fluence per keV per mAs at 1 m, air kerma uGy per mAs at 1 m). Each costs seconds."""
    import spekpy

    s = spekpy.Spek(kvp=kvp, th=12.0, dk=0.5)
    s.filter("Al", filtration_mm_al)
    k, phi = s.get_spectrum()
    return k, phi, float(s.get_kerma())


def spekpy_kerma(kvp: float, fl=II) -> float:
    """Air kerma per mAs at 1 m of the profile's tube at `kvp`, from spekpy itself."""
    return _spek(float(kvp), float(fl.tube.filtration_mm_al))[2]


def water_signal(kvp: float, water_mm: float, fl=II) -> float:
    """An energy-integrating detector's signal per mAs behind `water_mm` of water at `kvp`
    through the tube filtration of profile `fl`: spekpy's spectrum (0.5 keV steps) through
    xraylib's water, summed over photons x energy."""
    import xraylib

    k, phi, _ = _spek(float(kvp), float(fl.tube.filtration_mm_al))
    mu = np.array([xraylib.CS_Total_CP("Water, Liquid", float(e)) for e in k]) / 10.0
    return float(np.sum(phi * k * np.exp(-mu * water_mm)))


@pytest.mark.parametrize("water_mm", [90.0, 200.0])
def test_exposure_control_moves_along_its_kv_ma_curve_to_the_reference_signal(water_mm):
    """With abc.curve the control raises kV and mA together: a thicker slab gets a higher point
    of the curve, and at the point it sets, mA x the detector signal per mAs behind the slab
    (spekpy's spectrum at that kV through water, computed here) equals the reference: the open
    field at the reference technique times exp(-reference_attenuation), within the spectrum
    model's and soft tissue's few per cent; the dose rate follows spekpy's air kerma per mAs."""
    plain = with_chain(II, veiling_glare=0.0)        # no glare or vignetting: the slab's signal is uniform
    plain = plain.model_copy(update={"detector": plain.detector.model_copy(update={"vignetting": 0.0})})
    flat_ii = Renderer(at_resolution(plain, 64, 64), Materials(), device="cpu")
    n = int(water_mm // 5)
    vol = box_volume((n, 64, 64), (8.0, 8.0, 5.0), (0, 0, 0), (63, 63, n - 1), hu=0)[0]
    T = np.eye(4)
    T[2, 3] = 620.0
    frame = flat_ii.render(flat_ii.prepare(vol), T, View(noise=False))
    curve = II.abc.curve
    assert not frame.limited and curve[0].kvp < frame.kvp < curve[-1].kvp
    i = max(j for j in range(len(curve) - 1) if curve[j].kvp <= frame.kvp)
    w = (frame.kvp - curve[i].kvp) / (curve[i + 1].kvp - curve[i].kvp)
    # On the curve, the mA trimmed down within the last 1 kV step (a step moves the signal ~5-10 %).
    on_curve = curve[i].ma + w * (curve[i + 1].ma - curve[i].ma)
    assert 0.88 * on_curve <= frame.ma <= on_curve * (1 + 1e-9)
    # The reference: the open field at the reference technique times exp(-reference_attenuation).
    # (HU 0 is soft tissue to the renderer; its attenuation is within a few per cent of water's.)
    signal = frame.ma * water_signal(frame.kvp, water_mm)
    target = II.tube.ma * water_signal(II.tube.kvp, 0.0) * math.exp(-II.abc.reference_attenuation)
    assert signal == pytest.approx(target, rel=0.10)
    assert frame.exposure_factor == pytest.approx(frame.ma * spekpy_kerma(frame.kvp) /
                                                  (II.tube.ma * spekpy_kerma(II.tube.kvp)), rel=0.02)


def _keeps_its_anatomy_on_screen(renderer, volume, centres, zoom):
    prepared = renderer.prepare(volume)
    for centre in centres:
        T = acceptance.ap_pose(620.0, centre)
        frame = renderer.render(prepared, T, View(zoom=zoom, seed=7))
        mask = renderer.field_mask(zoom, None, True)
        inside = acceptance.interior(mask, renderer.detector.edge(mask, zoom))
        assert acceptance.clipped_fraction(frame.image, inside) <= 0.01
        assert acceptance.grey_span(frame.image, inside) >= 0.5
        clean = renderer.render(prepared, T, View(zoom=zoom, noise=False))
        line = renderer.line_integral(prepared, T, zoom)
        # Distortion bends the display's rays away from the pinhole line integral's at the
        # edge; the middle of the field still has to follow the anatomy.
        assert acceptance.detail_correlation(clean.image, line, inside) >= 0.6


@pytest.mark.parametrize("zoom", [1, 4])
def test_adult_chest_keeps_its_anatomy_on_screen(ii128, adult, zoom):
    _keeps_its_anatomy_on_screen(ii128, adult, ((0.0, 0.0, 30.0), (-90.0, 0.0, 60.0), (0.0, 0.0, -90.0)), zoom)


@pytest.mark.parametrize("zoom", [1, 4])
def test_abdomen_and_pelvis_with_couch_and_padding_keep_their_anatomy_on_screen(ii128, zoom):
    """Lumbar spine and bowel gas, then sacrum, iliac wings and femoral heads, the CT couch
    in the beam and -3024 HU padding outside the reconstruction circle."""
    hu, spacing, origin = adult_pelvis.build_adult_pelvis(*adult_pelvis.SIZES["small"], seed=1)
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    T[:3, 3] = origin
    pelvis = Volume(hu=hu, T_ct_from_voxel=T, source="adult abdomen-pelvis")
    _keeps_its_anatomy_on_screen(ii128, pelvis, ((0.0, 0.0, 60.0), (0.0, 0.0, -100.0)), zoom)


def test_invert_flips_every_screen_pixel(ii128, adult, tmp_path):
    """Same frame, INVERT pressed: each pixel the framebuffer shows inside the field becomes
    255 - p within 1 (the compositor's resize rounds once), outside the beam stays black."""
    prepared = ii128.prepare(adult)
    T = acceptance.ap_pose(620.0, (0.0, 0.0, 30.0))
    frames = [ii128.render(prepared, T, View(zoom=1, seed=3, invert=inv)).image for inv in (False, True)]
    comp = Compositor(640, 512)
    screens = []
    for k, (img, inv) in enumerate(zip(frames, (False, True))):
        path = str(tmp_path / f"screen{k}.raw")
        display = open_display("file", path, 640, 512, 32)
        display.show(comp.compose(img, Overlay(live=True, invert=inv), now=0.0))
        screens.append(open_display("file", path, 640, 512, 32, read_only=True).read_back()[..., 0].astype(int))
    mask = ii128.field_mask(1, None, True)
    inside = acceptance.interior(mask, ii128.detector.edge(mask, 1))
    assert np.abs(acceptance.grey8(frames[1])[inside].astype(int) - (255 - acceptance.grey8(frames[0])[inside])).max() <= 1
    # On screen: the image square is 512 x 512 in the middle of the 640-wide frame; compare a
    # central disc that holds no overlay text.
    v, u = np.ogrid[:512, :640]
    disc = (v - 255.5) ** 2 + (u - 319.5) ** 2 <= 200 ** 2
    diff = screens[1][disc] - (255 - screens[0][disc])
    assert np.abs(diff).max() <= 1
    corner = (v - 255.5) ** 2 + (u - 319.5) ** 2 >= 262 ** 2
    corner &= (u > 64) & (u < 576) & (v > 100) & (v < 400)          # beside the circle, away from the text
    assert screens[0][corner].max() == 0 and screens[1][corner].max() == 0


def test_saved_png_and_dicom_agree_with_the_screen_about_polarity(ii128, adult, tmp_path):
    """The saved PNG and DICOM hold the pixels as shown: inverted ones are 255 - p of the
    plain ones, and the DICOM says not to invert again (Presentation LUT Shape IDENTITY)."""
    import cv2
    import pydicom
    from test_saved_images import study_of_session

    from appliance.config import KeymapProfile
    from appliance.console.state import Console
    from appliance.records.saved_images import save_image

    keymap = load_profile(Path(__file__).resolve().parents[1] / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
    state = Console(II, keymap, t0=0.0).snapshot()
    prepared = ii128.prepare(adult)
    T = acceptance.ap_pose(620.0, (0.0, 0.0, 30.0))
    saved = []
    for k, inv in enumerate((False, True)):
        image = ii128.render(prepared, T, View(zoom=1, seed=3, invert=inv)).image
        (tmp_path / str(k)).mkdir()
        png, dcm = save_image(image, state, ii128.fluoroscope, tmp_path / str(k), t_wall=1.7e9,
                              study=study_of_session(tmp_path / str(k)), event_uid=None)
        ds = pydicom.dcmread(dcm)
        assert ds.PresentationLUTShape == "IDENTITY" and ds.PixelIntensityRelationship == "DISP"
        np.testing.assert_array_equal(ds.pixel_array, cv2.imread(str(png), cv2.IMREAD_UNCHANGED))
        saved.append(ds.pixel_array.astype(int))
    mask = ii128.field_mask(1, None, True)
    edge = ii128.detector.edge(mask, 1)
    inside = acceptance.interior(mask, edge)
    assert np.abs(saved[1][inside] - (255 - saved[0][inside])).max() <= 1
    # Beyond the edge's penumbra the unit blanks the image, in either polarity.
    assert saved[0][edge == 0].max() == 0 and saved[1][edge == 0].max() == 0


def test_the_field_edge_fades_softly_across_the_geometric_edge():
    """The aperture and the blades cast a blurred shadow: across the field's edge the displayed
    grey falls over image.field_edge_mm, with half the inside's grey at the geometric edge and
    rays cast out into the penumbra (the first wave's edge was hard, then half soft: a fade to
    one half, then black). Read on the centre row of a uniform slab at a 256 matrix, collimated
    to 150 mm (the circle meets the frame's border on that row), where the 3 mm fall spans
    about 3 pixels."""
    fl = at_resolution(II, 256, 256)
    r = Renderer(fl, Materials(), device="cpu")
    prepared = r.prepare(acceptance._water_slab(150.0))
    blades = (150.0, 150.0)
    grey = r.render(prepared, acceptance.ap_pose(620.0), View(noise=False, collimation_mm=blades)).image
    mask = r.field_mask(1, blades, True)
    row = 128
    cols = np.flatnonzero(mask[row])
    right = cols[-1]                                    # the last pixel inside the geometric circle
    pitch = fl.detector.pixel_pitch_mm
    fall_px = fl.image.field_edge_mm / pitch
    start = int(np.floor(right - fall_px))
    profile = grey[row, start - 2: right + int(np.ceil(fall_px)) + 3]
    level = float(grey[row, start - 1])                 # just inside the fall
    assert grey[row, right + 1] > 0.05 * level          # rays reach into the penumbra outside the field
    assert np.all(np.diff(profile) <= 0.01 * level)      # it only falls (slab's own fall-off aside)
    assert np.max(-np.diff(profile)) < 0.6 * level       # and over pixels, not at once (a hard edge drops it all)
    # Half the inside's grey where the geometric edge lies (between the last pixel in and the first out).
    at_edge = 0.5 * (grey[row, right] + grey[row, right + 1])
    assert at_edge == pytest.approx(0.5 * level, rel=0.2)
    assert grey[row, right + int(np.ceil(fall_px)) + 2] == 0.0          # black beyond the penumbra


def test_bar_pattern_limiting_resolution_follows_the_profile_and_rises_with_zoom():
    """The shipped TOR 18FG-like case on the input face, at the native 1024 matrix: the finest
    group still modulated 4 % lies within 20 % of the profile's lp/mm at zooms 1 and 4."""
    from appliance.patient.volume_io import load_volume
    from appliance.xray.bar_pattern import bar_pattern_volume

    shipped = load_volume(Path(__file__).resolve().parents[1] / "configs" / "cases" / "bar-pattern.mha")
    drawn = bar_pattern_volume()
    np.testing.assert_array_equal(shipped.hu, drawn.hu)
    np.testing.assert_allclose(shipped.T_ct_from_voxel, drawn.T_ct_from_voxel, atol=1e-9)
    figures = bar_pattern.resolution_per_zoom(II, "cpu", zooms=(1, 4))
    for zoom, measured, stated in figures:
        assert measured == pytest.approx(stated, rel=0.2), zoom
    assert figures[1][1] > 1.5 * figures[0][1]


def test_flat_detector_bar_pattern_at_zoom_4_reads_the_profiles_limiting_resolution():
    """The flat panel's zoom 4 (0.118 mm pixels, Nyquist 4.22 lp/mm): the stated 3.4 lp/mm
    within 20 %, below the matrix's Nyquist frequency. Its finest groups lie 0.045-0.06 rad off
    the axis, where Joseph steps along the pattern's 0.02 mm axis and samples across the
    plate's faces (test_joseph_bone_faces): misread there, they stayed modulated to Nyquist."""
    fd = load_profile(CONFIGS / "generic-flat-detector.yaml", FluoroscopeProfile)
    (zoom, measured, stated), = bar_pattern.resolution_per_zoom(fd, "cpu", zooms=(4,))
    nyquist = 0.5 / (fd.detector.pixel_pitch_mm * fd.zoom_levels[3].fov_mm / fd.zoom_levels[0].fov_mm)
    assert measured == pytest.approx(stated, rel=0.2)
    assert measured < 0.95 * nyquist


def test_bar_groups_the_field_cuts_are_left_out():
    """A row holding each group's fundamental at modulation 0.5 (I = 1 + 0.5 sin), the columns of
    the coarsest group's first half outside the beam (0): that group is not measured, and
    every other reads 0.5."""
    groups = bar_pattern.layout()
    scale = 10.0                                       # columns per mm, the pattern from column 100
    x0 = groups[0][1]
    cols = np.arange(int((groups[-1][2] - x0) * scale) + 200, dtype=float)
    x = x0 + (cols - 100) / scale
    row = np.ones_like(x)
    for f, a, b in groups:
        inside = (x >= a) & (x < b)
        row[inside] = 1.0 + 0.5 * np.sin(2 * np.pi * f * (x[inside] - a))
    row[x < 0.5 * (groups[0][1] + groups[0][2])] = 0.0
    mods = bar_pattern.modulations(row, lambda xm: 100 + (xm - x0) * scale, 1.0, nyquist_lp_per_mm=scale / 2)
    assert mods[0][0] == pytest.approx(groups[1][0])
    measured = [m for f, m in mods if f < 0.8 * scale / 2]     # well below Nyquist: 6 columns a period or more
    assert len(measured) > 10
    np.testing.assert_allclose(measured, 0.5, rtol=0.02)


def test_bar_groups_the_image_ends_cut_are_left_out():
    """The same row of fundamentals, all in the beam, but cut by the image's ends less than a
    column short of a group's fitted points (half a pair in from its ends): group 1's first lies
    half a column before column 0, group 8's last between the last column and the next. Groups 2
    to 7 are measured, each at 0.5, and neither end's group (nor group 0, wholly off the image)."""
    groups = bar_pattern.layout()
    scale = 10.0                                       # columns per mm
    f1, a1, _ = groups[1]
    x_start = a1 + 0.5 / f1 + 0.5 / scale              # column 0: half a column past group 1's first point

    def u_of_x(xm):
        return (xm - x_start) * scale
    assert u_of_x(a1 + 0.5 / f1) == pytest.approx(-0.5)
    f8, _, b8 = groups[8]
    last = u_of_x(b8 - 0.5 / f8)                       # group 8's last fitted point, in columns
    n = int(np.floor(last)) + 1
    assert n - 1 < last < n
    x = x_start + np.arange(n, dtype=float) / scale
    row = np.ones_like(x)
    for f, a, b in groups:
        inside = (x >= a) & (x < b)
        row[inside] = 1.0 + 0.5 * np.sin(2 * np.pi * f * (x[inside] - a))
    mods = bar_pattern.modulations(row, u_of_x, 1.0, nyquist_lp_per_mm=scale / 2)
    np.testing.assert_allclose([f for f, _ in mods], [g[0] for g in groups[2:8]])
    np.testing.assert_allclose([m for _, m in mods], 0.5, rtol=0.02)


def test_window_and_level_keys_reach_the_view():
    """F6 twice: the window 1.25^2 wider; F8: the level a twentieth of the width up; KP8 back to
    the automatic window. The exposure goes on: no dose event, no new run."""
    from appliance.config import KeymapProfile
    from appliance.console.state import Console
    from appliance.daemon.render_worker import view_for
    from drivers.input_event import InputEvent

    keymap = load_profile(Path(__file__).resolve().parents[1] / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
    console = Console(II, keymap, t0=0.0)
    console.handle(InputEvent(0.0, "pedal", "pedal", True))
    events = []
    for t, key in ((1.0, "KEY_F6"), (1.1, "KEY_F6"), (1.2, "KEY_F8")):
        events += console.handle(InputEvent(t, "keypad", key, True))
    state = console.snapshot()
    assert state.window_scale == pytest.approx(1.25 ** 2) and state.level_shift == pytest.approx(0.05)
    assert state.fluoro_on and not [e for e in events if e.kind in ("fluoro_off", "fluoro_on")]

    class Cfg:
        fluoroscope = II
    view = view_for(Cfg, state)
    assert view.window_scale == state.window_scale and view.level_shift == state.level_shift
    console.handle(InputEvent(2.0, "keypad", "KEY_KP8", True))
    assert console.snapshot().window_scale == 1.0 and console.snapshot().level_shift == 0.0


def test_a_frame_rendered_again_at_the_native_matrix_shows_the_same_view(adult):
    """at_matrix: the same prepared volume read out at a finer matrix (what a save stores) shows
    the same anatomy: the fine frame averaged down matches the coarse one."""
    import cv2

    coarse = Renderer(at_resolution(II, 64, 64), Materials(), device="cpu")
    fine = coarse.at_matrix(128, 128)
    assert fine.shape == (128, 128) and fine.dev is coarse.dev
    prepared = coarse.prepare(adult)
    T = acceptance.ap_pose(620.0, (0.0, 0.0, 30.0))
    a = coarse.render(prepared, T, View(noise=False)).image
    b = fine.render(prepared, T, View(noise=False)).image
    mask = coarse.field_mask(1, None, True)
    inside = acceptance.interior(mask, coarse.detector.edge(mask, 1))
    down = cv2.resize(b, (64, 64), interpolation=cv2.INTER_AREA)
    assert np.corrcoef(down[inside], a[inside])[0, 1] > 0.98
    assert coarse.at_matrix(64, 64) is coarse


def test_a_cast_in_bands_of_rows_is_the_whole_cast(adult):
    """A saved image's native re-render on a CPU device is cast in bands of rows so live frames
    run between them: every band of rows must land where the whole cast puts it, to the bit,
    including a last band shorter than the rest (100 rows in bands of 15)."""
    fine = Renderer(at_resolution(II, 96, 100), Materials(), device="cpu")
    prepared = fine.prepare(adult)
    T = acceptance.ap_pose(620.0, (0.0, 0.0, 30.0))
    for quantity in ("intensity", "display"):
        view = View(noise=False, quantity=quantity)
        whole = fine.render(prepared, T, view).image
        banded = fine.render(prepared, T, view, bands=7).image
        assert whole.shape == (100, 96) and np.array_equal(whole, banded), quantity
    # A shutdown cuts a banded cast short between bands: after the third, here.
    asked = []
    with pytest.raises(CastCancelled):
        fine.render(prepared, T, View(noise=False), bands=7, cancelled=lambda: asked.append(1) or len(asked) > 3)
    assert len(asked) == 4
