"""Where the renderer puts things, on a machine whose camera matrix is anything but symmetric.

Every shipped profile has fx = fy, a square matrix and a centred principal point, so a swapped
fx/fy, a transposed matrix or a principal point read as the centre would pass on them. This
profile has fx != fy, 160 x 120 pixels and an off-centre principal point; the truth is the
pinhole projection with a camera matrix written out by hand from the profile's numbers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from in_process_cli import fluorosim
from ruamel.yaml import YAML

from appliance.config.case import Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.patient.volume import Volume
from appliance.xray.renderer import Renderer

REPO = Path(__file__).resolve().parents[1]
FX, FY, CX, CY = 600.0, 450.0, 70.25, 64.75
COLUMNS, ROWS = 160, 120
FOV_MM = (300.0, 220.0, 160.0, 120.0)          # the flat-detector profile's zoom fields
SOD_MM = 750.0                                 # its source-to-isocentre distance


def hand_K(zoom: int) -> np.ndarray:
    """A zoom level narrows the field: both focal lengths grow by fov(1)/fov(zoom) about the
    principal point, which stays where the detector has it."""
    s = FOV_MM[0] / FOV_MM[zoom - 1]
    return np.array([[FX * s, 0.0, CX], [0.0, FY * s, CY], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def profile_path(tmp_path_factory) -> Path:
    data = YAML(typ="safe").load((REPO / "configs/fluoroscopes/generic-flat-detector.yaml").read_text())
    data["detector"].update(columns=COLUMNS, rows=ROWS, pixel_pitch_mm=1.9)
    data["intrinsics"].update(fx=FX, fy=FY, cx=CX, cy=CY)
    path = tmp_path_factory.mktemp("anisotropic") / "anisotropic.yaml"
    path.write_text(json.dumps(data, indent=1))        # JSON is YAML
    return path


@pytest.fixture(scope="module")
def renderer(profile_path) -> Renderer:
    return Renderer(load_profile(profile_path, FluoroscopeProfile), Materials(), device="cpu")


def bead_volume(centres_mm: list[tuple[float, float, float]], sigma_mm: float = 1.2) -> Volume:
    """Air with Gaussian beads at `centres_mm` (ct frame = xray frame shifted to the isocentre),
    0.2 mm voxels. A smooth bead, unlike a cube, has a shadow whose centroid over pixel-centre
    samples is the projection of its centre; voxels finer than a pixel at the isocentre at
    every zoom (0.5 mm at zoom 4) and incommensurate with it keep the voxelisation from
    biasing the samples (at 0.5 mm voxels, zoom 4 samples one voxel column a pixel and the
    centroid snaps to a voxel centre)."""
    sp = 0.2
    c = np.asarray(centres_mm, float)
    lo = np.floor(c.min(axis=0) - 5 * sigma_mm) + 0.1       # the beads and their tails, nothing more
    nx, ny, nz = (np.ceil((c.max(axis=0) + 5 * sigma_mm - lo) / sp).astype(int) + 1)
    x = lo[0] + sp * np.arange(nx)
    y = lo[1] + sp * np.arange(ny)
    z = lo[2] + sp * np.arange(nz)
    density = np.zeros((nz, ny, nx))
    for cx, cy, cz in centres_mm:
        gx = np.exp(-((x - cx) ** 2) / (2 * sigma_mm**2))
        gy = np.exp(-((y - cy) ** 2) / (2 * sigma_mm**2))
        gz = np.exp(-((z - cz) ** 2) / (2 * sigma_mm**2))
        density += gz[:, None, None] * gy[None, :, None] * gx[None, None, :]
    hu = np.rint(-1000 + 3000 * np.clip(density, 0, 1)).astype(np.int16)
    T = np.eye(4)
    T[:3, :3] *= sp
    T[:3, 3] = lo
    return Volume(hu=hu, T_ct_from_voxel=T, source="beads")


def centroid_near(image: np.ndarray, u: float, v: float, r: int = 9) -> tuple[float, float]:
    u0, v0 = int(round(u)), int(round(v))
    win = image[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1].astype(np.float64)
    vv, uu = np.mgrid[v0 - r:v0 + r + 1, u0 - r:u0 + r + 1]
    return float((win * uu).sum() / win.sum()), float((win * vv).sum() / win.sum())


@pytest.mark.parametrize("zoom,offsets", [(1, [(-30.0, -20.0), (28.0, 18.0), (25.0, -15.0)]),
                                          (4, [(-22.0, -16.0), (20.0, 15.0)])])
def test_beads_land_where_the_hand_built_camera_matrix_puts_them(renderer, zoom, offsets):
    assert renderer.shape == (ROWS, COLUMNS)
    centres = [(x, y, 0.0) for x, y in offsets]
    prepared = renderer.prepare(bead_volume(centres))
    T_xray_from_ct = np.eye(4)
    T_xray_from_ct[2, 3] = SOD_MM
    image = renderer.line_integral(prepared, T_xray_from_ct, zoom=zoom)
    K = hand_K(zoom)
    for x, y, z in centres:
        u, v, w = K @ np.array([x, y, z + SOD_MM])
        u, v = u / w, v / w
        assert 10 <= u <= COLUMNS - 11 and 10 <= v <= ROWS - 11, "the test's beads lie inside the matrix"
        got_u, got_v = centroid_near(image, u, v)
        assert abs(got_u - u) < 0.1 and abs(got_v - v) < 0.1, (zoom, (x, y), (got_u, got_v), (u, v))


def test_render_command_zoom_magnifies_about_the_principal_point(profile_path, tmp_path):
    """`fluorosim render` at zoom 1 and 3: one bead off the axis moves away from the principal
    point by fov(1)/fov(3) along both axes, each with its own focal length."""
    import SimpleITK as sitk

    bead = (40.0, -30.0, 0.0)
    volume = bead_volume([bead])
    image = sitk.GetImageFromArray(volume.hu)
    image.SetSpacing([float(s) for s in volume.spacing_mm])
    image.SetOrigin([float(o) for o in volume.T_ct_from_voxel[:3, 3]])
    ct = tmp_path / "bead.mha"
    sitk.WriteImage(image, str(ct))
    pose = tmp_path / "pose.yaml"
    pose.write_text(json.dumps({"T_xray_from_ct": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, SOD_MM], [0, 0, 0, 1]]}))
    found = {}
    for zoom in (1, 3):
        out = tmp_path / f"zoom{zoom}.npy"
        result = fluorosim("render", "--fluoroscope", profile_path, "--volume", ct, "--pose", pose, "--zoom", zoom,
                           "--quantity", "line-integral", "--output", out, cwd=REPO)
        assert result.returncode == 0, result.stderr
        image = np.load(out)
        assert image.shape == (ROWS, COLUMNS)
        u, v, w = hand_K(zoom) @ np.array([bead[0], bead[1], bead[2] + SOD_MM])
        found[zoom] = centroid_near(image, u / w, v / w)
        assert abs(found[zoom][0] - u / w) < 0.1 and abs(found[zoom][1] - v / w) < 0.1, (zoom, found[zoom])
    s = FOV_MM[0] / FOV_MM[2]
    assert (found[3][0] - CX) / (found[1][0] - CX) == pytest.approx(s, rel=0.01)
    assert (found[3][1] - CY) / (found[1][1] - CY) == pytest.approx(s, rel=0.01)
