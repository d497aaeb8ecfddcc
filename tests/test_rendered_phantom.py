"""The sphere phantom as a CT volume for the DRR renderer, and calibration from rendered images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.calibration.truth.rendered_phantom import phantom_volume
from appliance.config import load_profile
from appliance.config.calibration_phantom import CalibrationPhantomProfile
from appliance.geometry import apply

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "configs" / "calibration-phantoms" / "two-plane-36.yaml"


@pytest.fixture(scope="module")
def phantom() -> CalibrationPhantomProfile:
    return load_profile(PHANTOM, CalibrationPhantomProfile)


def test_voxelised_balls_keep_their_volume_and_centre(phantom):
    volume = phantom_volume(phantom, voxel_mm=0.5)
    assert np.allclose(volume.spacing_mm, 0.5)
    m = phantom.materials
    T_voxel_from_ct = np.linalg.inv(volume.T_ct_from_voxel)  # not rigid: it carries the voxel size
    for c, d in zip(phantom.centres(), phantom.diameters()):
        i, j, k = np.round(apply(T_voxel_from_ct, c)).astype(int)
        r = int(np.ceil(d / 2 / 0.5)) + 2
        block = volume.hu[k - r:k + r + 1, j - r:j + r + 1, i - r:i + r + 1].astype(float)
        fraction = (block - m.plate_hu) / (m.sphere_hu - m.plate_hu)
        fraction[fraction < 0.5 / (m.sphere_hu - m.plate_hu)] = 0.0
        analytic = 4 / 3 * np.pi * (d / 2) ** 3
        assert fraction.sum() * 0.125 == pytest.approx(analytic, rel=0.02)
        kk, jj, ii = np.mgrid[k - r:k + r + 1, j - r:j + r + 1, i - r:i + r + 1]
        centroid = np.array([(fraction * ii).sum(), (fraction * jj).sum(), (fraction * kk).sum()]) / fraction.sum()
        assert np.linalg.norm(apply(volume.T_ct_from_voxel, centroid) - c) < 0.02  # mm


def test_plates_have_their_thickness(phantom):
    volume = phantom_volume(phantom, voxel_mm=0.5)
    i, j = volume.hu.shape[2] // 2 + 30, volume.hu.shape[1] // 2 + 100  # away from every ball
    column = volume.hu[:, j, i].astype(float)
    plate_mm = ((column + 1000) / (phantom.materials.plate_hu + 1000)).sum() * 0.5
    assert plate_mm == pytest.approx(sum(p.thickness_mm for p in phantom.plates), abs=0.01)
