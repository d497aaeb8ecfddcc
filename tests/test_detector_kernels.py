"""The detector's SIMD kernels (drr.cl): the polychromatic sum with its blend of two phases, and
the quantum noise sixteen pixels at a time, checked against NumPy in float64 and against
Poisson's probabilities."""

import math

import numpy as np
import pytest

from appliance.xray.device import ClDevice

#: Pixels not a multiple of the 16-pixel packet, so the kernels' tails run too.
N = 16 * 700 + 9


@pytest.fixture(scope="module")
def dev():
    return ClDevice("cpu")


def transmission_f64(lines, mu, weights):
    """I/I0 = sum_e w_e exp(-0.1 sum_m mu_em L_m) (L in g/cm^3 * mm, mu in cm^2/g), in float64."""
    return np.exp(-0.1 * (lines.astype(np.float64) @ mu.T.astype(np.float64))) @ weights.astype(np.float64)


@pytest.mark.parametrize("kernel", ["polychromatic_packet", "polychromatic"])
def test_polychromatic_sum_of_two_blended_phases_is_the_spectrum_of_the_blend(dev, kernel):
    rng = np.random.default_rng(3)
    # Air, soft tissue, bone and contrast integrals up to 400 mm of tissue: transmissions down to 1e-13.
    a = (rng.random((N, 4)) * [5.0, 400.0, 60.0, 3.0]).astype(np.float32)
    b = (rng.random((N, 4)) * [5.0, 400.0, 60.0, 3.0]).astype(np.float32)
    mu = (rng.random((24, 4)) * [0.3, 0.3, 1.2, 8.0]).astype(np.float32)
    weights = rng.random(24).astype(np.float32)
    weights /= weights.sum()
    mask = np.ones(N, np.uint8)
    mask[: 16 * 40] = 0                      # whole packets outside the beam
    mask[16 * 50 + 3] = 0                    # one pixel of a packet
    out = dev.scratch(N * 4)
    k = dev.kernel(kernel)
    for w in (0.0, 0.37, 1.0):
        args = (dev.upload(a), dev.upload(b), np.float32(w), dev.upload(mask), dev.upload(weights), dev.upload(mu),
                np.int32(24))
        if kernel == "polychromatic_packet":
            k(dev.queue, (-(-N // 16),), None, *args, np.int32(N), out)
        else:
            k(dev.queue, (N,), None, *args, out)
        got = dev.download(out, np.empty(N, np.float32))
        truth = transmission_f64((1.0 - w) * a.astype(np.float64) + w * b.astype(np.float64), mu, weights) * mask
        np.testing.assert_allclose(got, truth, rtol=2e-6, atol=1e-30)
        assert np.all(got[mask == 0] == 0.0)


def test_packet_noise_draws_what_one_pixel_per_work_item_draws(dev):
    """Same seed, same pixel: the same count, in both regimes (Knuth below 30 photons, normal
    above) and with both in one packet."""
    rng = np.random.default_rng(5)
    n0 = 1000.0
    lam = np.where(rng.random(N) < 0.5, rng.random(N) * 40.0, 30.0 + rng.random(N) * 3000.0)
    image = (lam / n0).astype(np.float32)
    results = []
    for name in ("quantum_noise_packet", "quantum_noise"):
        buf = dev.upload(image.copy(), writable=True)
        size = -(-N // 16) if name.endswith("packet") else N
        tail = (np.int32(N),) if name.endswith("packet") else ()
        dev.kernel(name)(dev.queue, (size,), None, buf, np.float32(n0), np.uint32(77), *tail)
        results.append(dev.download(buf, np.empty(N, np.float32)))
    np.testing.assert_allclose(results[0], results[1], rtol=1e-5, atol=1e-6)


def test_packet_noise_is_poisson_where_lanes_of_one_packet_differ(dev):
    """Alternate pixels expect 2 and 500 photons: the low lanes go through the packet's masked
    Knuth loop while their neighbours do not; each set has Poisson's mean, variance and
    probability of no photon at all."""
    n, n0 = 16 * 20000, 1000.0
    lam = np.where(np.arange(n) % 2 == 0, 2.0, 500.0)
    buf = dev.upload((lam / n0).astype(np.float32), writable=True)
    dev.kernel("quantum_noise_packet")(dev.queue, (n // 16,), None, buf, np.float32(n0), np.uint32(11), np.int32(n))
    counts = dev.download(buf, np.empty(n, np.float32)) * n0
    low, high = counts[0::2], counts[1::2]
    np.testing.assert_allclose(low, np.rint(low), atol=1e-3)            # whole photons
    assert low.mean() == pytest.approx(2.0, abs=4 * math.sqrt(2.0 / low.size))
    assert low.var() == pytest.approx(2.0, rel=0.03)
    assert (np.rint(low) == 0).mean() == pytest.approx(math.exp(-2.0), abs=0.005)
    assert high.mean() == pytest.approx(500.0, abs=4 * math.sqrt(500.0 / high.size))
    assert high.std() == pytest.approx(math.sqrt(500.0), rel=0.02)


@pytest.mark.parametrize("invert", [False, True])
def test_display_knee_in_closed_form_is_the_two_hyperbolas_and_identity(invert):
    """to_display's one-formula knee against soft_knee's three branches, far past both ends too."""
    from types import SimpleNamespace

    from appliance.xray.display_lut import soft_knee, to_display

    rng = np.random.default_rng(2)
    p = rng.uniform(-30.0, 30.0, (64, 80)).astype(np.float32)
    edge = rng.random((64, 80)).astype(np.float32)
    edge[:, :5] = 0.0
    chain = SimpleNamespace(display_knee=0.15)
    centre, width = 1.3, 2.5
    x = (p.astype(np.float64) - centre) / width + 0.5
    grey = soft_knee(x, 0.15).astype(np.float64)
    truth = ((1.0 - grey) if invert else grey) * edge
    got = to_display(p, edge, chain, invert, centre, width)
    np.testing.assert_allclose(got, truth, atol=2e-6)
    assert np.all(got[:, :5] == 0.0)
    assert 0.0 < got[:, 5:].min() and got.max() < 1.0
