"""The detector on the device (device_chain.py, detector_chain.cl): its blurs and resizes against
OpenCV's own, and whole display frames against the host's chain, on the adult chest's anatomy
(ribs, vessels, lungs, bowel gas) through both shipped fluoroscopes."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.config.case import Contrast, Materials
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.patient.adult_chest import build_adult_chest
from appliance.patient.volume import Volume
from appliance.xray.bench import pa_pose
from appliance.xray.device import ClDevice
from appliance.xray.device_chain import DeviceChain, area_taps, gaussian_taps, linear_taps, resample_host
from appliance.xray.renderer import Renderer, View, at_resolution

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "fluoroscopes"


@pytest.fixture(scope="module")
def chain():
    return DeviceChain(ClDevice("cpu"))


def _random(shape, seed):
    return np.random.default_rng(seed).random(shape).astype(np.float32) * 3.0


# Sizes below a kernel's reach too (7 and 2 pixels under a sigma of 4: the border reflected more than once).
@pytest.mark.parametrize("shape,sigma", [((96, 130), 0.6), ((64, 80), 2.3), ((7, 40), 4.0), ((2, 33), 1.1)])
def test_gaussian_taps_are_opencvs_blur(shape, sigma):
    x = _random(shape, 1)
    rows, cols = shape
    got = resample_host(x, gaussian_taps(rows, sigma), gaussian_taps(cols, sigma))
    np.testing.assert_allclose(got, cv2.GaussianBlur(x, (0, 0), sigma), rtol=0, atol=2e-6)


# 1024 -> 85 and 512 -> 42 are the glare's grids (not whole multiples); 512 -> 64 is one.
@pytest.mark.parametrize("n_src,n_dst", [(1024, 85), (512, 42), (512, 64), (100, 7)])
def test_area_and_linear_taps_are_opencvs_resize(n_src, n_dst):
    x = _random((n_src, n_src // 2 + 3), 2)
    small = (n_dst, n_dst // 2 + 1)
    want = cv2.resize(x, small[::-1], interpolation=cv2.INTER_AREA)
    got = resample_host(x, area_taps(x.shape[0], small[0]), area_taps(x.shape[1], small[1]))
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
    back = cv2.resize(want, x.shape[::-1], interpolation=cv2.INTER_LINEAR)
    got = resample_host(want, linear_taps(small[0], x.shape[0]), linear_taps(small[1], x.shape[1]))
    np.testing.assert_allclose(got, back, rtol=0, atol=2e-6)


def test_kernels_blur_and_resize_as_opencv(chain):
    x = _random((200, 151), 3)
    buf = chain.upload(x)
    np.testing.assert_allclose(chain.download(chain.blur(buf, x.shape, 1.7), x.shape),
                               cv2.GaussianBlur(x, (0, 0), 1.7), rtol=0, atol=2e-6)
    small = chain.resize(buf, x.shape, (17, 12), "area")
    want = cv2.resize(x, (12, 17), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(chain.download(small, (17, 12)), want, rtol=0, atol=2e-6)
    np.testing.assert_allclose(chain.download(chain.resize(small, (17, 12), x.shape, "linear"), x.shape),
                               cv2.resize(want, (151, 200), interpolation=cv2.INTER_LINEAR), rtol=0, atol=2e-6)
    index = np.array([0, 5, 200 * 151 - 1, 77], dtype=np.intp)
    np.testing.assert_array_equal(chain.gather(buf, index), x.ravel()[index])


@pytest.fixture(scope="module")
def chest():
    hu, spacing, origin = build_adult_chest(shape_zyx=(48, 128, 128), spacing_mm=(7.0, 3.0, 3.0))
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    nz, ny, nx = hu.shape
    T[:3, 3] = -T[:3, :3] @ ((np.array([nx, ny, nz]) - 1) / 2.0)
    return Volume(hu=hu, T_ct_from_voxel=T, source="adult chest 128x128x48")


def _pose(deg: float) -> np.ndarray:
    """PA, the C-arm turned `deg` off the axis, isocentre 620 mm from the source."""
    return pa_pose(620.0, deg)


def _profile(name: str) -> FluoroscopeProfile:
    """A shipped fluoroscope; "+enhanced": with a site's edge enhancement and a heavier
    frame integrator than the shipped 0.5, whose weight and its complement are the same."""
    fl = load_profile(CONFIGS / name.split("+")[0], FluoroscopeProfile)
    if name.endswith("+enhanced"):
        fl = fl.model_copy(update={"image": fl.image.model_copy(update={"recursive_weight": 0.75,
                                                                         "unsharp_amount": 0.6})})
    return fl


@pytest.mark.parametrize("profile", ["generic-ii-carm.yaml", "generic-flat-detector.yaml",
                                     "generic-ii-carm.yaml+enhanced"])
@pytest.mark.parametrize("packet", [True, False])
def test_display_frames_on_the_device_are_the_hosts(chest, profile, packet):
    """Frame by frame, the host's chain and the device's give the same grey, signal, window,
    technique and photons, with noise (one seed) and without, through the recursive filter
    as the C-arm turns, inverted, zoomed and collimated; `packet` False runs a GPU's kernels."""
    fl = at_resolution(_profile(profile), 160, 160)
    frames = {}
    for on_device in (False, True):
        r = Renderer(fl, Materials(contrast_min_hu=2500), Contrast(concentration_mg_per_ml=150), device="cpu",
                     packet=packet, device_chain=on_device)
        assert (r.chain is not None) == on_device
        a = r.prepare(chest)
        got = []
        views = [View(noise=False), View(seed=11), View(noise=False, temporal="live"),
                 View(seed=4, temporal="live", invert=True, zoom=2, collimation_mm=(120.0, 90.0)),
                 View(noise=False, temporal="off", window_scale=1.5, level_shift=0.2)]
        for view in views:
            for k in range(4):                       # the filter's state carried frame to frame
                got.append(r.render(a, _pose(3.0 * k), view))
        frames[on_device] = got
    for host, device in zip(frames[False], frames[True]):
        np.testing.assert_allclose(device.image, host.image, rtol=0, atol=2e-5)
        np.testing.assert_allclose(device.signal, host.signal, rtol=2e-5, atol=1e-9)
        np.testing.assert_allclose(device.window, host.window, rtol=1e-5)
        np.testing.assert_allclose(device.photons_per_pixel, host.photons_per_pixel, rtol=1e-5)
        assert (device.exposure_factor, device.kvp, device.limited) == (host.exposure_factor, host.kvp, host.limited)
        assert device.image.dtype == np.float32 and device.image.shape == host.image.shape


def test_filter_carried_over_to_another_matrix_runs_on_the_device(chest):
    """A held view's switch of matrix (progressive.py) carries the filter's state over; the
    device's next step starts from it as the host's does."""
    fl = _profile("generic-ii-carm.yaml+enhanced")
    results = []
    for on_device in (False, True):
        small = Renderer(at_resolution(fl, 96, 96), Materials(contrast_min_hu=2500), None, device="cpu",
                         device_chain=on_device)
        big = small.at_matrix(160, 160)
        a = small.prepare(chest)
        view = View(noise=False, temporal="live")
        for k in range(3):
            small.render(a, _pose(2.0 * k), view)
        big.lag.carry_over(small.lag, big.shape)
        results.append(big.render(a, _pose(6.0), view))
    np.testing.assert_allclose(results[1].signal, results[0].signal, rtol=2e-5, atol=1e-9)
    np.testing.assert_allclose(results[1].image, results[0].image, rtol=0, atol=2e-5)


def test_a_driver_that_cannot_build_the_chain_leaves_the_detector_on_the_host(chest, tmp_path, monkeypatch, caplog):
    import appliance.xray.device_chain as device_chain

    broken = tmp_path / "detector_chain.cl"
    broken.write_text("kernel void multiply(global float *a) { a[0] = undeclared; }\n")
    monkeypatch.setattr(device_chain, "SOURCE", broken)
    fl = at_resolution(_profile("generic-ii-carm.yaml"), 64, 64)
    with caplog.at_level("WARNING"):
        r = Renderer(fl, Materials(contrast_min_hu=2500), None, device="cpu", device_chain=True)
    assert r.chain is None
    assert any("detector stays on the host" in m and "detector_chain.cl" in m for m in caplog.messages)
    frame = r.render(r.prepare(chest), _pose(0.0), View(seed=1))
    assert frame.image.shape == (64, 64) and 0.2 < float(frame.image[32, 32]) < 0.9
