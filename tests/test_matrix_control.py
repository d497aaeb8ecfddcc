"""The moving matrix's controller on hand-worked frame-time sequences: its ladder, a step down
over the budget, a step up only where the larger matrix is predicted to fit, no hunting on a
machine whose frame time is a fixed part plus a part per pixel, and the profile's checks."""

import numpy as np
import pytest
from pydantic import ValidationError

from appliance.config.rendering import Rendering
from appliance.xray.matrix_control import MatrixController, matrix_ladder

LADDER = Rendering(moving_matrix_px=256, moving_matrix_min_px=128, moving_matrix_step_px=32,
                   frame_budget_ms=40.0, matrix_window_frames=3, matrix_step_up_margin=0.8)


def feed(control: MatrixController, times_ms: list[float]) -> list[int | None]:
    """Each frame at the matrix the controller gives; the matrix after each."""
    out = []
    for t in times_ms:
        out.append(control.observe(control.matrix, t / 1000.0))
    return out


def test_the_ladder_runs_from_the_moving_matrix_down_to_the_minimum():
    assert matrix_ladder(LADDER, 512) == [256, 224, 192, 160, 128]
    # A minimum off the steps is the last rung itself.
    assert matrix_ladder(LADDER.model_copy(update=dict(moving_matrix_min_px=140)), 512) == [256, 224, 192, 160, 140]
    # Without a minimum, one moving matrix (the fixed one of before); none at or above the full matrix.
    assert matrix_ladder(Rendering(moving_matrix_px=256), 512) == [256]
    assert matrix_ladder(LADDER, 256) == []
    assert MatrixController(Rendering(), 512).matrix is None


def test_a_median_over_the_budget_steps_down_one_rung_at_a_time():
    c = MatrixController(LADDER, 512)
    assert c.matrix == 256
    # Medians of three: 48 ms > 40 ms, one rung down only after the third frame.
    assert feed(c, [50, 45, 48]) == [256, 256, 224]
    # A frame begun at the old matrix before the step does not count for the new one.
    assert c.observe(256, 0.300) == 224
    # One slow frame among fast ones is not the median. The window slides: the medians of
    # (39, 90, 38), (90, 38, 37), (38, 37, 41) are 39, 38, 38 ms; of (37, 41, 42), 41 ms > 40.
    assert feed(c, [39, 90, 38, 37, 41, 42]) == [224, 224, 224, 224, 224, 192]
    assert c.steps == [(256, 224), (224, 192)]


def test_a_step_up_needs_the_larger_matrix_predicted_within_the_margin():
    c = MatrixController(LADDER, 512)
    feed(c, [50, 50, 50])
    assert c.matrix == 224
    # 25 ms at 224 predicts 25 x (256/224)^2 = 32.65 ms at 256, over 0.8 x 40 = 32 ms: stay.
    assert feed(c, [25, 25, 25]) == [224, 224, 224]
    # 24 ms predicts 31.35 ms: within the margin, one rung up once it is the median, at the
    # second 24 ms frame (the window slides: 25, 24, 24).
    assert feed(c, [24, 24, 24]) == [224, 256, 256]
    # At the top there is nothing larger; fast frames keep it there.
    assert feed(c, [5, 5, 5]) == [256, 256, 256]
    assert c.steps == [(256, 224), (224, 256)]


def test_always_over_the_budget_it_rests_at_the_smallest_matrix():
    c = MatrixController(LADDER, 512)
    matrices = feed(c, [100.0] * 30)
    assert matrices[-1] == 128 and c.steps == [(256, 224), (224, 192), (192, 160), (160, 128)]
    # Three frames per rung: each step starts its count again.
    assert [i for i in range(1, 30) if matrices[i] != matrices[i - 1]] == [2, 5, 8, 11]


def test_it_settles_without_hunting_and_climbs_back_when_the_machine_frees_up():
    """Frame time = a + b x pixels, with +-5 % noise. a = 12 ms, b such that 256 takes 52 ms:
    224 takes 12 + 40 x (224/256)^2 = 42.6 ms (over), 192 takes 12 + 22.5 = 34.5 ms (under);
    192 -> 224 is predicted 34.5 x (224/192)^2 = 47.0 ms, over 32 ms: it stays at 192."""
    rng = np.random.default_rng(7)
    c = MatrixController(LADDER.model_copy(update=dict(matrix_window_frames=6)), 512)

    def run(a_ms, b_ms_per_px2, frames):
        out = []
        for _ in range(frames):
            n = c.matrix
            out.append(c.observe(n, (a_ms + b_ms_per_px2 * n * n) * rng.uniform(0.95, 1.05) / 1000.0))
        return out

    busy = run(12.0, 40.0 / 256**2, 300)
    assert busy[-1] == 192 and c.steps == [(256, 224), (224, 192)]
    assert all(m == 192 for m in busy[12:])
    # The machine frees up: a = 2 ms, b halved. 192 takes 13.3 ms, predicted 18.0 ms at 224 and
    # then 17.3 x (256/224)^2 = 22.6 ms at 256, both within 32 ms: back to the top and held.
    free = run(2.0, 20.0 / 256**2, 100)
    assert free[-1] == 256 and c.steps[2:] == [(192, 224), (224, 256)]
    assert all(m == 256 for m in free[12:])


@pytest.mark.parametrize("fields, says", [
    (dict(moving_matrix_px=128, moving_matrix_min_px=256), "must not exceed moving_matrix_px"),
    (dict(moving_matrix_min_px=128), "needs moving_matrix_px"),
    (dict(moving_matrix_px=256, matrix_step_up_margin=1.0), "less than 1"),
    (dict(moving_matrix_px=256, frame_budget_ms=0), "greater than 0"),
    (dict(rest_matrix_px=512), r"rest_matrix_px \(512\) needs refine_bands"),
    (dict(rest_hold_px=0.25), r"rest_hold_px \(0.25\) must exceed cache_pose_tolerance_px \(0.25\)"),
])
def test_the_profile_refuses_a_ladder_that_cannot_be(fields, says):
    with pytest.raises(ValidationError, match=says):
        Rendering(**fields)
