"""`bench e2e`'s native-matrix figure timed from the synthetic webcam's path standing still."""

from types import SimpleNamespace

import numpy as np

from appliance.daemon.bench import held_casts_text, native_after_stops, rests_after
from appliance.geometry import make_transform
from appliance.tracking.trajectory import Trajectory

A, B = make_transform(np.eye(3), [0, 0, 300]), make_transform(np.eye(3), [40, 0, 300])
# Still from 2 s to 5 s of each 10 s loop.
PATH = Trajectory.from_poses([0, 2, 5, 10], [A, B, B, A])


def test_each_stop_is_timed_to_the_first_full_matrix_within_it():
    camera = SimpleNamespace(trajectory=PATH, t0=100.0)
    # Stops at 102-105, 112-115 and 122-125 on the clock: the first full matrix 0.30 s into the
    # first (the second one then is not a new rest), 0.45 s into the second, none in the third.
    refined = [102.30, 103.0, 108.0, 112.45]
    assert native_after_stops(camera, refined, 100.0, 125.0) == (
        "median 375 ms, max 450 ms after the camera's path stood still (3 stops, 1 not refined before it moved on)")
    # A stop begun before `since` or not over by `until` is not counted.
    assert native_after_stops(camera, refined, 103.0, 124.0) == (
        "median 450 ms, max 450 ms after the camera's path stood still (1 stop)")


def test_no_figure_without_a_path():
    assert native_after_stops(SimpleNamespace(), [1.0], 0.0, 10.0) is None
    assert native_after_stops(SimpleNamespace(trajectory=PATH, t0=0.0), [], 0.0, 4.0) is None


def test_the_rest_figure_leaves_out_the_rests_before_the_measured_span():
    # Three rests: the full matrix 1.4 s after the warm-up's first (cold kernels), then 0.3 and
    # 0.5 s after two in the measured span, which begins at 12 s.
    renderer = SimpleNamespace(refined_after_s=[1.4, 0.3, 0.5], refined_at=[3.0, 20.3, 31.5])
    assert rests_after(renderer, 12.0) == [0.3, 0.5]
    assert rests_after(renderer, 0.0) == [1.4, 0.3, 0.5]
    assert rests_after(SimpleNamespace(), 12.0) == []


def test_the_held_view_figure_counts_the_measured_span_only():
    # Frames at a held view that cast a phase themselves at 5 s (warm-up), 20 s and 30 s, taking
    # 0.9, 0.04 and 0.06 s; casts ahead begun at 4, 21 and 25 s. The span begins at 12 s.
    renderer = SimpleNamespace(held_casts=[(5.0, 0.9), (20.0, 0.04), (30.0, 0.06)], prefetched_at=[4.0, 21.0, 25.0])
    assert held_casts_text(renderer, 12.0) == (
        "2 frames cast a phase within themselves (median 50 ms, max 60 ms to render); "
        "2 casts of coming phases begun beside the live frames")
    assert held_casts_text(renderer, 40.0) == (
        "no frame cast a phase within itself; 0 casts of coming phases begun beside the live frames")
    assert held_casts_text(SimpleNamespace(), 0.0) is None
