"""Joseph's samples of voxels larger than the display pixel (fluoroscope `ct_sampling`), against
the closed-form line integrals of a box on a coarse anisotropic grid.

The box fills whole voxels (its faces on voxel faces), so the voxel grid is exactly the box
and its exact line integral is each ray's chord through it (`truth.analytic.box_chords`). The
grid's slices are 5 mm thick and the view is at zoom 4, about 0.49 mm per pixel at the
isocentre: a slice spans some ten pixels, as a clinical CT's 2.5 mm slices do on the 256 matrix.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_image_chain import CONFIGS

from appliance.config.case import Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.geometry import make_transform
from appliance.xray import acceptance, bar_pattern
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer, View, at_resolution, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

SIZE = 128
ZOOM = 4
#: 48 x 48 voxels of 1 mm across the beam's x, 10 slices of 5 mm (z); the box fills voxels
#: 9..38 in x and y (30 mm) and slices 2..7 (30 mm): faces at +-15 mm in each direction.
SHAPE_ZYX, SPACING_XYZ = (10, 48, 48), (1.0, 1.0, 5.0)
LO, HI = (9, 9, 2), (38, 38, 7)


def _profile(edge_px: float | None) -> FluoroscopeProfile:
    ii = load_profile(CONFIGS / "generic-ii-carm.yaml", FluoroscopeProfile)
    fl = bar_pattern.undistorted(at_resolution(ii, SIZE, SIZE))
    return fl.model_copy(update={"ct_sampling": fl.ct_sampling.model_copy(update={"voxel_edge_px": edge_px})})


@pytest.fixture(scope="module")
def scene():
    vol, lo, hi = box_volume(SHAPE_ZYX, SPACING_XYZ, LO, HI)
    fl = _profile(1.0)
    T = acceptance.ap_pose(fl.geometry.source_to_isocentre_mm)
    s, d = pixel_rays_ct(zoomed_K(fl, ZOOM), T, SIZE, SIZE)
    return vol, T, box_chords(s, d, lo, hi)


def _cast(vol, T, edge_px: float | None, packet: bool | None = None) -> np.ndarray:
    """Water-equivalent path (mm) through the box along each pixel's ray: HU 0 is 1 g/cm^3."""
    renderer = Renderer(_profile(edge_px), Materials(), device="cpu", packet=packet)
    prepared = renderer.prepare(vol)
    return renderer.material_integrals(prepared, T, View(zoom=ZOOM), distorted=False, circle=False).sum(-1)


def _ramp_rows(column: np.ndarray, plateau: float) -> int:
    """Pixels of a profile between 5 % and 95 % of the plateau: the width of its two edges."""
    return int(np.count_nonzero((column > 0.05 * plateau) & (column < 0.95 * plateau)))


def test_a_thick_slice_keeps_its_face_as_the_exact_integral_does(scene):
    vol, T, truth = scene
    plateau = float(truth.max())
    assert 29.9 < plateau < 30.5                     # the 30 mm box, rays near the axis
    col = SIZE // 2                                  # the image's rows cross the slices' faces
    exact = _ramp_rows(truth[:, col], plateau)       # the rays' divergence: a pixel or so per face
    sampled = _ramp_rows(_cast(vol, T, 1.0)[:, col], plateau)
    linear = _ramp_rows(_cast(vol, T, None)[:, col], plateau)
    # Footprint sampling: each face within about a pixel of the truth's; linear interpolation
    # ramps each 5 mm face over its whole slice (5 / 0.49 ~ 10 px, 90 % of it between 5 and 95 %).
    assert sampled <= exact + 2
    assert linear >= exact + 12


def test_the_box_reads_its_chords_away_from_its_faces(scene):
    import cv2

    vol, T, truth = scene
    plateau = float(truth.max())
    # Pixels whose 5 x 5 neighbourhood of exact chords is flat to 0.2 % of the plateau: two
    # pixels or more from every face's image.
    kernel = np.ones((5, 5), np.uint8)
    spread = cv2.dilate(truth.astype(np.float32), kernel) - cv2.erode(truth.astype(np.float32), kernel)
    flat = spread < 0.002 * plateau
    inside, outside = flat & (truth > 0.5 * plateau), flat & (truth < 0.5 * plateau)
    assert inside.sum() > 1500 and outside.sum() > 1500
    lines = _cast(vol, T, 1.0)
    assert np.max(np.abs(lines[inside] - truth[inside])) < 0.005 * plateau
    assert np.max(np.abs(lines[outside])) < 1e-4 * plateau
    # Linear interpolation misses those pixels by a slice's ramp (up to half the plateau).
    assert np.max(np.abs(_cast(vol, T, None)[inside] - truth[inside])) > 0.1 * plateau


def test_the_edge_width_is_the_profiles(scene):
    vol, T, truth = scene
    plateau = float(truth.max())
    col = SIZE // 2
    # A box filter e px wide puts 90 % of a step (0.9 e px) between 5 and 95 %: two faces take
    # about 1.8 e pixels once e is wider than the rays' own divergence across the box.
    for edge_px in (4.0, 8.0):
        wide = _ramp_rows(_cast(vol, T, edge_px)[:, col], plateau)
        assert abs(wide - 1.8 * edge_px) <= 2.0, (edge_px, wide)


def test_the_scalar_kernel_samples_as_the_packet_kernel(scene):
    vol, T, _ = scene
    packet, scalar = _cast(vol, T, 1.0, packet=True), _cast(vol, T, 1.0, packet=False)
    np.testing.assert_allclose(scalar, packet, rtol=1e-5, atol=1e-4)


def test_voxels_smaller_than_the_pixel_are_interpolated_linearly():
    # 0.25 mm voxels at zoom 1 (1.1 mm per pixel at the isocentre): the footprint spans
    # several voxels, so sampling is exactly Joseph's linear interpolation.
    vol, _, _ = box_volume((40, 40, 40), (0.25, 0.25, 0.25), (8, 8, 8), (31, 31, 31))
    fl = _profile(1.0)
    T = acceptance.ap_pose(fl.geometry.source_to_isocentre_mm)
    out = []
    for edge in (1.0, None):
        renderer = Renderer(_profile(edge), Materials(), device="cpu")
        out.append(renderer.material_integrals(renderer.prepare(vol), T, View(zoom=1), distorted=False, circle=False))
    assert out[0].sum() > 0
    np.testing.assert_array_equal(out[0], out[1])


def test_a_ray_steep_to_thick_voxels_integrates_its_whole_step():
    # 50 mm slices along the beam, 6 mm voxels across: the field's outer rays step along x in
    # the grid's index space, each step a 50 mm stretch of ray, and cross the slab's faces
    # inside one step; the sample's weight spans that crossing, so the slab reads its exact
    # chord (the scalar kernel, each ray its own dominant axis) instead of 50 mm in or out.
    vol, lo, hi = box_volume((8, 64, 64), (6.0, 6.0, 50.0), (0, 0, 0), (63, 63, 7))
    fl = flat_profile(64)
    T = make_transform(np.eye(3), [0.0, 0.0, 750.0])          # the beam along the slab's 400 mm
    s, d = pixel_rays_ct(zoomed_K(fl, 1), T, 64, 64)
    truth = box_chords(s, d, lo, hi)
    renderer = Renderer(fl, Materials(), device="cpu", packet=False)
    lines = renderer.material_integrals(renderer.prepare(vol), T, View(), distorted=False, circle=False).sum(-1)
    assert truth.max() > 390
    assert np.max(np.abs(lines - truth)) < 0.01 * truth.max()


@pytest.mark.parametrize("value", ["0", "-1.0", "100", "'wide'"])
def test_a_bad_edge_width_is_one_line_naming_the_field(tmp_path, value):
    from appliance.config import ProfileProblems

    text = (CONFIGS / "generic-ii-carm.yaml").read_text()
    assert "  voxel_edge_px: 4.0" in text
    path = tmp_path / "fluoroscopes" / "f.yaml"
    path.parent.mkdir()
    path.write_text(text.replace("  voxel_edge_px: 4.0", f"  voxel_edge_px: {value}", 1))
    with pytest.raises(ProfileProblems) as e:
        load_profile(path, FluoroscopeProfile)
    (problem,) = e.value.problems
    assert "\n" not in str(problem) and str(problem).startswith(str(path)) and "ct_sampling.voxel_edge_px" in str(problem)
