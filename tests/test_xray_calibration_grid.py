"""The field-filling grid phantom and what its dense shadows ask of detection, and the exact
centroid of a ball's shadow, on analytic shadowgraph images (ray-sphere chords through
OpenCV's distortion) at known poses."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.calibration.blobs import detect_blobs
from appliance.calibration.field_of_view import find_field_of_view
from appliance.calibration.fit import centroid_offsets
from appliance.calibration.identification import identify
from appliance.calibration.truth import scenario, shadowgraph
from appliance.config import FluoroscopeProfile, load_profile
from appliance.config.calibration_phantom import CalibrationPhantomProfile
from appliance.geometry import apply, make_transform, rotation_about

ROOT = Path(__file__).resolve().parents[1]
GRID = ROOT / "configs" / "calibration-phantoms" / "two-plane-grid-332.yaml"
PHANTOM_36 = ROOT / "configs" / "calibration-phantoms" / "two-plane-36.yaml"
FLUOROSCOPE = ROOT / "configs" / "fluoroscopes" / "generic-ii-carm.yaml"


@pytest.fixture(scope="module")
def grid():
    return load_profile(GRID, CalibrationPhantomProfile)


@pytest.fixture(scope="module")
def machine():
    return scenario.true_machine(load_profile(FLUOROSCOPE, FluoroscopeProfile))


def test_the_grid_reaches_the_field_edge_and_keeps_its_shadows_apart(grid):
    centres, large = grid.centres(), grid.large_mask()
    assert len(centres) == 332 and large.sum() == 10
    assert {s.line for s, big in zip(grid.spheres, large) if big} == {"A", "B", "D"}
    # The field of a 230 mm intensifier at 1000 mm, seen at 600-700 mm from the source, is a
    # disc of 64-74 mm radius on the phantom; the balls reach 80 mm so they fill it even shifted.
    assert np.hypot(centres[:, 0], centres[:, 1]).max() == pytest.approx(80.0, abs=1.0)
    # Large balls stay within 45 mm, in the field at every pose of the acquisition.
    assert np.hypot(centres[large, 0], centres[large, 1]).max() < 45
    # Tilted 12 degrees any way, the plates' 16 mm apart shift one plate's shadows by up to
    # 16 tan 12 = 3.4 mm: no small ball of one plate comes within 3.5 mm (its own diameter
    # plus a radius of the other) of the other plate's, nor a small one within 8 mm of a large.
    top, bottom = centres[:, 2] > 0, centres[:, 2] < 0
    for angle in np.radians(np.arange(0, 360, 5)):
        shift = 16 * np.tan(np.radians(12)) * np.array([np.cos(angle), np.sin(angle)])
        gap = np.linalg.norm(centres[top, None, :2] - (centres[None, bottom, :2] + shift), axis=2)
        assert gap[~large[top]].min() > 3.5 and gap[large[top]].min() > 8.0


def test_every_ball_of_the_dense_grid_is_found_dark_and_paired_right(grid, machine):
    # Full matrix, as the old detector failed only there: its 3-D maxima were taken of the
    # response over each scale's noise, and the grid's balls lift the noise estimate of
    # every scale but the finest, so every peak slid to the finest scales and the large
    # balls were lost. One sample per pixel keeps the image fast to make.
    K = machine.K
    T = make_transform(rotation_about([1, 0.5, 0], np.radians(5)) @ rotation_about([0, 0, 1], 0.4), [4, -6, 650])
    exposure = shadowgraph.Exposure(fov_radius_px=0.49 * 1024, supersample=1, vignetting=0.25, glare_fraction=0.06)
    image = shadowgraph.render(grid, K, machine.dist, T, exposure, np.random.default_rng(2))
    fov = find_field_of_view(image)
    blobs = detect_blobs(image, fov, grid.detection)
    truth, _ = cv2.projectPoints(apply(T, grid.centres()), np.zeros(3), np.zeros(3), K, machine.dist)
    truth = truth.reshape(-1, 2)
    well_inside = np.hypot(truth[:, 0] - 511.5, truth[:, 1] - 511.5) < 0.49 * 1024 - 30
    # Between the balls of a dense grid the open field forms as many bright "blobs" as there
    # are balls; picking the polarity by count found the gaps. Every blob is a ball's shadow.
    nearest = np.linalg.norm(blobs.uv[:, None] - truth[None], axis=2).min(axis=1)
    assert np.all(nearest < 1.0) and len(blobs) >= 0.9 * well_inside.sum()
    # A large ball among small ones: its scale-space peak survives (10 of 10 found).
    large_found = np.linalg.norm(blobs.uv[:, None] - truth[None, grid.large_mask()], axis=2).min(axis=0) < 1.0
    assert large_found.all()
    nominal = load_profile(FLUOROSCOPE, FluoroscopeProfile)
    found = identify(blobs, grid, nominal.intrinsics.K(), nominal.intrinsics.distortion.coefficients(), "grid", fov)
    err = np.linalg.norm(found.uv - truth[found.sphere_index], axis=1)
    assert len(found.sphere_index) >= 0.9 * well_inside.sum() and err.max() < 1.0


def test_the_centroid_offset_is_the_shadow_s_exact_chord_weighted_centroid(machine):
    """Truth: the attenuation image's own centroid, each pixel's chord found through
    `cv2.undistortPoints` and the ray-sphere formula, supersampled 5 x 5. Close to the
    source the balls' shadows are ellipses stretched outward by up to 0.05 px."""
    phantom = load_profile(PHANTOM_36, CalibrationPhantomProfile)
    T = make_transform(np.eye(3), [20, 15, 420])
    line = shadowgraph.ball_line_integrals(phantom, machine.K, machine.dist, T,
                                           shadowgraph.Exposure(supersample=5, text=False))
    centres = apply(T, phantom.centres())
    uv, _ = cv2.projectPoints(centres, np.zeros(3), np.zeros(3), machine.K, machine.dist)
    uv = uv.reshape(-1, 2)
    model = centroid_offsets(machine.K, machine.dist, T, phantom.centres(), phantom.diameters() / 2)
    checked = 0
    for i, (u, v) in enumerate(uv):
        if not (60 < u < 964 and 60 < v < 964):
            continue
        half = int(1.3 * machine.K[0, 0] * phantom.diameters()[i] / 2 / centres[i, 2]) + 3
        u0, v0 = int(round(u)), int(round(v))
        patch = line[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1]
        vv, uu = np.mgrid[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1]
        truth = np.array([(patch * uu).sum(), (patch * vv).sum()]) / patch.sum() - (u, v)
        assert np.abs(model[i] - truth).max() < 0.0015, (i, model[i], truth)
        checked += 1
    assert checked >= 15 and np.abs(model).max() > 0.03
