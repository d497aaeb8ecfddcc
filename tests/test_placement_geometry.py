"""Placing a CT, checked against the anatomy each beam names and numbers worked by hand.

Ground truth: the orientation rules of each beam (PA: the patient's back toward the source;
AP: the front toward it; LAT: the left side toward the detector; the head along the box's
long axis, phantom +x), a proper rotation (LPS is right-handed: left x posterior = superior),
the field's radius at the isocentre by similar triangles (115 mm x 620 / 1000 = 71.3 mm), and
the field running past a CT's ends by the distances of a box whose faces are known.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.geometry import apply, make_transform
from appliance.patient.placement import BeamGeometry, beam_geometry, coverage, place, rotation_phantom_from_ct
from appliance.patient.volume import Volume

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
II = load_profile(CONFIGS / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)


def tilted_beam() -> np.ndarray:
    """A beam direction off every axis, mostly along phantom -z (the couch's vertical)."""
    d = np.array([0.2, -0.3, -1.0])
    return d / np.linalg.norm(d)


@pytest.mark.parametrize("beam, column, sign", [("PA", 1, -1.0), ("AP", 1, 1.0), ("LAT", 0, 1.0)])
def test_each_beam_sees_the_side_it_names(beam, column, sign):
    """Columns of R are where the CT's left (x), posterior (y) and superior (z) axes point.
    The beam direction runs from the source toward the detector."""
    d = tilted_beam()
    R = rotation_phantom_from_ct(beam, d)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)                      # no mirror image of the patient
    assert R[:, column] @ d == pytest.approx(sign)
    head = R[:, 2]
    assert head @ d == pytest.approx(0.0, abs=1e-12) and head[0] > 0.9   # across the beam, along the box
    np.testing.assert_allclose(np.cross(R[:, 0], R[:, 1]), head, atol=1e-12)


def test_place_puts_the_target_at_the_isocentre_and_moves_the_rest_rigidly():
    geometry = BeamGeometry(np.eye(4), np.array([10.0, 20.0, 620.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]),
                            71.3, 620.0, 1000.0)
    target = np.array([37.0, -12.0, -210.0])
    T = place(target, "PA", geometry)
    np.testing.assert_allclose(apply(T, target), geometry.isocentre, atol=1e-9)
    # 40 mm superior of the target lies 40 mm along the box (+x); 40 mm posterior, toward the source (-z).
    np.testing.assert_allclose(apply(T, target + [0, 0, 40.0]), geometry.isocentre + [40.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(apply(T, target + [0, 40.0, 0]), geometry.isocentre + [0, 0, -40.0], atol=1e-9)


def test_beam_geometry_at_home_and_the_field_radius_at_the_isocentre():
    """With the webcam at the phantom (identity home pose), the xray frame's principal ray
    taken back into the phantom frame: the focal spot, the isocentre 620 mm down the ray, and
    the widest field (230 mm at 1000 mm) narrowed to 620 / 1000 of it there."""
    g = beam_geometry(II, np.eye(4))
    T_phantom_from_xray = np.linalg.inv(II.T_xray_from_webcam())
    np.testing.assert_allclose(g.source, T_phantom_from_xray[:3, 3], atol=1e-9)
    np.testing.assert_allclose(g.isocentre, g.source + 620.0 * g.direction, atol=1e-9)
    np.testing.assert_allclose(g.direction, T_phantom_from_xray[:3, 2], atol=1e-12)
    assert g.field_radius_mm == pytest.approx(0.5 * 230.0 * 620.0 / 1000.0)
    assert (g.source_to_isocentre_mm, g.source_to_image_mm) == (620.0, 1000.0)


def test_coverage_is_how_far_the_field_runs_past_each_end_of_the_ct():
    """A CT box 150 mm along the box axis (x from iso - 50 to iso + 100) and 230 mm across it
    (y from iso - 200 to iso + 30), the beam along +z: the 71.3 mm field runs 21.3 mm past its
    foot end and 41.3 mm past one side, and not at all past the other two."""
    geometry = BeamGeometry(np.eye(4), np.array([0.0, 0.0, 620.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]),
                            71.3, 620.0, 1000.0)
    spacing = np.array([150.0 / 15, 230.0 / 23, 10.0])
    volume = Volume(np.zeros((3, 24, 16), np.int16), make_transform(np.diag(spacing), np.zeros(3)))
    T_phantom_from_ct = make_transform(np.eye(3), np.array([-50.0, -200.0, 610.0]))
    short = coverage(volume, T_phantom_from_ct, geometry).short_mm
    # head = +x, across = d x head = +y.
    assert short == pytest.approx({"head+": 0.0, "head-": 21.3, "across+": 41.3, "across-": 0.0})
