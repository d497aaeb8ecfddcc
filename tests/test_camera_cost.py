"""The synthetic webcam's cheap paths: a sensor noise pool that is still fresh Gaussian noise on
every frame, and a box drawn and blurred only where it can reach, with no trace left behind."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivers.camera_scene import RenderSettings, SceneRenderer, _covers, box_marker_quads

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
W, H = 1280, 720
BACKGROUND = 70.0
BOX_MM = (120.0, 80.0, 60.0)


def _pose(rx_deg, ry_deg, t):
    R = cv2.Rodrigues(np.radians([rx_deg, ry_deg, 0.0]))[0] @ np.diag([1.0, -1.0, -1.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _backdrop():
    """The room behind the box as RenderSettings describes it: a bilinear gradient, which a
    symmetric blur leaves as it is away from the image's edges."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return BACKGROUND * (0.8 + 0.4 * xx / W) * (0.9 + 0.2 * yy / H)


def _box_renderer(settings):
    T_top = np.eye(4)
    T_top[2, 3] = BOX_MM[2] / 2                      # a marker printed on the top face
    quads = box_marker_quads([3], [T_top], 40.0, "DICT_4X4_50", settings)
    return SceneRenderer(K, (0.0,) * 5, W, H, BOX_MM, quads, settings, seed=11)


def test_sensor_noise_is_fresh_gaussian_noise_on_every_frame():
    sigma = 2.0
    r = SceneRenderer(K, (0.0,) * 5, W, H, None, [], RenderSettings(noise_sigma=sigma, background=BACKGROUND), seed=5)
    T = _pose(0, 0, [0.0, 0.0, 500.0])
    inner = (slice(8, H - 8), slice(8, W - 8))
    truth = _backdrop()[inner]
    residuals = [r.render(T).astype(np.float64)[inner] - truth for _ in range(6)]
    # Rounding to whole grey levels adds a uniform error of variance 1/12.
    expected_sd = np.sqrt(sigma**2 + 1 / 12)
    n = residuals[0].size
    for e in residuals:
        assert abs(e.mean()) < 4 * expected_sd / np.sqrt(n)
        assert e.std() == pytest.approx(expected_sd, rel=0.01)
        assert np.mean(np.abs(e) < expected_sd) == pytest.approx(0.683, abs=0.01)   # Gaussian, not uniform
        # White: a pixel's noise says nothing of its neighbour's.
        assert abs(np.corrcoef(e[:, 1:].ravel(), e[:, :-1].ravel())[0, 1]) < 0.01
    # Consecutive frames (the first drawn whole, the rest from the pool at random offsets) do not
    # share their noise pixel for pixel; 0.01 is over four standard errors at this many pixels.
    for a, b in zip(residuals, residuals[1:]):
        assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.01


def test_a_box_drawn_in_its_own_region_leaves_no_trace_of_the_frame_before():
    settings = RenderSettings(noise_sigma=0.0, background=BACKGROUND)
    near = _pose(20, -15, [60.0, -40.0, 400.0])
    far = _pose(-10, 25, [-150.0, 90.0, 900.0])
    moving = (_pose(-10, 25, [-156.0, 90.0, 900.0]), _pose(-10, 25, [-144.0, 90.0, 900.0]))
    seen = _box_renderer(settings)
    seen.render(near)                                # a large box first, then a small one elsewhere
    after = seen.render(far, moving).astype(np.float64)
    fresh = _box_renderer(settings).render(far, moving).astype(np.float64)
    np.testing.assert_array_equal(after, fresh)
    # A box whose region holds the last one's paints over all of it, leaving nothing to restore.
    over = _pose(-10, 25, [-80.0, 50.0, 350.0])
    last = seen._pasted
    np.testing.assert_array_equal(seen.render(over), _box_renderer(settings).render(over))
    assert last is not None and _covers(seen._pasted, last)
    # Away from where the far box can reach, the image is the bare backdrop, also where the near box was.
    x0, y0, x1, y1 = seen._extent(far)
    room = np.ones((H, W), bool)
    room[max(y0 - 20, 0):y1 + 20, max(x0 - 20, 0):x1 + 20] = False
    room[:8], room[-8:], room[:, :8], room[:, -8:] = False, False, False, False
    assert np.abs(after - np.round(_backdrop()))[room].max() <= 1.0
    # ... and the near box really was drawn over part of that room.
    nx0, ny0, nx1, ny1 = seen._extent(near)
    assert room[ny0:ny1, nx0:nx1].any()
    # The box itself is there: its top face, lit, beside the marker, is well above the backdrop.
    cx, cy = seen._project((far @ [50.0, 0.0, BOX_MM[2] / 2, 1.0])[None, :3])[0].round().astype(int)
    assert after[cy, cx] > 1.2 * _backdrop()[cy, cx]


def test_bench_tracking_refuses_a_part_it_does_not_have(capsys):
    from appliance.cli import main

    assert main(["bench", "tracking", "--parts", "speed,sped"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--parts" in err[0] and "sped" in err[0] and "speed" in err[0]
