"""How long a test lets the appliance take to stop after SIGTERM.

The appliance promises 2 s (daemon/pipeline.py: SHUTDOWN_S for the workers, CLOSE_DEVICES_S for
the devices), budgets of waiting that hold where the machine has CPU to spare. On a machine
with more runnable processes than cores, wall time also counts the time it was not given the
CPU, and the bound that matters is the one systemd enforces: TimeoutStopSec of the unit, after
which it kills the service and the session is not ended cleanly. A hang is caught either way:
the hung waits under test are 30 s or unbounded.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "fluorosim.service"
PROMISE_S = 2.0


def unit_timeout_stop_s() -> float:
    """TimeoutStopSec of the shipped unit, in seconds (plain seconds or an "s"/"min" suffix)."""
    m = re.search(r"^TimeoutStopSec=(\d+(?:\.\d+)?)\s*(s|sec|min)?\s*$", UNIT.read_text(), re.M)
    assert m, f"{UNIT.name}: no TimeoutStopSec= line"
    return float(m.group(1)) * (60.0 if m.group(2) == "min" else 1.0)


def busy() -> bool:
    """More runnable processes than cores over the last minute."""
    return os.getloadavg()[0] > (os.cpu_count() or 1)


def stop_deadline_s(promise_s: float = PROMISE_S) -> float:
    """`promise_s` on a machine with CPU to spare, else the unit's TimeoutStopSec."""
    return unit_timeout_stop_s() if busy() else promise_s


def join_left_behind_sends(timeout_s: float = 30.0) -> None:
    """Wait for the shutdown's send threads (records_worker: "fluorosim-send-..."), which an
    appliance run in the test's own process leaves behind when their budget runs out, so what
    they record is in the queue before the test reads it, however loaded the machine."""
    import threading

    for thread in threading.enumerate():
        if thread.name.startswith("fluorosim-send-"):
            thread.join(timeout_s)
