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


def test_a_paced_clock_waits_for_the_screen_and_skips_the_wait():
    """x6 paced at 2 s: it runs 2 simulated seconds (1/3 s of wall time) past the last image, then
    stands; the next image lets it run on from where it stood, with no jump."""
    from appliance.daemon.clock import SimClock
    wall = [100.0]
    clock = SimClock(6.0, base=lambda: wall[0], pace_s=2.0)
    wall[0] = 100.1
    assert clock() == pytest.approx(100.6)          # within the pace: x6
    wall[0] = 101.0
    assert clock() == pytest.approx(102.0)          # stood 2 s past the image at 100.0
    wall[0] = 103.0
    assert clock() == pytest.approx(102.0)
    clock.shown()
    assert clock() == pytest.approx(102.0)          # no jump when the image comes
    wall[0] = 103.2
    assert clock() == pytest.approx(103.2)          # x6 again: 0.2 s of wall time
    clock.shown()                                   # images in time: never paused
    wall[0] = 103.3
    clock.shown()
    wall[0] = 103.5
    assert clock() == pytest.approx(103.2 + 0.3 * 6)
    unpaced = SimClock(6.0, base=lambda: wall[0])
    wall[0] = 200.0
    assert unpaced() == pytest.approx(103.5 + (200.0 - 103.5) * 6)
    with pytest.raises(ValueError):
        SimClock(6.0, pace_s=0)
