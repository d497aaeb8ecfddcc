"""The latency breakdown by stage against hand-worked time stamps."""

from __future__ import annotations

import pytest


def stamps(t0: float, k: int):
    from appliance.daemon.stage_times import FrameStamps
    # Frame k: capture 2 ms, tracking 10 ms of which the filter 0.5 ms, pose wait k ms, render
    # 40 ms, overlay 1 ms, compose 12 ms, write 3 ms.
    t_picked = t0 + 0.002
    t_tracked = t_picked + 0.010
    t_render = t_tracked + k / 1000
    t_rendered = t_render + 0.040
    t_compose = t_rendered + 0.001
    t_composed = t_compose + 0.012
    return FrameStamps(t0, t_picked, t_tracked, 0.0005, t_render, t_rendered, t_compose, t_composed, t_composed + 0.003)


def test_stages_add_up_to_the_latency_and_read_their_hand_worked_medians():
    from appliance.daemon.stage_times import STAGES, StageTimes, breakdown_text
    times = StageTimes()
    for k in range(101):                      # pose waits of 0 .. 100 ms
        times.add(stamps(100.0 + k, k))
    one = stamps(7.0, 30)
    assert sum(one.durations()) == pytest.approx(one.t_shown - one.t_frame, abs=1e-12)
    s = times.summary()
    assert list(s) == list(STAGES)
    want = {"capture": 2.0, "tracking": 9.5, "pose filter": 0.5, "pose wait": 50.0, "render": 40.0,
            "overlay": 1.0, "compose": 12.0, "write": 3.0}
    for stage, ms in want.items():
        assert s[stage][0] == pytest.approx(ms, abs=1e-6), stage
    assert s["pose wait"][1] == pytest.approx(99.0, abs=1e-6)     # p99 of 0..100 ms
    # Only the frames shown from `since` on: frames 60 .. 100, pose waits 60 .. 100 ms, median 80.
    late = times.summary(since=160.0)
    assert late["pose wait"][0] == pytest.approx(80.0, abs=1e-6)
    assert times.summary(since=1e9) == {}
    assert breakdown_text(s).startswith("capture 2.0/2, tracking 9.5/10, pose filter 0.5/0, pose wait 50.0/99")


def test_the_median_and_p99_of_a_skewed_stage_and_the_frames_kept():
    """Pose waits 0, 0, 0, 0 and 100 ms: median 0 (the mean would be 20); p99 by linear
    interpolation between the 4th and 5th of the sorted five, at 0.99 x 4 = 3.96: 96 ms. A frame
    shown exactly at `since` counts ("at or after"). Keeping 3 frames, the last three count."""
    from appliance.daemon.stage_times import StageTimes
    times = StageTimes()
    rows = [stamps(10.0 * n, k) for n, k in enumerate((0, 0, 100, 0, 0))]
    for row in rows:
        times.add(row)
    s = times.summary()
    assert s["pose wait"] == pytest.approx((0.0, 96.0), abs=1e-6)
    assert s["render"] == pytest.approx((40.0, 40.0), abs=1e-6)
    at = times.summary(since=rows[2].t_shown)          # frames 2, 3, 4: waits 100, 0, 0
    assert at["pose wait"] == pytest.approx((0.0, 98.0), abs=1e-6)
    kept = StageTimes(keep=3)
    for row in rows:
        kept.add(row)
    assert kept.summary()["pose wait"] == pytest.approx((0.0, 98.0), abs=1e-6)
    assert kept.summary(since=rows[3].t_shown)["pose wait"] == pytest.approx((0.0, 0.0), abs=1e-6)
