"""PoseDemand: which camera frames the renderer could still take, on a hand-worked timeline."""

from appliance.daemon.pose_demand import PoseDemand


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_frames_superseded_before_the_renderer_is_free_are_not_wanted():
    clock = Clock()
    demand = PoseDemand(frame_period_s=0.033, clock=clock)
    assert demand.wanted()                         # nothing known yet: every frame
    for start in (0.0, 1.0, 2.0):                  # three renders of 200 ms, tracking 10 ms
        demand.rendering(start)
        demand.tracked(0.010)
        demand.rendered(start, start + 0.200)
    assert demand.wanted()                         # idle: every frame is wanted
    demand.rendering(10.0)                         # expected free at 10.200
    # A frame in hand is wanted once it can be the newest when the renderer is free: from
    # 10.200 - 0.033 (one period: no newer frame will come in time) - 0.010 (its tracking) = 10.157.
    clock.t = 10.150
    assert not demand.wanted()
    clock.t = 10.158
    assert demand.wanted()
    # A frame the webcam would need 20 ms to draw is wanted 20 ms earlier.
    clock.t = 10.140
    assert not demand.wanted()
    assert demand.wanted(ahead_s=0.020)
    # The render ends early: from then on every frame is wanted again.
    clock.t = 10.100
    demand.rendered(10.0, 10.100)
    assert demand.wanted()


def test_the_expected_render_time_is_the_median_of_the_recent_ones():
    clock = Clock()
    demand = PoseDemand(frame_period_s=0.040, clock=clock)
    for i, seconds in enumerate((0.1, 0.1, 5.0, 0.1, 0.1)):    # one stall does not move it
        demand.rendering(float(i))
        demand.rendered(float(i), i + seconds)
    demand.rendering(100.0)
    clock.t = 100.0 + 0.1 - 0.040 - 0.001
    assert not demand.wanted()
    clock.t = 100.0 + 0.1 - 0.040 + 0.001
    assert demand.wanted()


def test_the_synthetic_webcam_draws_only_the_frames_wanted():
    """A real SyntheticCamera at 200 fps told that no frame is wanted after its first (a
    renderer busy for ever): it draws the first and then none, counting the frame times it let
    pass; told yes again, it draws at once."""
    import time

    import numpy as np

    from drivers.camera import SyntheticCamera

    K = np.array([[900.0, 0, 160], [0, 900.0, 120], [0, 0, 1]])
    T = np.eye(4)
    T[2, 3] = 500.0
    asked = []
    answer = [False]

    def wanted(draw_s):
        asked.append(draw_s)
        return answer[0]
    cam = SyntheticCamera([7], [np.eye(4)], 40.0, "DICT_4X4_50", None, K, (0.0,) * 5, 320, 240, lambda t: T,
                          fps=200.0, seed=1)
    cam.wanted = wanted
    with cam:
        first = cam.wait(-1, 5.0)
        assert first is not None
        time.sleep(0.1)                            # 20 frame times
        assert cam.frames_captured == 1 and cam.frames_skipped >= 5
        assert asked and asked[-1] > 0.0           # it offers its own drawing time as the lead
        answer[0] = True
        assert cam.wait(first.seq, 2.0) is not None
