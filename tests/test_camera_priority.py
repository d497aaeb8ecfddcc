"""The synthetic webcam's drawing thread runs at the lower priority it is given, read back from
the kernel's own record of the thread."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.camera import SyntheticCamera

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
T = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 500.0], [0, 0, 0, 1.0]])


def kernel_nice(tid: int) -> int:
    """The thread's nice value from /proc (field 19 of its stat line, after the command's parentheses)."""
    stat = Path(f"/proc/self/task/{tid}/stat").read_text()
    return int(stat[stat.rindex(")") + 2:].split()[16])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
@pytest.mark.parametrize("nice", [0, 7])
def test_the_drawing_thread_runs_nice_steps_below_its_starter(nice):
    base = os.getpriority(os.PRIO_PROCESS, 0)
    if base + nice > 19:
        pytest.skip(f"this process already runs at nice {base}: no room for {nice} more")
    cam = SyntheticCamera([7], [np.eye(4)], 50.0, "DICT_4X4_50", None, K, (0.0,) * 5, 320, 240, lambda t: T,
                          fps=100.0, seed=1, nice=nice)
    with cam:
        assert cam.wait(-1, 5.0) is not None
        assert cam._thread is not None and cam._thread.native_id is not None
        assert kernel_nice(cam._thread.native_id) == base + nice
        assert cam.thread_nice == base + nice
    assert os.getpriority(os.PRIO_PROCESS, 0) == base           # the starter's own priority is untouched
