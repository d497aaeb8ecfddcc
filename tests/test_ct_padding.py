"""CT padding (voxels below the CT scale, outside the reconstruction circle) reads as air,
in the loader and in the renderer, and the abdomen-pelvis CT holds what a scanner writes."""

import cv2
import numpy as np
import pytest
import SimpleITK as sitk

from appliance.config.case import Materials
from appliance.geometry import make_transform
from appliance.patient import adult_pelvis
from appliance.patient.volume import Volume
from appliance.patient.volume_io import load_volume
from appliance.xray.bench import flat_profile
from appliance.xray.renderer import Renderer, View, zoomed_K
from appliance.xray.truth.analytic import box_chords, box_volume, pixel_rays_ct

SIZE = 96
POSE = make_transform(np.eye(3), [0.0, 0.0, 750.0])


def test_the_loader_reads_padding_as_air_and_keeps_the_ct_scale(tmp_path):
    arr = np.array([-3024, -2000, -1025, -1024, -1000, 0, 1000, 3071], np.int16).reshape(2, 2, 2)
    path = tmp_path / "padded.mha"
    sitk.WriteImage(sitk.GetImageFromArray(arr), str(path))
    got = load_volume(path, hu_checked=False).hu
    np.testing.assert_array_equal(got.ravel(), [-1000, -1000, -1000, -1024, -1000, 0, 1000, 3071])


@pytest.mark.parametrize("padding_hu", [-3024, -2000])
def test_a_water_box_in_padding_projects_its_closed_form_chords(padding_hu):
    """A 0 HU box (1 g/cm^3) whose surroundings are padding: every ray's soft-tissue density
    integral is its chord through the box, and at the box's side faces, where samples blend
    it with what lies beside it, each ray reads what it reads with air beside it: -3024 HU
    blended in as a density of -2 g/cm^3 would cancel half a voxel of water."""
    vol, lo, hi = box_volume((24, 40, 40), (2.0, 2.0, 2.0), (8, 8, 4), (31, 31, 19))
    padded = vol.hu.copy()
    padded[padded == -1000] = padding_hu
    fl = flat_profile(SIZE)
    renderer = Renderer(fl, Materials(), device="cpu")
    view = View(zoom=1)
    in_air = renderer.material_integrals(renderer.prepare(vol), POSE, view, distorted=False, circle=False)
    in_padding = renderer.material_integrals(
        renderer.prepare(Volume(hu=padded, T_ct_from_voxel=vol.T_ct_from_voxel, source="padded box")),
        POSE, view, distorted=False, circle=False)
    assert in_padding.min() >= 0.0
    np.testing.assert_allclose(in_padding, in_air, atol=1e-4)
    s, d = pixel_rays_ct(zoomed_K(fl, 1), POSE, SIZE, SIZE)
    chords = box_chords(s, d, lo, hi)
    # Rays in through the front face and out through the back (32 mm of water or more),
    # two pixels clear of the side faces (g/cm^3 x mm = 1 x chord).
    through = cv2.erode((chords >= 32.0 - 1e-6).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert through.sum() > 100
    np.testing.assert_allclose(in_padding[..., 1][through], chords[through], rtol=2e-3)


def test_the_couch_lies_under_the_patient_on_the_clinical_grid():
    """Three 0.8 mm slices: the 3 mm carbon shell is resolved there, not on the small grid."""
    hu, spacing, origin = adult_pelvis.build_adult_pelvis((3, 512, 512), (0.8, 0.8, 0.8), ct_noise=False)
    y = origin[1] + spacing[1] * np.arange(512)
    mid = hu[1, :, 256]
    behind = y > adult_pelvis.BACK_Y
    # Skin and fat down to the back, then shell, foam core, shell, then air.
    assert np.median(mid[(y > adult_pelvis.BACK_Y - 20) & (y < adult_pelvis.BACK_Y - 5)]) == pytest.approx(-100, abs=10)
    assert mid[behind].max() == pytest.approx(adult_pelvis.HU_TABLE_SHELL, abs=10)
    core = behind & (y < adult_pelvis.BACK_Y + 1 + adult_pelvis.TABLE_CORE_MM)
    assert np.median(mid[core]) == pytest.approx(adult_pelvis.HU_TABLE_CORE, abs=10)
    assert np.all(mid[y > adult_pelvis.BACK_Y + 60] == -1000)


def test_the_abdomen_pelvis_ct_holds_padding_couch_gas_fat_and_bone():
    hu, spacing, origin = adult_pelvis.build_adult_pelvis(*adult_pelvis.SIZES["small"], ct_noise=False)
    nz, ny, nx = hu.shape
    y = origin[1] + spacing[1] * np.arange(ny)
    x = origin[0] + spacing[2] * np.arange(nx)
    r = np.hypot(*np.meshgrid(y, x, indexing="ij"))
    radius = min(nx * spacing[2], ny * spacing[1]) / 2
    # Outside the reconstruction circle, padding; inside, the CT scale only.
    assert np.all(hu[:, r > radius + 1e-3] == adult_pelvis.HU_PADDING)
    assert hu[:, r < radius - 1e-3].min() >= -1024
    # The arms beside the body are cut by the circle: tissue on the last voxels inside it.
    edge = (r < radius) & (r > radius - 2 * spacing[2]) & (np.abs(y)[:, None] < 20)
    assert np.median(hu[nz // 2][edge]) > -200
    # Bowel gas, subcutaneous and intra-abdominal fat, and dense bone all present.
    body = hu[:, (np.abs(y)[:, None] < 90) & (np.abs(x)[None, :] < 130)]     # inside the trunk, 352 x 236 mm at its narrowest
    assert np.mean(body < -900) > 0.002
    assert np.mean(np.abs(body + 100) < 15) > 0.10
    assert np.mean(body > 700) > 0.002
