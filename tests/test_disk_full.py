"""A full or refusing disk: side tasks fail quietly, dose recording keeps what it has.

Where this machine lets the test mount a 1 MiB tmpfs (root in a container or VM) the disk is
really full (ENOSPC from the kernel); elsewhere those tests skip and say why.
"""

from __future__ import annotations

import subprocess
from types import SimpleNamespace

import numpy as np
import pytest

from appliance.daemon.snapshots import Moment, Snapshotter


def frame():
    return SimpleNamespace(rgb_source=lambda: np.zeros((8, 8, 3), np.uint8), state=SimpleNamespace(alarm_sounding=False))


def test_a_snapshot_the_disk_refuses_never_reaches_the_renderer(tmp_path, caplog):
    blocker = tmp_path / "data"
    blocker.write_text("a file where the snapshots folder should be")
    snapper = Snapshotter(blocker / "snapshots", [Moment("first", "first image", lambda f: True)])
    for _ in range(3):
        snapper(frame())                   # raises nothing into the render worker
    assert snapper.failures == 1           # tried once, then waits RETRY_S before the next try
    assert snapper.problem and "snapshots" in snapper.problem
    assert len([r for r in caplog.records if "snapshot not written" in r.getMessage()]) == 1
    # Space returns: the next try after the wait writes it.
    blocker.unlink()
    blocker.mkdir()
    snapper._retry_at = 0.0
    snapper(frame())
    assert snapper.taken["first"].is_file() and snapper.problem is None


@pytest.fixture
def full_disk(tmp_path):
    """A 1 MiB tmpfs filled to its last block."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mnt)], capture_output=True)
    if result.returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root); the full-disk tests use a real full file system")
    try:
        with open(mnt / "filler", "wb") as f:
            try:
                while True:
                    f.write(b"\0" * 65536)
                    f.flush()
            except OSError:
                pass
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_snapshot_on_a_really_full_disk(full_disk):
    snapper = Snapshotter(full_disk / "snapshots", [Moment("first", "first image", lambda f: True)])
    snapper(frame())
    assert snapper.failures == 1 and "No space left on device" in (snapper.problem or "")
    assert "first" not in snapper.taken


def test_ledger_on_a_full_disk_opens_when_space_returns(full_disk):
    """`run` on a full disk: the ledger cannot open, the events wait in memory, then all are written."""
    from appliance.console.state import ConsoleEvent
    from appliance.errors import FluorosimError
    from appliance.records.deferred_ledger import DeferredLedger, open_ledger
    from appliance.records.ledger import open_readonly, verify

    path = full_disk / "ledger.sqlite"
    ledger = open_ledger(path)
    assert isinstance(ledger, DeferredLedger) and "the disk is full" in ledger.problem
    events = [ConsoleEvent(1.0, "fluoro_on"),
              ConsoleEvent(31.0, "fluoro_off", {"start_t": 1.0}, 30.0, 4.0, 0.4, 30.0, 4.0, 0.4)]
    with pytest.raises(FluorosimError, match="the disk is full"):
        ledger.start_session("trainee", "case", "C-arm", t_wall=1_700_000_000.0, t_monotonic=0.0)
    (full_disk / "filler").unlink()     # an admin frees space
    ledger.start_session("trainee", "case", "C-arm", t_wall=1_700_000_000.0, t_monotonic=0.0)
    ledger.record(events)
    ledger.end_session(t_wall=1_700_000_040.0)
    ledger.close()
    conn = open_readonly(path)
    row = conn.execute("SELECT fluoro_time_s, air_kerma_mgy, runs FROM sessions").fetchone()
    assert tuple(row) == (30.0, 4.0, 1) and verify(conn).ok
    conn.close()
