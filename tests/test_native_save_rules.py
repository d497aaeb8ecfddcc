"""A saved image's native re-render (appliance/daemon/native_save.py) beside its pacing waits
(tests/test_native_save.py): what the pacer reports of itself, a cancel at its first ask, and
the native frame's matrix, filter and 16-bit scale.

Ground truth: simulated time worked by hand (the pacer, made at t = 0, asks the records
worker's callback once after each band and then after every 20 ms slice of its wait, so the
longest gap between asks is the longest band, or a slice where the bands are shorter still);
the detector's rows and columns as typed here; the recursive filter's settled noise, whose
variance is (1 - w) / (1 + w) of one frame's: a third at the profile's w = 0.5, so the noise's
standard deviation 1 / sqrt(3) of an unfiltered frame's at the same exposure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_native_save import Clock

from appliance.config.appliance import Daemon
from appliance.config.case import Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.daemon.native_save import PACE_SLICE_S, SavePacer, native_frame
from appliance.xray import acceptance
from appliance.xray.renderer import Renderer, View, at_resolution
from appliance.xray.truth.analytic import box_volume

REPO = Path(__file__).resolve().parents[1]


def bands(share: float, live: bool, lengths_s: list[float]) -> SavePacer:
    clock = Clock()
    pacer = SavePacer(share, lambda: False, lambda: live, clock, clock.sleep)
    for band in lengths_s:
        clock.sleep(band)
        assert pacer() is False
    return pacer


def test_the_longest_gap_is_the_longest_band():
    # Bands of 60, 100 and 40 ms at share 0.5: waits of as long, in 20 ms slices; gaps 60, 20,
    # 20, 20, then 100, 20 x 5, then 40, 20, 20: the longest 100 ms.
    assert bands(0.5, True, [0.06, 0.10, 0.04]).longest_gap_s == pytest.approx(0.10, abs=1e-9)
    # With no live frame coming there is no wait: the gaps are the bands alone.
    assert bands(0.5, False, [0.03, 0.07, 0.05]).longest_gap_s == pytest.approx(0.07, abs=1e-9)


def test_with_bands_shorter_than_a_slice_the_longest_gap_is_a_slice():
    # Bands of 10 ms at share 0.2: each followed by 40 ms of wait, asked every 20 ms.
    assert bands(0.2, True, [0.01] * 4).longest_gap_s == pytest.approx(PACE_SLICE_S, abs=1e-9)


def test_before_any_band_no_gap_is_counted():
    assert bands(0.5, True, []).longest_gap_s == 0.0


@pytest.mark.parametrize("live", [True, False])
def test_a_cancel_at_the_first_ask_ends_the_save_with_no_wait(live):
    clock, asked = Clock(), []
    pacer = SavePacer(0.5, lambda: asked.append(clock.t) or True, lambda: live, clock, clock.sleep)
    clock.sleep(0.06)
    assert pacer() is True and clock.t == pytest.approx(0.06) and len(asked) == 1


@pytest.fixture(scope="module")
def setup():
    ii = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
    assert ii.image.recursive_weight == 0.5
    fixed = ii.model_copy(update={"abc": ii.abc.model_copy(update={"enabled": False})})   # a fixed window
    live = Renderer(at_resolution(fixed, 24, 24), Materials(), device="cpu")
    water = live.prepare(box_volume((40, 40, 40), (5.0, 5.0, 5.0), (0, 0, 0), (39, 39, 39))[0])   # 200 mm of water
    return live, fixed, water, acceptance.ap_pose(ii.geometry.source_to_isocentre_mm)


def native(setup, seed: int, columns: int = 96, rows: int = 96):
    live, fixed, water, T = setup
    # The live view asks for its recursive filter ("live"); the save shows the settled one.
    request = (water, T, View(noise=True, seed=seed, temporal="live"), None)
    (image, profile), pacer = native_frame(live, request, at_resolution(fixed, columns, rows), Daemon(), False)
    assert pacer is None
    return image, profile


def test_the_native_frame_has_the_detectors_rows_and_columns(setup):
    image, profile = native(setup, 1, columns=96, rows=64)
    assert image.shape == (64, 96) and image.dtype == np.uint16
    assert (profile.detector.columns, profile.detector.rows) == (96, 64)


def test_the_native_frame_has_the_settled_filters_noise_in_full_16_bit_scale(setup):
    """Two seeds' difference over the middle of 200 mm of water, over sqrt 2: the noise alone.
    The same view unfiltered at the native matrix ("off") is the peer; the save's is 1 / sqrt 3
    of it (a live frame, its filter's first, would be the peer's own). The 16-bit frame is the
    display's 0-1 scaled to 0-65535, so its mean is the peer's mean times 65535."""
    live, _, water, T = setup
    middle = (slice(24, 72), slice(24, 72))
    a, b = (native(setup, s)[0].astype(float) for s in (1, 2))
    peer = live.at_matrix(96, 96)
    c, d = (peer.render(water, T, View(noise=True, seed=s, temporal="off")).image.astype(float) for s in (1, 2))
    saved_sd = np.std((a - b)[middle]) / np.sqrt(2)
    peer_sd = np.std((c - d)[middle]) / np.sqrt(2) * 65535
    assert saved_sd / peer_sd == pytest.approx(1 / np.sqrt(3), rel=0.06)
    assert a[middle].mean() == pytest.approx(c[middle].mean() * 65535, rel=1e-3)


def test_a_saturated_pixel_is_full_scale_white(setup):
    """Without the display's soft knee (display_knee 0) 200 mm of dense bone is past the top of
    the window in every pixel: display 1.0, so 65535 in the 16-bit frame (not 0, a wrap)."""
    live, fixed, _, T = setup
    hard = fixed.model_copy(update={"image": fixed.image.model_copy(update={"display_knee": 0.0})})
    renderer = Renderer(at_resolution(hard, 24, 24), Materials(), device="cpu")
    bone = renderer.prepare(box_volume((40, 40, 40), (5.0, 5.0, 5.0), (0, 0, 0), (39, 39, 39), hu=3000)[0])
    request = (bone, T, View(noise=True, seed=1, temporal="live"), None)
    (image, _), _ = native_frame(renderer, request, at_resolution(hard, 64, 64), Daemon(), False)
    assert (image[16:48, 16:48] == 65535).all()
