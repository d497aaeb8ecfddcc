"""`fluorosim case inspect` and `case place`: a CT's frame read right, and a placed target
imaged at the centre of the detector along the demo path's geometry."""

import re
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
import SimpleITK as sitk

from appliance.cli import main
from appliance.config.appliance import ApplianceProfile
from appliance.config.case import CaseProfile
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile, resolve
from appliance.patient.volume_io import load_volume
from appliance.tracking.trajectory import load_trajectory
from appliance.xray.renderer import Renderer, at_resolution

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def write_nifti_ras(path: Path, hu: np.ndarray, srow: np.ndarray) -> None:
    """A NIfTI-1 file written byte by byte (no imaging library): int16 voxels, shape
    (nz, ny, nx), and an sform giving RAS mm = srow @ (i, j, k, 1) as the standard defines."""
    nz, ny, nx = hu.shape
    header = bytearray(352)
    struct.pack_into("<i", header, 0, 348)
    struct.pack_into("<8h", header, 40, 3, nx, ny, nz, 1, 1, 1, 1)
    struct.pack_into("<hh", header, 70, 4, 16)                          # NIFTI_TYPE_INT16, 16 bits
    spacing = np.linalg.norm(srow[:, :3], axis=0)
    struct.pack_into("<8f", header, 76, 1.0, *spacing, 0, 0, 0, 0)
    struct.pack_into("<fff", header, 108, 352.0, 1.0, 0.0)              # vox_offset, scl_slope, scl_inter
    struct.pack_into("<B", header, 123, 2)                               # xyzt_units: mm
    struct.pack_into("<hh", header, 252, 0, 1)                          # qform_code 0, sform_code 1 (scanner)
    struct.pack_into("<12f", header, 280, *srow.reshape(-1))
    header[344:348] = b"n+1\0"
    path.write_bytes(bytes(header) + hu.astype("<i2").tobytes())


def bounds_printed(out: str) -> np.ndarray:
    rows = re.findall(r"^\s+[xyz] \(.*?\)\s+(-?\d+\.\d+) to\s+(-?\d+\.\d+)", out, re.M)
    return np.array(rows, float)


def test_inspect_reports_a_nifti_in_lps_not_the_ras_its_header_gives(tmp_path, capsys):
    nz, ny, nx = 10, 30, 20
    hu = np.full((nz, ny, nx), -1000, np.int16)
    hu[2:8, 5:25, 4:16] = 40
    hu[4:6, 10:14, 8:10] = 900
    srow = np.array([[2.0, 0, 0, -100.0], [0, 1.5, 0, -60.0], [0, 0, 3.0, -30.0]])
    path = tmp_path / "ras.nii"
    write_nifti_ras(path, hu, srow)
    assert main(["case", "inspect", str(path), "--at", "84,42,-15"]) == 0
    out = capsys.readouterr().out
    # RAS of the voxel-centre corners from the sform; LPS negates x and y.
    corners = np.array([[i, j, k, 1] for i in (0, nx - 1) for j in (0, ny - 1) for k in (0, nz - 1)], float)
    lps = (srow @ corners.T).T * [-1, -1, 1]
    np.testing.assert_allclose(bounds_printed(out), np.stack([lps.min(0), lps.max(0)], axis=1), atol=0.05)
    assert "i, j, k increase toward R, A, S" in out
    # LPS (84, 42, -15) is RAS (-84, -42, -15): voxel ((-84 + 100) / 2, (-42 + 60) / 1.5, (-15 + 30) / 3).
    assert "at (84.0, 42.0, -15.0) mm: 900 HU (voxel (8, 12, 5))" in out
    assert "looks like a CT in HU: yes" in out


def test_inspect_value_at_a_point_and_refuses_raw_scanner_values(tmp_path, capsys):
    hu = np.full((12, 16, 16), -1000, np.int16)
    hu[3:9, 3:13, 3:13] = 40
    hu[5, 7, 9] = 1234
    image = sitk.GetImageFromArray(hu)
    image.SetSpacing((1.0, 2.0, 2.5))
    image.SetOrigin((-10.0, 20.0, 300.0))
    path = tmp_path / "ct.mha"
    sitk.WriteImage(image, str(path))
    # Voxel (i 9, j 7, k 5) lies at LPS (-10 + 9, 20 + 14, 300 + 12.5).
    assert main(["case", "inspect", str(path), "--at=-1,34,312.5"]) == 0
    out = capsys.readouterr().out
    assert "at (-1.0, 34.0, 312.5) mm: 1234 HU (voxel (9, 7, 5))" in out
    np.testing.assert_allclose(bounds_printed(out), [[-10, 5], [20, 50], [300, 327.5]])
    raw = sitk.GetImageFromArray((hu.astype(np.int32) + 1024).astype(np.int16))
    sitk.WriteImage(raw, str(tmp_path / "raw.mha"))
    assert main(["case", "inspect", str(tmp_path / "raw.mha")]) == 0
    assert "looks like a CT in HU: no" in capsys.readouterr().out


def test_inspect_a_missing_ct_is_one_line(tmp_path, capsys):
    assert main(["case", "inspect", str(tmp_path / "none.nii.gz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such file" in err[0]


TARGET = np.array([37.0, -12.0, -210.0])        # LPS mm
OFFSET_MM = 40.0


@pytest.fixture(scope="module")
def ball_ct(tmp_path_factory):
    """Air with three steel-dense balls: at TARGET, 40 mm to the patient's left of it and
    40 mm superior to it; stored RAS-wise (direction diag(-1, -1, 1)) with an odd origin."""
    spacing, n = 1.5, 96
    direction = np.diag([-1.0, -1.0, 1.0])
    origin = TARGET + direction @ np.full(3, -0.5 * spacing * (n - 1)) + np.array([6.0, -4.0, 10.0])
    k, j, i = np.mgrid[0:n, 0:n, 0:n]
    xyz = np.stack([i, j, k], -1) * spacing @ direction.T + origin
    hu = np.full((n, n, n), -1000, np.int16)
    for centre in (TARGET, TARGET + [OFFSET_MM, 0, 0], TARGET + [0, 0, OFFSET_MM]):
        hu[np.linalg.norm(xyz - centre, axis=-1) <= 5.0] = 3000
    image = sitk.GetImageFromArray(hu)
    image.SetSpacing((spacing,) * 3)
    image.SetOrigin(tuple(origin))
    image.SetDirection(tuple(direction.reshape(-1)))
    path = tmp_path_factory.mktemp("ct") / "balls.nii.gz"
    sitk.WriteImage(image, str(path))
    return path


def shadows(fluoroscope, case_path: Path):
    """Centroids (u, v) of the balls' shadows in a 128 x 128 line-integral render of the case
    at the demo path's home pose, and the principal point of that matrix."""
    demo = load_profile(CONFIGS / "appliance-demo.yaml", ApplianceProfile)
    home = load_trajectory(resolve(CONFIGS / "appliance-demo.yaml", demo.devices.camera.trajectory))(0.0)
    case = load_profile(case_path, CaseProfile)
    T_xray_from_ct = fluoroscope.T_xray_from_webcam() @ home @ np.asarray(case.T_phantom_from_ct)
    small = at_resolution(fluoroscope, 128, 128)
    renderer = Renderer(small, case.materials, device="cpu")
    image = renderer.line_integral(renderer.prepare(load_volume(resolve(case_path, case.phases[0].volume))), T_xray_from_ct)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats((image > 0.05 * image.max()).astype(np.uint8))
    weights = [(image * (labels == c)).sum() for c in range(1, n)]
    uv = [((image * (labels == c) * np.arange(128)[None]).sum() / w, (image * (labels == c) * np.arange(128)[:, None]).sum() / w)
          for c, w in zip(range(1, n), weights)]
    return np.array(uv), np.array([small.intrinsics.cx, small.intrinsics.cy])


def test_placed_target_images_at_the_detector_centre_pa(ball_ct, tmp_path, capsys):
    out = tmp_path / "cases" / "own.yaml"
    out.parent.mkdir()
    assert main(["case", "place", str(ball_ct), "--target=" + ",".join(f"{v:g}" for v in TARGET), "--out", str(out)]) == 0
    assert main(["validate", str(out)]) == 0
    assert (tmp_path / "cases" / "own-preview.png").is_file()
    fluoroscope = load_profile(CONFIGS / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    uv, centre = shadows(fluoroscope, out)
    assert len(uv) == 3
    d = np.linalg.norm(uv - centre, axis=1)
    assert d.min() < 0.3                                     # the target at the principal point
    # PA, supine, head along the box: the superior ball lies toward +u (phantom +x is xray +x
    # at home), the left ball across the image; both at 40 mm x SID/SOD magnification.
    pitch = 0.225 * 1024 / 128
    expected_px = OFFSET_MM * 1000 / 620 / pitch
    others = uv[np.argsort(d)[1:]]
    superior = others[np.argmax(others[:, 0])]
    left = others[np.argmin(others[:, 0])]
    assert superior[0] - centre[0] == pytest.approx(expected_px, rel=0.05)
    assert abs(superior[1] - centre[1]) < 0.5
    assert abs(left[0] - centre[0]) < 0.5 and abs(left[1] - centre[1]) == pytest.approx(expected_px, rel=0.05)
    capsys.readouterr()


def test_lateral_puts_the_left_ball_behind_the_target(ball_ct, tmp_path):
    out = tmp_path / "lat.yaml"
    assert main(["case", "place", str(ball_ct), "--target", ",".join(f"{v:g}" for v in TARGET), "--beam", "LAT",
                 "--out", str(out)]) == 0
    fluoroscope = load_profile(CONFIGS / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    uv, centre = shadows(fluoroscope, out)
    # Target and left ball on one ray: two shadows, the merged one at the centre.
    assert len(uv) == 2
    assert np.linalg.norm(uv - centre, axis=1).min() < 0.3


def test_place_refuses_a_target_outside_the_ct(ball_ct, tmp_path, capsys):
    assert main(["case", "place", str(ball_ct), "--target=900,0,0", "--out", str(tmp_path / "x.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "outside" in err[0] and "case inspect" in err[0]
    assert not (tmp_path / "x.yaml").exists()
    assert main(["case", "place", str(ball_ct), "--target=1,2", "--out", str(tmp_path / "x.yaml")]) == 2
    assert "three numbers" in capsys.readouterr().err
