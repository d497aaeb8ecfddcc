"""The renderer's geometry worked by hand on an anisotropic machine: the camera matrix at a zoom,
the matrix read out at another size, each pixel's ray, the intensifier's circle, the blades'
mask and the exposure control's measuring field.

The machine: 160 x 120 pixels of 1.9 mm, fx 600 != fy 450, principal point (70.25, 64.75),
zoom fields 300 / 220 / 160 / 120 mm. Every expected number below is written out from those
figures; the distorted rays are checked with OpenCV's own forward model (projectPoints)."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from ruamel.yaml import YAML

from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.errors import FluorosimError
from appliance.xray.pixel_geometry import (
    at_resolution,
    field_mask,
    field_radius_px,
    measuring_field,
    pixel_pitch_at_zoom_mm,
    ray_directions,
    zoomed_K,
)

REPO = Path(__file__).resolve().parents[1]
FX, FY, CX, CY = 600.0, 450.0, 70.25, 64.75
COLUMNS, ROWS, PITCH = 160, 120, 1.9
FOV_MM = (300.0, 220.0, 160.0, 120.0)
DIST = (-0.12, 0.03, 0.004, -0.003, 0.01)      # a pincushion with a tangential part, every coefficient set


def machine(tmp_path: Path, dist=(0.0,) * 5, detector=(COLUMNS, ROWS, PITCH)) -> FluoroscopeProfile:
    data = YAML(typ="safe").load((REPO / "configs/fluoroscopes/generic-flat-detector.yaml").read_text())
    data["detector"].update(dict(zip(("columns", "rows", "pixel_pitch_mm"), detector)))
    data["intrinsics"].update(fx=FX, fy=FY, cx=CX, cy=CY, distortion=dict(zip(("k1", "k2", "p1", "p2", "k3"), dist)))
    assert [z["fov_mm"] for z in data["zoom_levels"]] == list(FOV_MM)
    path = tmp_path / "anisotropic.yaml"
    path.write_text(json.dumps(data))
    return load_profile(path, FluoroscopeProfile)


def reprojection_error_px(rays: np.ndarray, K: np.ndarray, dist) -> float:
    """Largest distance (px) from each pixel centre of OpenCV's forward model of its ray."""
    rows, cols = rays.shape[:2]
    pts = np.concatenate([rays.reshape(-1, 2).astype(np.float64), np.ones((rows * cols, 1))], axis=1)
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, np.asarray(dist, dtype=np.float64))
    u, v = np.meshgrid(np.arange(cols), np.arange(rows))
    return float(np.hypot(uv[:, 0, 0] - u.ravel(), uv[:, 0, 1] - v.ravel()).max())


def test_camera_matrix_at_each_zoom_and_refusal_outside_the_levels(tmp_path):
    fl = machine(tmp_path)
    for zoom, s in ((1, 1.0), (2, 300 / 220), (3, 300 / 160), (4, 2.5)):
        np.testing.assert_allclose(zoomed_K(fl, zoom), [[FX * s, 0, CX], [0, FY * s, CY], [0, 0, 1]], rtol=1e-12)
    np.testing.assert_array_equal(fl.intrinsics.K(), [[FX, 0, CX], [0, FY, CY], [0, 0, 1]])   # the profile's own, untouched
    for zoom in (0, 5):
        with pytest.raises(FluorosimError, match=f"zoom {zoom} is not one of the fluoroscope's levels 1..4"):
            zoomed_K(fl, zoom)


def test_pixel_pitch_and_circle_at_the_input_plane(tmp_path):
    fl = machine(tmp_path)
    assert [pixel_pitch_at_zoom_mm(fl, z) for z in (1, 2, 3, 4)] == pytest.approx(
        [1.9, 1.9 * 220 / 300, 1.9 * 160 / 300, 1.9 * 120 / 300], rel=1e-12)
    assert field_radius_px(fl) == pytest.approx(300 / 1.9 / 2, rel=1e-12)     # the same circle at every zoom


def test_the_same_machine_read_out_at_half_the_matrix(tmp_path):
    half = at_resolution(machine(tmp_path), 80, 60)
    i, d = half.intrinsics, half.detector
    assert (d.columns, d.rows) == (80, 60) and d.pixel_pitch_mm == pytest.approx(3.8, rel=1e-12)
    # Focal lengths halve; the principal point keeps its place on the detector: pixel centres sit
    # at integers, so a position p in the full matrix is (p + 0.5) / 2 - 0.5 in the half one.
    assert (i.fx, i.fy) == pytest.approx((300.0, 225.0), rel=1e-12)
    assert (i.cx, i.cy) == pytest.approx((34.875, 32.125), rel=1e-12)
    wide = at_resolution(machine(tmp_path), 320, 180)       # unequal factors: 2 along columns, 1.5 along rows
    assert (wide.intrinsics.fx, wide.intrinsics.fy) == pytest.approx((1200.0, 675.0), rel=1e-12)
    assert (wide.intrinsics.cx, wide.intrinsics.cy) == pytest.approx((141.0, 97.375), rel=1e-12)
    assert wide.detector.pixel_pitch_mm == pytest.approx(0.95, rel=1e-12)


@pytest.mark.parametrize("zoom", [1, 3])
def test_pinhole_rays_through_each_pixel_centre(tmp_path, zoom):
    fl = machine(tmp_path, DIST)
    s = FOV_MM[0] / FOV_MM[zoom - 1]
    rays = ray_directions(fl, zoom, False)       # the profile's distortion left out
    assert rays.shape == (ROWS, COLUMNS, 2) and rays.dtype == np.float32
    for v, u in ((0, 0), (0, 159), (119, 0), (119, 159), (64, 70), (7, 133)):
        assert rays[v, u, 0] == pytest.approx((u - CX) / (FX * s), abs=1e-6)
        assert rays[v, u, 1] == pytest.approx((v - CY) / (FY * s), abs=1e-6)
    # No distortion in the profile: the distorted rays are the pinhole's.
    plain = machine(tmp_path)
    np.testing.assert_array_equal(ray_directions(plain, zoom, True), ray_directions(plain, zoom, False))


@pytest.mark.parametrize("zoom", [1, 4])
def test_distorted_rays_are_where_opencv_projects_each_pixel_from(tmp_path, zoom):
    fl = machine(tmp_path, DIST)
    K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
    K[0, 0] *= FOV_MM[0] / FOV_MM[zoom - 1]
    K[1, 1] *= FOV_MM[0] / FOV_MM[zoom - 1]
    rays = ray_directions(fl, zoom, True).astype(np.float64)
    assert reprojection_error_px(rays, K, DIST) < 1e-3
    # The distortion is really applied: at zoom 1 the corner rays differ from the pinhole's.
    pinhole = ray_directions(fl, zoom, False).astype(np.float64)
    if zoom == 1:
        assert np.abs(rays[0, 0] - pinhole[0, 0]).max() * K[0, 0] > 0.2


def test_rays_through_a_strong_barrel_still_reproject_onto_their_pixels(tmp_path):
    # Twelve times the distortion above (k1 -1.44): OpenCV's default five iterations of
    # undistortPoints leave corner rays 0.01 px off; the fifty the renderer asks for reach 1e-5.
    strong = tuple(12 * c for c in DIST)
    fl = machine(tmp_path, strong)
    K = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
    assert reprojection_error_px(ray_directions(fl, 1, True), K, strong) < 1e-3


def test_a_distortion_of_ones_is_applied_on_a_detector_small_enough_to_accept_it(tmp_path):
    # Every coefficient 1.0 moves the corner of a 4 x 3 mm detector (40 x 30 pixels of 0.1 mm at
    # 1100 mm, f = 11000 px, corner radius 2.5 / 1100 normalised) by 0.9 %, inside the profile's
    # bounds: its rays go through the distortion like any other's, and reproject onto their pixels.
    data = YAML(typ="safe").load((REPO / "configs/fluoroscopes/generic-flat-detector.yaml").read_text())
    assert data["geometry"]["source_to_image_mm"] == 1100
    data["detector"].update(columns=40, rows=30, pixel_pitch_mm=0.1)
    data["intrinsics"].update(fx=11000.0, fy=11000.0, cx=19.5, cy=14.5, distortion=dict.fromkeys(("k1", "k2", "p1", "p2", "k3"), 1.0))
    for level, fov in zip(data["zoom_levels"], (4.0, 3.0, 2.0, 1.5)):
        level["fov_mm"] = fov
    data["collimator"]["min_opening_mm"] = 1.0
    path = tmp_path / "tiny.yaml"
    path.write_text(json.dumps(data))
    K = np.array([[11000.0, 0, 19.5], [0, 11000.0, 14.5], [0, 0, 1.0]])
    rays = ray_directions(load_profile(path, FluoroscopeProfile), 1, True)
    assert reprojection_error_px(rays, K, np.ones(5)) < 1e-3          # the pinhole's rays: 0.23 px


def test_blades_and_circle_mask_the_pixels_the_beam_reaches(tmp_path):
    fl = machine(tmp_path)
    assert field_mask(fl, 1, None, circle=False).all()
    # Zoom 2: 1.9 * 220 / 300 mm a pixel; blades 50 x 30 mm open 17.94 and 10.77 pixels either side
    # of the matrix centre (79.5, 59.5): columns 62..97 and rows 49..70.
    blades = field_mask(fl, 2, (50.0, 30.0), circle=False)
    rows, cols = np.nonzero(blades)
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (62, 97, 49, 70)
    assert blades.sum() == 36 * 22
    # The circle: radius 300 / 1.9 / 2 = 78.95 pixels about the centre, the same at every zoom.
    circle = field_mask(fl, 3, None, circle=True)
    assert circle[59, 79] and circle[59, 158] and not circle[59, 159] and circle[59, 1] and not circle[59, 0]
    assert not circle[0, 0] and not circle[119, 159] and circle[0, 79]
    # Both: the blades inside the circle.
    both = field_mask(fl, 1, (280.0, 100.0), circle=True)
    # 140 / 1.9 = 73.7 px of half opening across (columns 6..153), 50 / 1.9 = 26.3 px down (rows 34..85).
    assert both[59, 6] and both[59, 153] and not both[59, 5] and not both[59, 154]
    assert both[34, 79] and both[85, 79] and not both[33, 79] and not both[86, 79]



def test_a_pixel_centred_on_a_blade_edge_or_on_the_circle_is_in_the_field(tmp_path):
    # The mask samples pixel centres and the field is closed: a centre exactly on an edge (the
    # beam covers half that pixel) counts in. 161 x 121 pixels of 2 mm, centre pixel (60, 80):
    # blades 200 x 100 mm reach 50 and 25 pixels either side, exactly on columns 30 and 130 and
    # rows 35 and 85; the circle's radius is 300 / 2 / 2 = 75 pixels, through (60, 5) and (60, 155).
    fl = machine(tmp_path, detector=(161, 121, 2.0))
    blades = field_mask(fl, 1, (200.0, 100.0), circle=False)
    rows, cols = np.nonzero(blades)
    assert (cols.min(), cols.max(), rows.min(), rows.max()) == (30, 130, 35, 85)
    assert blades.sum() == 101 * 51
    circle = field_mask(fl, 1, None, circle=True)
    assert circle[60, 5] and circle[60, 155] and not circle[60, 4] and not circle[60, 156]
    assert circle[0, 35] and circle[0, 125] and not circle[0, 34] and not circle[0, 126]   # 45^2 + 60^2 = 75^2

def test_measuring_field_is_the_central_disc_of_half_the_beams_diameter():
    beam = np.zeros((120, 160), bool)
    beam[20:60, 30:110] = True                  # 40 x 80 pixels, centre (row 39.5, column 69.5)
    central = measuring_field(beam)
    r = 0.5 * math.sqrt(3200 / math.pi)         # 15.96 px
    assert not (central & ~beam).any()
    assert central[39, 69] and central[39, 69 + 15] and not central[39, 69 + 17]
    assert central[int(39.5 + 15.4), 69] and not central[39 + 17, 69]
    assert abs(int(central.sum()) - math.pi * r * r) < 2 * math.pi * r
    # A beam with a hole where its centroid falls: no disc fits, the whole beam measures.
    yy, xx = np.mgrid[0:120, 0:160]
    ring = (30 ** 2 <= (yy - 59.5) ** 2 + (xx - 79.5) ** 2) & ((yy - 59.5) ** 2 + (xx - 79.5) ** 2 <= 40 ** 2)
    np.testing.assert_array_equal(measuring_field(ring), ring)
    # Blades shut: no beam, nothing to measure, and no warning from averaging an empty field.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not measuring_field(np.zeros((8, 8), bool)).any()
