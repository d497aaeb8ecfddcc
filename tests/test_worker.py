"""Worker: the heartbeat and the grace a knowingly long step takes."""

from __future__ import annotations

import pytest

from appliance.daemon.worker import Worker


def test_grace_covers_a_known_long_step():
    clock = [100.0]
    w = Worker("loader", lambda w: False, clock=lambda: clock[0])
    w.beat()
    clock[0] = 103.0
    assert w.stall_s() == pytest.approx(3.0)
    with w.grace(30.0):
        clock[0] = 120.0
        assert w.stall_s() == 0.0
        clock[0] = 140.0
        assert w.stall_s() == pytest.approx(7.0)  # the grace ran out at 133
    assert w.stall_s() == 0.0  # leaving the block beats
