"""The detector model's small formulas, each against its closed form worked from the profile's numbers.

Ground truth: the exposure control without a kV-mA curve brings the signal back to the
reference patient's, exp(attenuation - reference), bounded by min_factor, max_factor and the
21 CFR 1020.32 limit (88 mGy/min over the zoom level's reference rate); the focal spot's
penumbra is f (M - 1) at the detector, M = SID / depth, its FWHM 2 sqrt(2 ln 2) sigma; the
recursive filter carried to another matrix goes on averaging (y = w y' + (1 - w) x) instead
of restarting.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.xray.detector import Detector, RecursiveFilter

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "fluoroscopes"
II = load_profile(CONFIGS / "generic-ii-carm.yaml", FluoroscopeProfile)
#: The same machine with a generator that only trims the mA (no kV-mA curve): the exposure control's other path.
NO_CURVE = II.model_copy(update={"abc": II.abc.model_copy(update={"curve": []})})
MU_WATER = 0.02      # per mm; only the photon counts use it, not the formulas below


def test_profile_numbers_the_expected_values_are_worked_from():
    # The cases below are worked by hand from these; a changed profile must change them too.
    assert (II.abc.reference_attenuation, II.abc.min_factor, II.abc.max_factor) == (3.0, 0.1, 4.0)
    assert II.image.dose_rate_limit_mgy_per_min == 88
    assert II.zoom_levels[0].air_kerma_rate_mgy_per_min["continuous"] == 8.0
    assert II.zoom_levels[3].air_kerma_rate_mgy_per_min["continuous"] == 42.3
    assert (II.tube.focal_spot_mm, II.geometry.source_to_image_mm, II.geometry.source_to_isocentre_mm) == (0.6, 1000, 620)
    assert (II.detector.pixel_pitch_mm, II.zoom_levels[0].fov_mm, II.zoom_levels[3].fov_mm) == (0.225, 230, 100)


@pytest.mark.parametrize("attenuation, zoom, factor, limited", [
    (3.0, 1, 1.0, False),                          # the reference patient: the reference technique
    (3.5, 1, math.exp(0.5), False),                # half a unit more: e^0.5 more output
    (1.0, 1, math.exp(-2.0), False),               # thinner: less, still above min_factor 0.1
    (0.5, 1, 0.1, True),                           # e^-2.5 = 0.082 is under min_factor
    (6.0, 1, 4.0, True),                           # e^3 = 20 is over max_factor (88 / 8 = 11 is further)
    (4.0, 4, 88.0 / 42.3, True),                   # e = 2.72 is over the dose-rate limit's 88 / 42.3 = 2.08
    (3.5, 4, math.exp(0.5), False),                # 1.65 is under both
])
def test_exposure_control_without_a_curve_follows_the_attenuation_within_its_bounds(attenuation, zoom, factor, limited):
    exposure = Detector(NO_CURVE, MU_WATER).exposure(math.exp(-attenuation), zoom, "continuous")
    assert exposure.factor == pytest.approx(factor, rel=1e-12)
    assert exposure.attenuation == pytest.approx(attenuation, rel=1e-12)
    assert exposure.limited is limited
    assert exposure.factor * II.zoom_levels[zoom - 1].air_kerma_rate_mgy_per_min["continuous"] <= 88.0 + 1e-9


@pytest.mark.parametrize("zoom", [1, 4])
@pytest.mark.parametrize("depth_mm, expected_depth_mm", [(None, 620.0), (300.0, 300.0), (900.0, 900.0),
                                                         (5000.0, 1000.0), (0.0, 1.0)])
def test_focal_spot_penumbra_is_the_spot_times_magnification_minus_one(zoom, depth_mm, expected_depth_mm):
    """An object at depth d from the source is magnified M = SID / d; each point of a spot of
    width f lands f (M - 1) apart on the detector. That width is the blur's FWHM, in pixels of
    the zoom level's pitch at the input plane (230 mm / 1024 px widened at zoom 1, 100 mm at 4)."""
    magnification = 1000.0 / expected_depth_mm
    pitch_mm = 0.225 * (230.0, 170.0, 130.0, 100.0)[zoom - 1] / 230.0
    fwhm_px = 0.6 * (magnification - 1.0) / pitch_mm
    sigma = Detector(II, MU_WATER).focal_blur_px(zoom, depth_mm)
    assert sigma * 2.0 * math.sqrt(2.0 * math.log(2.0)) == pytest.approx(fwhm_px, rel=1e-4, abs=1e-12)


def test_recursive_filter_carried_to_another_matrix_goes_on_averaging():
    """The progressive renderer moves a still field to another matrix: the lag carries on there
    (one more frame weighs 1 - w), and a frame at the old matrix or another field restarts it."""
    w = 0.5
    big = RecursiveFilter(w)
    key = (1, None)
    big.step(np.full((8, 8), 100.0, np.float32), (*key, (8, 8)))
    big.step(np.full((8, 8), 200.0, np.float32), (*key, (8, 8)))        # 0.5 x 100 + 0.5 x 200 = 150
    small = RecursiveFilter(w)
    small.carry_over(big, (4, 4))
    out = small.step(np.full((4, 4), 10.0, np.float32), (*key, (4, 4)))
    assert out.shape == (4, 4)
    assert np.allclose(out, w * 150.0 + (1 - w) * 10.0)
    # Another zoom is another field: the filter starts again from that frame.
    assert np.allclose(small.step(np.full((4, 4), 10.0, np.float32), (2, None, (4, 4))), 10.0)
    # Nothing to carry: the next frame starts it.
    fresh = RecursiveFilter(w)
    fresh.carry_over(RecursiveFilter(w), (4, 4))
    assert np.allclose(fresh.step(np.full((4, 4), 7.0, np.float32), (*key, (4, 4))), 7.0)
