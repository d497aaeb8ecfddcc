"""SimClock: the console's clock runs at daemon.clock_rate times the wall clock."""

from __future__ import annotations

import pytest


def test_sim_clock_runs_at_its_rate():
    from appliance.daemon.clock import SimClock
    wall = [50.0]
    clock = SimClock(6.0, base=lambda: wall[0])
    assert clock() == 50.0
    wall[0] = 60.0
    assert clock() == pytest.approx(50.0 + 60.0)
    assert clock.wall_s(30.0) == pytest.approx(5.0)
    with pytest.raises(ValueError):
        SimClock(0)
