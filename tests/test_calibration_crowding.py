"""An image refused because the phantom is tilted too far says so (crowded shadows, the tilt to
stay under), instead of "check that the whole phantom is in the field"; the crowding tilt of a
phantom matches the closed form for two balls."""

from pathlib import Path

import numpy as np
import pytest

from appliance.calibration.blobs import detect_blobs
from appliance.calibration.crowding import NEIGHBOUR_DIAMETERS, OWN_DIAMETERS, crowding_advice, crowding_tilt_deg
from appliance.calibration.field_of_view import find_field_of_view
from appliance.calibration.identification import IdentificationFailed, identify
from appliance.calibration.truth.scenario import true_machine
from appliance.calibration.truth.shadowgraph import Exposure, render
from appliance.config import FluoroscopeProfile, load_profile
from appliance.config.calibration_phantom import CalibrationPhantomProfile
from appliance.geometry import make_transform, rotation_about

REPO = Path(__file__).resolve().parents[1]


def test_two_balls_crowd_at_the_closed_form_tilt():
    # Balls of diameter D, 10 mm apart in plan and 16 mm apart in height. Tilted by t about the
    # axis across their offset, their plan distance is 10 cos t - 16 sin t = R cos(t + a), with
    # R = hypot(10, 16) and a = atan2(16, 10); they crowd below (1.15 + 0.5) D.
    D = 2.0
    reach = (OWN_DIAMETERS + NEIGHBOUR_DIAMETERS) * D
    exact = np.degrees(np.arccos(reach / np.hypot(10.0, 16.0)) - np.arctan2(16.0, 10.0))   # 21.9 deg
    found = crowding_tilt_deg(np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 16.0]]), np.array([D, D]))
    assert found == np.ceil(exact)                      # searched in whole degrees
    # Side by side in one plate they never crowd: the search's top comes back.
    assert crowding_tilt_deg(np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]), np.array([D, D])) == 60.0


def test_a_few_crowded_shadows_are_no_explanation():
    phantom = load_profile(REPO / "configs/calibration-phantoms/two-plane-36.yaml", CalibrationPhantomProfile)
    assert crowding_advice(33, 3, phantom) is None
    assert crowding_advice(300, 10, phantom) is None          # 3 %: a few crowd in any image
    advice = crowding_advice(30, 6, phantom)
    assert advice is not None and advice.startswith("6 of its 36 ball shadows") and "tilt it less than 15 deg" in advice


def test_a_steeply_tilted_grid_is_refused_for_its_tilt():
    fluoroscope = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
    phantom = load_profile(REPO / "configs/calibration-phantoms/two-plane-grid-332.yaml", CalibrationPhantomProfile)
    machine = true_machine(fluoroscope)
    pose = make_transform(rotation_about([1.0, 0.3, 0.0], np.radians(40.0)) @ rotation_about([0, 0, 1], 0.4), [3, -2, 650])
    image = render(phantom, machine.K, machine.dist, pose, Exposure(supersample=1, text=False))
    fov = find_field_of_view(image, "tilted.png")
    blobs = detect_blobs(image, fov, phantom.detection)
    assert blobs.crowded >= 0.1 * (len(blobs) + blobs.crowded)
    with pytest.raises(IdentificationFailed) as refused:
        identify(blobs, phantom, fluoroscope.intrinsics.K(), fluoroscope.intrinsics.distortion.coefficients(),
                 "tilted.png", fov)
    message = str(refused.value)
    assert message.startswith("tilted.png: ") and "\n" not in message
    assert "tilted too far" in message and "tilt it less than 13 deg" in message
    assert "check that the whole phantom is in the field" not in message
