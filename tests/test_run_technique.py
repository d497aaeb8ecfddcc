"""The kV and mA a run records are its time-weighted means over the exposure, as the dose
report's per-event KVP and X-Ray Tube Current are (PS3.16 TID 10003B: mean values over the
irradiation event), worked by hand from a known schedule of the exposure control's settings."""

from __future__ import annotations

import json
import os

import pytest
from test_console import II, KEYMAP, press, release
from test_export import DAY1, name
from test_rdsr_content import children, number

from appliance.console.state import Console
from appliance.records import rdsr
from appliance.records.ledger import Ledger

#: (time s, kV, mA) the exposure control sets during one continuous run, pedal down at 1 s and
#: up at 11 s: 75 kV 2 mA (the reference technique) for 2.5 s, 88 kV 2.8 mA for 4 s, 104 kV
#: 3.7 mA for 3.5 s.
SCHEDULE = [(3.5, 88.0, 2.8), (7.5, 104.0, 3.7)]
MEAN_KVP = (2.5 * 75.0 + 4.0 * 88.0 + 3.5 * 104.0) / 10.0     # 90.35 kV
MEAN_MA = (2.5 * 2.0 + 4.0 * 2.8 + 3.5 * 3.7) / 10.0          # 2.915 mA


def _run_with_schedule(console: Console, until: float = 11.0, released: bool = True) -> list:
    """The pedal down at 1 s, the technique changed at SCHEDULE's times, ticks of 40 ms until
    `until`; the pedal up then when `released` (otherwise the process dies there)."""
    events = console.handle(press(1.0, "pedal"))
    t = 1.0
    for when, kvp, ma in SCHEDULE:
        while t < when:
            t = min(t + 0.04, when)
            events += console.tick(t)
        events += console.set_exposure_factor(1.0, when, kvp, ma)
    while t < until:
        t = min(t + 0.04, until)
        events += console.tick(t)
    return events + (console.handle(release(until, "pedal")) if released else [])


def test_a_run_records_the_time_weighted_mean_of_the_kv_and_ma_the_control_set():
    events = _run_with_schedule(Console(II, KEYMAP, t0=0.0))
    (on,) = [e for e in events if e.kind == "fluoro_on"]
    (off,) = [e for e in events if e.kind == "fluoro_off"]
    assert off.detail["duration_s"] == pytest.approx(10.0)
    assert off.detail["kvp"] == pytest.approx(MEAN_KVP, rel=1e-9)
    assert off.detail["ma"] == pytest.approx(MEAN_MA, rel=1e-9)
    # The run began at the reference technique; the end's technique alone would read 104 kV.
    assert (on.detail["kvp"], on.detail["ma"]) == (75.0, 2.0)


def test_the_dose_report_carries_the_runs_mean_kv_and_ma(tmp_path):
    path = tmp_path / "ledger.sqlite"
    console = Console(II, KEYMAP, t0=0.0)
    with Ledger(path) as ledger:
        ledger.start_session("Dr Trainee", "Adult chest", II.name, t_wall=DAY1, t_monotonic=0.0)
        ledger.record(_run_with_schedule(console))
        ledger.end_session(DAY1 + 20.0)
        session, events = ledger.session_rows(1)
    (event,) = children(rdsr.session_report(session, events))["Irradiation Event X-Ray Data"]
    rows = children(event)
    assert name(rows["KVP"][0]) == "KVP"
    assert number(rows["KVP"][0]) == (pytest.approx(MEAN_KVP, rel=1e-9), "kV")
    assert number(rows["X-Ray Tube Current"][0]) == (pytest.approx(MEAN_MA, rel=1e-9), "mA")


def test_a_pulsed_run_weights_each_technique_by_the_time_it_was_held():
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "mode_next"))                     # pulsed-15
    events = console.handle(press(1.0, "pedal"))
    events += console.tick(1.5)
    events += console.set_exposure_factor(1.4, 1.6, 82.0, 2.4)
    events += console.tick(2.9)
    events += console.handle(release(3.0, "pedal"))
    (off,) = [e for e in events if e.kind == "fluoro_off"]
    # 0.6 s at 75 kV 2 mA, 1.4 s at 82 kV 2.4 mA.
    assert off.detail["kvp"] == pytest.approx((0.6 * 75.0 + 1.4 * 82.0) / 2.0, rel=1e-9)
    assert off.detail["ma"] == pytest.approx((0.6 * 2.0 + 1.4 * 2.4) / 2.0, rel=1e-9)


def test_without_a_kv_curve_the_tube_current_follows_the_exposure_factor():
    # A control without a curve moves only the tube output: at 2.5 x the reference output the
    # tube current is 2.5 x tube.ma (2 mA on the intensifier), the kV stays tube.kvp.
    console = Console(II, KEYMAP, t0=0.0)
    events = console.handle(press(0.0, "pedal"))
    events += console.tick(4.0)
    events += console.set_exposure_factor(2.5, 4.0)
    events += console.tick(8.0)
    events += console.handle(release(8.0, "pedal"))
    (off,) = [e for e in events if e.kind == "fluoro_off"]
    assert off.detail["kvp"] == pytest.approx(75.0)
    assert off.detail["ma"] == pytest.approx((4.0 * 2.0 + 4.0 * 5.0) / 8.0, rel=1e-9)
    assert console.snapshot().ma == pytest.approx(5.0)


def _crash(ledger: Ledger) -> None:
    """The process dies: the ledger's file is left as it was, no run or session closed."""
    ledger._conn.close()
    ledger._conn = None
    os.close(ledger._lock_fd)


def _recovered_run(path, events) -> dict:
    ledger = Ledger(path, seal=None)
    ledger.start_session("Dr Trainee", "Adult chest", II.name, t_wall=DAY1, t_monotonic=0.0)
    ledger.record(events)
    _crash(ledger)
    with Ledger(path, seal=None) as ledger:          # the restart: recovery closes the run and the session
        assert ledger.recovered == [1]
        _, rows = ledger.session_rows(1)
    (off,) = [json.loads(r["detail"]) for r in rows if r["kind"] == "fluoro_off"]
    assert off["reason"] == "recovered"
    return off


def test_a_run_a_crash_cut_off_gets_its_mean_technique_up_to_its_last_progress_record(tmp_path):
    """The schedule above, the process dying at 9.7 s with the pedal still down: progress records
    each second from 2 s, the last at 9 s. Up to it, 8 s: 2.5 s at 75 kV 2 mA, 4 s at 88 kV
    2.8 mA, 1.5 s at 104 kV 3.7 mA."""
    events = _run_with_schedule(Console(II, KEYMAP, t0=0.0), until=9.7, released=False)
    off = _recovered_run(tmp_path / "ledger.sqlite", events)
    assert off["kvp"] == pytest.approx((2.5 * 75.0 + 4.0 * 88.0 + 1.5 * 104.0) / 8.0, rel=1e-9)   # 86.9375 kV
    assert off["ma"] == pytest.approx((2.5 * 2.0 + 4.0 * 2.8 + 1.5 * 3.7) / 8.0, rel=1e-9)        # 2.71875 mA
    assert off["duration_s"] == pytest.approx(8.0)


def test_a_pulsed_run_a_crash_cut_off_is_weighted_up_to_its_last_pulse(tmp_path):
    """Pulsed-15 from 1 s, 82 kV 2.4 mA from 1.6 s, dying at 2.05 s: the last pulse at
    1 + 15/15 = 2 s, so 0.6 s at 75 kV 2 mA and 0.4 s at 82 kV 2.4 mA."""
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(press(0.0, "mode_next"))
    events = console.handle(press(1.0, "pedal"))
    events += console.tick(1.5)
    events += console.set_exposure_factor(1.4, 1.6, 82.0, 2.4)
    events += console.tick(2.05)
    off = _recovered_run(tmp_path / "ledger.sqlite", events)
    assert off["kvp"] == pytest.approx((0.6 * 75.0 + 0.4 * 82.0) / 1.0, rel=1e-9)
    assert off["ma"] == pytest.approx((0.6 * 2.0 + 0.4 * 2.4) / 1.0, rel=1e-9)


def test_a_run_cut_off_before_its_first_progress_record_keeps_the_technique_it_began_with(tmp_path):
    console = Console(II, KEYMAP, t0=0.0)
    events = console.handle(press(1.0, "pedal")) + console.tick(1.5)
    off = _recovered_run(tmp_path / "ledger.sqlite", events)
    assert (off["kvp"], off["ma"]) == (75.0, 2.0)
