"""The moving matrix's profile at its edges (rendering.moving_matrix_*, matrix_window_frames),
beside the controller's sequences (tests/test_matrix_control.py): a ladder of one rung, and the
shipped default window riding out a single slow frame.

Ground truth: ladders and medians worked by hand.
"""

from __future__ import annotations

from appliance.config.rendering import Rendering
from appliance.xray.matrix_control import MatrixController, matrix_ladder


def test_a_minimum_equal_to_the_moving_matrix_is_a_ladder_of_one_rung():
    one = Rendering(moving_matrix_px=128, moving_matrix_min_px=128)
    assert matrix_ladder(one, 512) == [128]
    c = MatrixController(one, 512)
    for _ in range(12):                      # always over the budget: nowhere lower to go
        c.observe(128, 0.5)
    assert c.matrix == 128 and c.steps == []


def test_one_slow_frame_among_fast_ones_does_not_change_the_matrix_by_default():
    """A hiccup (100 ms, a page fault or another process) among frames of 30 ms, under the 40 ms
    budget: the median of any window of several frames is 30 ms, so the matrix stays."""
    c = MatrixController(Rendering(moving_matrix_px=256, moving_matrix_min_px=128), 512)
    for t_ms in [30, 30, 100, 30, 30, 30, 30, 30, 30, 30]:
        c.observe(c.matrix, t_ms / 1000.0)
    assert c.steps == [] and c.matrix == 256
