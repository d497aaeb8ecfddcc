"""The latency breakdown by stage: against hand-worked time stamps, and in the running
appliance against sleeps added to its stages."""

from __future__ import annotations

import time

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


#: Sleeps added to the appliance's own stages (s), each in the one stage it belongs to; spaced so
#: that time moved from one stage into another shows. The stages left alone (capture, pose
#: filter, pose wait) are given none.
ADDED_S = {"tracking": 0.015, "render": 0.030, "overlay": 0.008, "compose": 0.045, "write": 0.060}
#: What a stage's median may take beyond its sleep: the stage's own work (a 64-pixel render, a
#: 320 x 256 screen) on a loaded two-core machine (ms).
OWN_WORK_MS = 25.0


def slowed(call, seconds: float):
    def slow(*args, **kwargs):
        time.sleep(seconds)
        return call(*args, **kwargs)
    return slow


def test_each_stage_of_the_running_appliance_holds_the_time_added_to_it_and_no_other(tmp_path):
    """The appliance run for real (tiny CT, the pedal held), with a known sleep added to its
    tracking, its render, what is done between image and compositor (the banners), the
    compositor and the display's write: each of those stages' median lies within OWN_WORK_MS
    above its sleep, and the stages with no sleep stay above 0. A stamp passed in
    another's slot (two swapped, one passed twice) moves a sleep into a neighbour or makes a
    stage negative."""
    from appliance_setup import make_appliance

    from appliance.daemon.notify import Notifier
    from appliance.daemon.pipeline import Appliance
    from appliance.daemon.reload import ProfileKeeper

    app = Appliance(ProfileKeeper(make_appliance(tmp_path)), Notifier({}))
    parts = app.parts
    parts.tracker.track = slowed(parts.tracker.track, ADDED_S["tracking"])
    parts.renderer.render = slowed(parts.renderer.render, ADDED_S["render"])
    parts.compositor.compose = slowed(parts.compositor.compose, ADDED_S["compose"])
    parts.display.show = slowed(parts.display.show, ADDED_S["write"])
    app.render.banners = slowed(app.render.banners, ADDED_S["overlay"])
    warm: list[float] = []

    def until() -> bool:
        # From the third live frame on (the first build kernels and tables), 7 frames.
        shown = app.stats.shown_at
        if len(shown) >= 3 and not warm:
            warm.append(shown[2])
        return len(shown) >= 9
    app.run(until=until, signals=False)
    s = app.render.stages.summary(since=warm[0])
    assert s, "no live frame was shown"
    for stage, added in ADDED_S.items():
        median_ms = s[stage][0]
        assert added * 1000 <= median_ms <= added * 1000 + OWN_WORK_MS, (stage, s)
    # Each is stamped after the one before it: never exactly 0, as a stamp passed twice would make
    # it. "pose wait" holds the pose while the frame before it renders (up to a frame's sleeps,
    # about 160 ms, longer on a loaded machine), so the upper bound is only a sanity bound: a sleep
    # moved into one of these stages has already left its own stage under its lower bound above.
    for stage in ("capture", "pose filter", "pose wait"):
        assert 0.0 < s[stage][0] < 400.0, (stage, s)
