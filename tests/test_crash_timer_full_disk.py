"""A crash, then a start on a full disk: the cumulative fluoroscopy timer and the alarm count
still go on from the crashed session (21 CFR 1020.32), although the ledger opens only later.

Real parts: the session is written by a separate process that is killed with SIGKILL (so its
WAL is left as a crash leaves it), on a 1 MiB tmpfs then filled to its last block. The figures
are hand-worked as in test_crash_timer: a 300 s alarm period, 320 s of fluoroscopy and one
alarm before the crash, so the next alarm is due at 600 s cumulative, 280 s into the new session.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from test_disk_full import full_disk  # noqa: F401  # the fixture: a really full tmpfs

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from appliance.errors import FluorosimError
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
FLUOROSCOPE = REPO / "configs/fluoroscopes/generic-ii-carm.yaml"     # alarm_period_s: 300
KEYMAP = REPO / "configs/keymaps/usb-numeric-keypad.yaml"

CRASHING_WRITER = """
import sys, time
from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from appliance.records.ledger import Ledger
from drivers.input_event import InputEvent
fl = load_profile(sys.argv[2], FluoroscopeProfile)
km = load_profile(sys.argv[3], KeymapProfile)
ledger = Ledger(sys.argv[1], seal=None)
console = Console(fl, km, t0=0.0)
ledger.start_session("trainee", "case", fl.name, t_wall=1_700_000_000.0, t_monotonic=0.0)
events = console.handle(InputEvent(1.0, "pedal", "pedal", True)) + console.tick(321.0)
events += console.handle(InputEvent(321.0, "pedal", "pedal", False))
ledger.record(events)
print(sum(e.kind == "alarm" for e in events), flush=True)
time.sleep(60)
"""


def fill(folder: Path) -> None:
    with open(folder / "filler", "wb", buffering=0) as f:     # unbuffered: nothing left to fail at close
        try:
            while True:
                f.write(b"\0" * 4096)
                f.flush()
        except OSError:
            pass


def test_a_deferred_ledger_still_carries_the_crashed_sessions_timer(full_disk):  # noqa: F811
    from appliance.records.deferred_ledger import DeferredLedger, open_ledger
    from appliance.records.ledger import open_readonly, verify

    (full_disk / "filler").unlink()
    path = full_disk / "ledger.sqlite"
    writer = subprocess.Popen([sys.executable, "-c", CRASHING_WRITER, str(path), str(FLUOROSCOPE), str(KEYMAP)],
                              stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert writer.stdout is not None and writer.stdout.readline().strip() == "1"    # one alarm at 300 s
    finally:
        writer.kill()                                    # SIGKILL: the session stays open, its WAL unmerged
        writer.wait(timeout=10)
    assert (full_disk / "ledger.sqlite-wal").stat().st_size > 0
    fill(full_disk)

    ledger = open_ledger(path)
    assert isinstance(ledger, DeferredLedger) and "disk is full" in (ledger.problem or "")
    carried = ledger.carry_over()
    assert carried is not None and carried["from_session"] == 1
    assert carried["fluoro_time_s"] == pytest.approx(320.0) and carried["alarms"] == 1

    fl, km = load_profile(FLUOROSCOPE, FluoroscopeProfile), load_profile(KEYMAP, KeymapProfile)
    console = Console(fl, km, t0=0.0)
    console.carry_over(carried["fluoro_time_s"], carried["alarms"])
    assert console.snapshot().fluoro_time_s == pytest.approx(320.0) and console.snapshot().alarm_count == 1
    events = console.handle(InputEvent(1.0, "pedal", "pedal", True)) + console.tick(281.5)
    events += console.handle(InputEvent(282.0, "pedal", "pedal", False))
    alarms = [e for e in events if e.kind == "alarm"]
    assert len(alarms) == 1 and alarms[0].t_monotonic == pytest.approx(281.0, abs=1e-6)
    assert console.snapshot().alarm_count == 2

    with pytest.raises(FluorosimError, match="disk is full"):
        ledger.start_session("trainee", "case", fl.name, t_wall=1_700_001_000.0, t_monotonic=0.0)
    (full_disk / "filler").unlink()                     # an admin frees space
    ledger.start_session("trainee", "case", fl.name, t_wall=1_700_001_000.0, t_monotonic=0.0)
    ledger.record(events)
    ledger.end_session(t_wall=1_700_001_300.0)
    ledger.close()

    conn = open_readonly(path)
    sessions = {r["id"]: dict(r) for r in conn.execute("SELECT id, end_reason, fluoro_time_s, alarms FROM sessions")}
    assert sessions[1]["end_reason"] == "recovered"
    assert sessions[1]["fluoro_time_s"] == pytest.approx(320.0) and sessions[1]["alarms"] == 1
    # The new session records what it carried, and its own dose record holds only its own time.
    start = conn.execute("SELECT detail FROM events WHERE session_id = 2 AND kind = 'session_start'").fetchone()[0]
    assert json.loads(start)["carried"] == {"fluoro_time_s": pytest.approx(320.0), "alarms": 1, "from_session": 1}
    assert sessions[2]["fluoro_time_s"] == pytest.approx(281.0) and sessions[2]["alarms"] == 1
    assert verify(conn).ok
    conn.close()


def test_no_crashed_session_no_carry_and_no_file_no_error(full_disk, caplog):  # noqa: F811
    from appliance.records.deferred_ledger import open_ledger

    ledger = open_ledger(full_disk / "ledger.sqlite")     # a fresh appliance on a full disk: no file yet
    assert ledger.carry_over() is None
    assert not [r for r in caplog.records if "timer" in r.getMessage()]
