"""FrameStats: frames per second and motion-to-photon latency against hand-worked numbers."""

from __future__ import annotations

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
    # The last second holds frames at 109.0 .. 110.0: 11 frames over a 1 s window.
    assert stats.fps(110.0) == pytest.approx(11.0)
    assert stats.fps(200.0) == 0.0
