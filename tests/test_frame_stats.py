"""FrameStats: frames per second and motion-to-photon latency against hand-worked numbers."""

from __future__ import annotations

import numpy as np
import pytest


def test_frame_stats_against_hand_worked_numbers():
    from appliance.daemon.frame_stats import FrameStats
    stats = FrameStats(window_s=1.0)
    # 101 frames 0.1 s apart (10 fps), latency k ms for frame k (k = 0..100).
    for k in range(101):
        stats.add(100.0 + 0.1 * k, k / 1000)
    s = stats.summary()
    assert s["frames"] == 101
    assert s["fps"] == pytest.approx(10.0)
    assert s["latency_median_ms"] == pytest.approx(50.0)
    assert s["latency_p99_ms"] == pytest.approx(99.0)
    # The last second holds frames at 109.0 .. 110.0: 10 intervals of 0.1 s, 10 fps.
    assert stats.fps(110.0) == pytest.approx(10.0)
    assert stats.fps(200.0) is None          # nothing shown for a while: no rate to tell


def test_the_first_frames_of_a_run_read_their_true_rate():
    """The first wave showed "0 fps" on the first live frame (one frame over a 2 s window)."""
    from appliance.daemon.frame_stats import FrameStats, fps_text
    stats = FrameStats(window_s=2.0)
    stats.add(5.0, 0.05)
    assert stats.fps(5.0) is None and fps_text(None).strip() == "-- fps"
    stats.add(5.04, 0.05)                    # 25 fps from the second frame on
    assert stats.fps(5.04) == pytest.approx(25.0)
    assert fps_text(stats.fps(5.04)) == "25.0 fps"


def test_the_rate_while_exposing_counts_continuous_frames_within_their_runs_only():
    """Hand-worked: run 1, continuous, 1 s of frames at 10 fps; the pedal up for 3 s; run 2, 1 s
    at 20 fps with one 0.4 s stall in it (the appliance's, so it counts); run 3 pulsed at 7.5
    pulses a second for 2 s. Exposing continuously: (10 + 19) intervals over 1 + 1.3 s."""
    from appliance.daemon.frame_stats import FrameStats
    stats = FrameStats()
    for k in range(11):
        stats.add(0.1 * k, 0.05, continuous_run=1)
    run2 = [4.0 + 0.05 * k for k in range(10)] + [4.45 + 0.4 + 0.05 * k for k in range(10)]   # 4.0 .. 5.3 s
    for t in run2:
        stats.add(t, 0.05, continuous_run=2)
    pulsed = [6.0 + k / 7.5 for k in range(1, 16)]          # 6.133 .. 8.0 s
    for t in pulsed:
        stats.add(t, 0.05)
    s = stats.summary()
    assert s["fps_exposing"] == pytest.approx((10 + 19) / (1.0 + 1.3))
    assert s["frames"] == 11 + 20 + 15
    assert s["fps"] == pytest.approx((11 + 20 + 15 - 1) / 8.0)
    empty = FrameStats()
    empty.add(1.0, 0.05)
    empty.add(1.1, 0.05)                                      # pulsed only: no continuous rate
    assert np.isnan(empty.summary()["fps_exposing"])
