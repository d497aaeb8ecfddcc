"""A full or refusing disk: side tasks fail quietly, dose recording keeps what it has.

Where this machine lets the test mount a 1 MiB tmpfs (root in a container or VM) the disk is
really full (ENOSPC from the kernel); elsewhere those tests skip and say why.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from appliance.daemon.snapshots import Moment, Snapshotter
from appliance.errors import FluorosimError


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


def test_records_worker_holds_the_session_until_the_disk_lets_it_be_written(full_disk):
    """The session begins on a full disk: its events wait in memory and are all written, with
    the session's own start time, once space returns; the dose totals are the events' sums."""
    import queue

    from appliance.console.state import ConsoleEvent
    from appliance.daemon.handoff import LatestValue, Recorded
    from appliance.daemon.records_worker import RecordsWorker
    from appliance.daemon.reload import ProfileKeeper
    from appliance.records.deferred_ledger import open_ledger
    from appliance.records.ledger import open_readonly, verify

    repo = Path(__file__).resolve().parents[1]
    keeper = ProfileKeeper(repo / "configs/appliance-demo.yaml", data_dir=full_disk)
    ledger = open_ledger(full_disk / "ledger.sqlite")
    events: queue.Queue = queue.Queue()
    clock = iter(range(100, 10_000)).__next__
    worker = RecordsWorker(ledger, keeper, None, lambda: float(clock()), events=events, shown=LatestValue(),
                           saves=LatestValue())
    worker.setup()                                   # on a full disk: no crash, a problem for the banner
    assert worker.session_id is None and "the disk is full" in worker.problem
    # Two runs: 12 s and 30 s, 1.5 and 4 mGy (hand-made increments; the totals are their sums).
    for ev in [ConsoleEvent(101.0, "fluoro_on"), ConsoleEvent(113.0, "fluoro_off", {}, 12.0, 1.5, 0.15, 12.0, 1.5, 0.15),
               ConsoleEvent(120.0, "fluoro_on"), ConsoleEvent(150.0, "fluoro_off", {}, 42.0, 5.5, 0.55, 30.0, 4.0, 0.4)]:
        events.put(Recorded(ev))
    worker.step()                                    # still full: held in memory
    assert worker.session_id is None and events.empty()
    (full_disk / "filler").unlink()
    worker.step()                                    # space returned: session opened, everything written
    assert worker.session_id == 1 and worker.problem is None
    worker.stop()
    worker.teardown()
    ledger.close()
    conn = open_readonly(full_disk / "ledger.sqlite")
    row = conn.execute("SELECT started_wall, fluoro_time_s, air_kerma_mgy, runs FROM sessions").fetchone()
    first_event = conn.execute("SELECT t_monotonic FROM events WHERE kind = 'session_start'").fetchone()[0]
    assert (row["fluoro_time_s"], row["air_kerma_mgy"], row["runs"]) == (42.0, 5.5, 2) and verify(conn).ok
    assert first_event == 100.0                     # the console time of the first try, not of the write
    conn.close()


def test_a_saved_image_leaves_the_ledger_its_reserve(full_disk, caplog):
    """On a nearly full disk a save press is recorded but its picture is not written: a freed MiB
    goes to the dose events, not to a PNG and DICOM of several MiB (the demo on a 4 MiB disk lost
    all 1657 of its events that way). The tmpfs holds 1 MiB, under the 16 MiB reserve."""
    import queue

    from appliance.console.state import Console, ConsoleEvent
    from appliance.daemon.handoff import LatestValue, Recorded, ShownImage
    from appliance.daemon.records_worker import RecordsWorker
    from appliance.daemon.reload import ProfileKeeper
    from appliance.records.deferred_ledger import open_ledger
    from appliance.records.ledger import open_readonly, verify

    (full_disk / "filler").unlink()                 # space returned: 1 MiB, all of the tmpfs
    repo = Path(__file__).resolve().parents[1]
    keeper = ProfileKeeper(repo / "configs/appliance-demo.yaml", data_dir=full_disk)
    assert keeper.current.appliance.daemon.records_reserve_mb == 16.0
    ledger = open_ledger(full_disk / "ledger.sqlite")
    events: queue.Queue = queue.Queue()
    shown: LatestValue = LatestValue()
    shown.put(ShownImage(np.full((1024, 1024), 0.5, np.float32), np.eye(4)))
    worker = RecordsWorker(ledger, keeper, None, lambda: 100.0, events=events, shown=shown, saves=LatestValue())
    worker.setup()
    state = Console(keeper.current.fluoroscope, keeper.current.keymap, 0.0).snapshot()
    for ev, save in [(ConsoleEvent(101.0, "fluoro_on"), None),
                     (ConsoleEvent(113.0, "fluoro_off", {}, 12.0, 1.5, 0.15, 12.0, 1.5, 0.15), None),
                     (ConsoleEvent(114.0, "save", {}, 12.0, 1.5, 0.15), state)]:
        events.put(Recorded(ev, save))
    worker.step()
    assert "records_reserve_mb" in (worker.problem or "") and worker.saved == []
    from appliance.daemon.health import records_check
    banner = records_check(lambda: worker.problem).check().banner
    assert banner.startswith("image not saved (the save is in the ledger)") and "kept in memory" not in banner
    assert not (full_disk / "images").exists() or not any((full_disk / "images").iterdir())
    assert [r for r in caplog.records if "image not saved" in r.getMessage()]
    worker.stop()
    worker.teardown()
    ledger.close()
    conn = open_readonly(full_disk / "ledger.sqlite")
    kinds = [r[0] for r in conn.execute("SELECT kind FROM events ORDER BY id")]
    row = conn.execute("SELECT fluoro_time_s, air_kerma_mgy, saves FROM sessions").fetchone()
    assert kinds == ["session_start", "fluoro_on", "fluoro_off", "save", "session_end"] and verify(conn).ok
    assert (row["fluoro_time_s"], row["air_kerma_mgy"], row["saves"]) == (12.0, 1.5, 1)
    conn.close()


def test_snapshots_leave_the_ledger_its_reserve(full_disk):
    """The demo on a 4 MiB disk: the 3.3 MiB an admin freed went to the snapshots waiting to be
    taken within 5 s, and the held dose events found the disk full again."""
    (full_disk / "filler").unlink()                 # 1 MiB free, under a 16 MiB reserve
    snapper = Snapshotter(full_disk / "snapshots", [Moment("first", "first image", lambda f: True)], reserve_mb=16.0)
    snapper(frame())
    assert "first" not in snapper.taken and "records_reserve_mb" in (snapper.problem or "")
    unreserved = Snapshotter(full_disk / "snapshots", [Moment("first", "first image", lambda f: True)])
    unreserved(frame())
    assert unreserved.taken["first"].is_file()      # the same disk takes the picture without a reserve


def test_built_in_patient_on_a_full_disk_is_refused_before_drawing(full_disk, capfd):
    """Refused in one line of ours, before a minute of drawing, and with nothing from
    SimpleITK's writer on stderr; no half-written cache folder is left."""
    from appliance.patient import builtin
    start = time.monotonic()
    with pytest.raises(FluorosimError, match=f"has {builtin.BUILD_FREE_MB} MB free") as refused:
        builtin.build(full_disk / "cache" / "child")
    assert time.monotonic() - start < 5.0
    assert "\n" not in str(refused.value) and str(full_disk / "cache") in str(refused.value)
    assert capfd.readouterr().err == ""
    assert sorted(p.name for p in (full_disk / "cache").iterdir()) == []


def test_a_snapshot_written_beside_the_renderer_is_the_frame_and_a_refused_one_is_taken_again(tmp_path, caplog):
    """With background=True the PNG is written on the snapshot thread: after flush() it holds the
    frame's pixels exactly (PNG is lossless), even though the screen was drawn over since; a write
    refused there (a folder where the PNG goes: the rename fails) leaves the moment untaken,
    counted and logged once, and its next hit after the wait writes it."""
    from appliance.daemon.snapshots import read_png

    out = tmp_path / "snapshots"
    out.mkdir()
    screen = np.zeros((6, 10, 3), np.uint8)
    screen[2:4, 3:7] = (200, 40, 10)
    shown = SimpleNamespace(rgb_source=lambda: screen, state=SimpleNamespace(alarm_sounding=False))
    (out / "00-first.png").mkdir()                # refused: a folder stands where the file goes
    snapper = Snapshotter(out, [Moment("first", "first image", lambda f: True)], background=True)
    snapper(shown)
    snapper.flush()
    assert "first" not in snapper.taken and snapper.failures == 1 and snapper.problem
    assert len([r for r in caplog.records if "snapshot not written" in r.getMessage()]) == 1
    (out / "00-first.png").rmdir()
    snapper._retry_at = 0.0
    expected = screen.copy()
    snapper(shown)
    screen[:] = 255                               # the next frame draws over the screen at once
    snapper.flush()
    assert snapper.taken["first"].is_file() and snapper.problem is None and snapper.failures == 1
    np.testing.assert_array_equal(read_png(snapper.taken["first"]), expected)
