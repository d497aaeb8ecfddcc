"""The detail bar at zoom 4 on a thin-slice CT: the noise-free display's band-passed detail
(sigma 1 px minus 6 px) correlates >= 0.80 with the band-passed exact (Siddon) line integral
of the same view, through the right lung of the adult chest drawn on 0.8 mm voxels, as a
chest CT reconstructed at thin slices has them (the view bench image misses on 2.5 mm slices)."""

from __future__ import annotations

import pytest
from test_image_chain import CONFIGS

from appliance.config.case import Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.xray import acceptance, bar_pattern
from appliance.xray.anatomy_reference import ANATOMY_HALF_MM, BODY_Y_MM, THIN_SPACING_MM, adult_chest_box
from appliance.xray.renderer import Renderer, View, at_resolution

R_LUNG = (-90.0, 0.0, 60.0)


@pytest.fixture(scope="module")
def thin_lung():
    cx, _, cz = R_LUNG
    lo = (cx - ANATOMY_HALF_MM, BODY_Y_MM[0], cz - ANATOMY_HALF_MM)
    hi = (cx + ANATOMY_HALF_MM, BODY_Y_MM[1], cz + ANATOMY_HALF_MM)
    return adult_chest_box(lo, hi, THIN_SPACING_MM)


def test_zoom_4_keeps_the_detail_of_a_thin_slice_ct(thin_lung):
    ii = load_profile(CONFIGS / "generic-ii-carm.yaml", FluoroscopeProfile)
    straight = bar_pattern.undistorted(at_resolution(ii, 256, 256))
    renderer = Renderer(straight, Materials(), device="cpu")
    prepared = renderer.prepare(thin_lung)
    T = acceptance.ap_pose(straight.geometry.source_to_isocentre_mm, R_LUNG)
    clean = renderer.render(prepared, T, View(zoom=4, noise=False)).image
    mask = renderer.field_mask(4, None, True)
    inside = acceptance.interior(mask, renderer.detector.edge(mask, 4))
    exact = renderer.line_integral(prepared, T, 4)
    assert acceptance.detail_correlation(clean, exact, inside) >= 0.80
    # With the profile's quantum noise and exposure control, after a 0.7 px blur: the issue's
    # zoom-4 bar for the noisy image.
    noisy = renderer.render(prepared, T, View(zoom=4, noise=True, seed=4)).image
    assert acceptance.detail_correlation(noisy, exact, inside, pre_blur_px=0.7) >= 0.30
