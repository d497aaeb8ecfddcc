"""The progressive renderer's use of the matrix controller and the slab cache
(appliance/xray/progressive.py): each moving cast's time is counted once, and the slab copies
of the phases it moves between are kept as the profile says (rendering.slab_phases).

Ground truth: frame counts kept by hand. A window of 3 frames over a 40 ms budget steps down
only after three moving casts were timed over it; two phases moved between, with room for 4
copies, are copied twice however often the view returns to each.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.config.case import Materials
from appliance.config.rendering import Rendering
from appliance.geometry import make_transform
from appliance.xray.bench import flat_profile
from appliance.xray.progressive import ProgressiveRenderer
from appliance.xray.renderer import Renderer, View
from appliance.xray.truth.analytic import box_volume


@pytest.fixture(scope="module")
def renderer():
    return Renderer(flat_profile(128), Materials(), device="cpu")


def pose(i: int) -> np.ndarray:
    return make_transform(np.eye(3), [4.0 + i, -3.0, 700.0])      # 1 mm further each frame: moving


def test_each_moving_cast_is_timed_once(renderer):
    prepared = renderer.prepare(box_volume((24, 24, 24), (3.0, 3.0, 3.0), (6, 6, 6), (17, 17, 17))[0])
    t = [100.0]
    settings = Rendering(moving_matrix_px=96, moving_matrix_min_px=64, moving_matrix_step_px=32,
                         frame_budget_ms=40.0, matrix_window_frames=3, settle_s=0.5)
    pr = ProgressiveRenderer(renderer, settings, clock=lambda: t[0])
    view = View(seed=1, noise=False)
    t[0] += 0.04
    pr.render(prepared, pose(0), view)
    assert pr.matrix == 96
    # The frame shown again (the screen refreshed, no new cast): still one frame of three.
    for _ in range(3):
        pr.frame_shown(0.100)
    assert pr.control.steps == []
    # Two more moving casts over the budget make three: one rung down.
    for i in (1, 2):
        t[0] += 0.04
        pr.render(prepared, pose(i), view)
        pr.frame_shown(0.100)
    assert pr.control.steps == [(96, 64)]
    # The pose stays: it keeps the 96 matrix its last cast was at, served from that cast (no new
    # one at 64); the next moving cast is at the controller's 64.
    counts = pr.cache(pr._movers[96]).counts
    casts, hits = counts.casts, counts.hits
    t[0] += 0.04
    pr.render(prepared, pose(2), view)
    assert pr.matrix == 96 and (counts.casts, counts.hits) == (casts, hits + 1)
    t[0] += 0.04
    pr.render(prepared, pose(3), view)
    assert pr.matrix == 64


def test_the_slab_copies_of_the_phases_moved_between_are_kept(renderer):
    first = renderer.prepare(box_volume((48, 64, 64), (1.5, 1.25, 2.5), (9, 14, 6), (52, 47, 40))[0])
    second = renderer.prepare(box_volume((48, 64, 64), (1.5, 1.25, 2.5), (11, 14, 6), (54, 47, 40))[0])
    t = [100.0]
    pr = ProgressiveRenderer(renderer, Rendering(moving_matrix_px=64, settle_s=0.1, slab_max_shift_px=1.0,
                                                 slab_phases=4), clock=lambda: t[0])
    view = View(seed=1, noise=False)
    for i in range(6):
        t[0] += 0.04
        pr.render(first if i % 2 == 0 else second, pose(i), view)
    assert pr.slab_casts == 6 and pr.slabs is not None and pr.slabs.made == 2
