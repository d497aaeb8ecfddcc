"""After a crash the cumulative fluoroscopy timer and the alarm count go on (21 CFR 1020.32).

The figures are hand-worked: a 300 s alarm period, 320 s of fluoroscopy before the crash, so
the next alarm is due at 600 s of cumulative time, 280 s into the recovered session.
"""

import os
from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]


def test_crash_carries_the_cumulative_timer_and_alarms_until_a_person_resets(tmp_path):
    """21 CFR 1020.32: the cumulative timer is reset only by a person, not by a crash."""
    from appliance.records.ledger import Ledger

    fl = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)   # 300 s alarm
    km = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
    path = tmp_path / "ledger.sqlite"
    ledger = Ledger(path, seal=None)
    console = Console(fl, km, t0=0.0)
    ledger.start_session("trainee", "case", fl.name, t_wall=1_700_000_000.0, t_monotonic=0.0)
    # 320 s of fluoroscopy: one alarm at 300 s; then the process dies (no end_session).
    events = console.handle(InputEvent(1.0, "pedal", "pedal", True)) + console.tick(321.0)
    events += console.handle(InputEvent(321.0, "pedal", "pedal", False))
    ledger.record(events)
    assert sum(e.kind == "alarm" for e in events) == 1
    ledger._conn.close()
    ledger._conn = None
    os.close(ledger._lock_fd)

    ledger = Ledger(path, seal=None)       # the restart: recovery closes session 1
    carried = ledger.carry_over()
    assert carried["fluoro_time_s"] == pytest.approx(320.0) and carried["alarms"] == 1
    console = Console(fl, km, t0=0.0)
    console.carry_over(carried["fluoro_time_s"], carried["alarms"])
    ledger.start_session("trainee", "case", fl.name, t_wall=1_700_001_000.0, t_monotonic=0.0)
    state = console.snapshot()
    assert state.fluoro_time_s == pytest.approx(320.0) and state.alarm_count == 1
    # The next alarm comes at 600 s of cumulative time: 280 s into the new session, not 300.
    events = console.handle(InputEvent(1.0, "pedal", "pedal", True)) + console.tick(281.5)
    alarms = [e for e in events if e.kind == "alarm"]
    assert len(alarms) == 1 and alarms[0].t_monotonic == pytest.approx(281.0, abs=1e-6)
    assert console.snapshot().alarm_count == 2
    assert console.snapshot().fluoro_time_s == pytest.approx(600.0, abs=0.6)
    events += console.handle(InputEvent(282.0, "pedal", "pedal", False))
    # Silence the alarm, then a deliberate reset (no alarm sounding) clears the carried part.
    events += console.handle(InputEvent(283.0, "keypad", "KEY_KPASTERISK", True))
    assert console.snapshot().alarm_count == 2
    events += console.handle(InputEvent(284.0, "keypad", "KEY_KPASTERISK", True))
    state = console.snapshot()
    assert state.fluoro_time_s == pytest.approx(281.0, abs=0.6) and state.alarm_count == 1
    ledger.record(events)
    # The new session's own dose record holds only its own time.
    ledger.end_session(t_wall=1_700_001_300.0)
    row = ledger._conn.execute("SELECT fluoro_time_s FROM sessions WHERE id = 2").fetchone()
    assert row[0] == pytest.approx(281.0, abs=0.6)
    ledger.close()
