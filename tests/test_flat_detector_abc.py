"""The flat-detector room's exposure control follows its own kV-mA curve (abc.curve of
configs/fluoroscopes/generic-flat-detector.yaml): at the point it sets for a water slab, the
detector signal (spekpy's spectrum through xraylib's water, computed here) is the reference
patient's at the reference technique, and the dose rate follows spekpy's air kerma per mAs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_image_chain import CONFIGS, spekpy_kerma, water_signal

from appliance.config.case import Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.xray.renderer import Renderer, View, at_resolution
from appliance.xray.truth.analytic import box_volume

FLAT = load_profile(CONFIGS / "generic-flat-detector.yaml", FluoroscopeProfile)


def test_the_flat_detector_ships_a_rising_curve_through_its_reference_technique():
    curve = FLAT.abc.curve
    assert len(curve) >= 3
    assert any(p.kvp == FLAT.tube.kvp and p.ma == FLAT.tube.ma for p in curve)
    assert all(b.kvp > a.kvp and b.ma > a.ma for a, b in zip(curve, curve[1:]))


@pytest.mark.parametrize("water_mm", [80.0, 220.0])
def test_the_flat_detector_moves_along_its_curve_to_the_reference_signal(water_mm):
    renderer = Renderer(at_resolution(FLAT, 64, 64), Materials(), device="cpu")
    n = int(water_mm // 5)
    vol = box_volume((n, 64, 64), (8.0, 8.0, 5.0), (0, 0, 0), (63, 63, n - 1), hu=0)[0]
    T = np.eye(4)
    T[2, 3] = FLAT.geometry.source_to_isocentre_mm
    frame = renderer.render(renderer.prepare(vol), T, View(noise=False))
    curve = FLAT.abc.curve
    assert frame.kvp is not None and frame.ma is not None
    assert not frame.limited and curve[0].kvp < frame.kvp < curve[-1].kvp
    # A thin slab stays below the reference kV (the mA does the work), a thick one climbs past it.
    assert (frame.kvp < FLAT.tube.kvp) if water_mm < 100 else (frame.kvp > FLAT.tube.kvp)
    i = max(j for j in range(len(curve) - 1) if curve[j].kvp <= frame.kvp)
    w = (frame.kvp - curve[i].kvp) / (curve[i + 1].kvp - curve[i].kvp)
    slope = (curve[i + 1].ma - curve[i].ma) / (curve[i + 1].kvp - curve[i].kvp)
    on_curve = curve[i].ma + w * (curve[i + 1].ma - curve[i].ma)
    # The generator sets kV in 1 kV steps (the curve's kV rounded) and trims the mA within one.
    assert 0.85 * on_curve <= frame.ma <= (on_curve + 0.5 * slope) * (1 + 1e-9)
    signal = frame.ma * water_signal(frame.kvp, water_mm, FLAT)
    target = FLAT.tube.ma * water_signal(FLAT.tube.kvp, 0.0, FLAT) * math.exp(-FLAT.abc.reference_attenuation)
    assert signal == pytest.approx(target, rel=0.10)
    assert frame.exposure_factor == pytest.approx(frame.ma * spekpy_kerma(frame.kvp, FLAT) /
                                                  (FLAT.tube.ma * spekpy_kerma(FLAT.tube.kvp, FLAT)), rel=0.02)
