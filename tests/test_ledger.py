"""The ledger: real SQLite in WAL mode, a hash chain, recovery after kill -9."""

import json
import math
import os
import random
import signal
import sqlite3
import time
from pathlib import Path

import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from appliance.errors import FluorosimError
from appliance.records.ledger import MIGRATIONS, Ledger, open_readonly, verify
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)


def scripted_session(ledger: Ledger, report=None, frames: int = 10**9, seed: int = 0, commit_every: int = 1) -> Console:
    """Drive a console through pedal runs and key presses, one ledger transaction per
    `commit_every` frames. The console clock runs 0.25 s per frame so runs, pulses and alarms
    all happen quickly."""
    rng = random.Random(seed)
    console = Console(II, KEYMAP, t0=0.0)
    sid = ledger.start_session("trainee", "Case", II.name, t_wall=1_700_000_000.0, t_monotonic=0.0)
    if report is not None:
        os.write(report, f"session {sid}\n".encode())
    keys = ["KEY_KP5", "KEY_KP2", "KEY_KP9", "KEY_KP7", "KEY_KP1", "KEY_KPPLUS", "KEY_KPASTERISK", "KEY_KPMINUS"]
    t, pedal = 0.0, False
    events = []
    for frame in range(frames):
        t += 0.25
        r = rng.random()
        if r < 0.15:
            pedal = not pedal
            events += console.handle(InputEvent(t, "pedal", "pedal", pedal))
        elif r < 0.25:
            events += console.handle(InputEvent(t, "keypad", rng.choice(keys), True))
        events += console.tick(t + 0.1)
        if (frame + 1) % commit_every:
            continue
        ledger.record(events)
        if report is not None and events:
            s = events[-1]
            os.write(report, f"{s.fluoro_time_s!r} {s.air_kerma_mgy!r} {s.dap_gy_cm2!r} {len(events)}\n".encode())
        events = []
    ledger.record(events)
    return console


def session_sums(conn, sid):
    return conn.execute("SELECT sum(d_fluoro_time_s), sum(d_air_kerma_mgy), sum(d_dap_gy_cm2), count(*) "
                        "FROM events WHERE session_id = ?", (sid,)).fetchone()


def test_wal_full_sync_and_migrations(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with Ledger(path):
        pass
    conn = sqlite3.connect(path)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert conn.execute("PRAGMA user_version").fetchone()[0] == len(MIGRATIONS)
    with Ledger(path) as ledger:
        assert ledger._conn.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL


def test_session_totals_are_the_sum_of_recorded_events(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with Ledger(path) as ledger:
        console = scripted_session(ledger, frames=3000, seed=1, commit_every=20)
        ledger.record(console.end(3000 * 0.25 + 1.0))
        ledger.end_session(1_700_001_000.0)
    state = console.snapshot()
    conn = open_readonly(path)
    s = conn.execute("SELECT * FROM sessions").fetchone()
    assert s["end_reason"] == "ended"
    # Events are recorded after each frame's tick, so the ledger holds everything the console counted.
    assert s["fluoro_time_s"] == pytest.approx(state.fluoro_time_s, rel=1e-9)
    assert s["air_kerma_mgy"] == pytest.approx(state.air_kerma_mgy, rel=1e-9)
    assert s["dap_gy_cm2"] == pytest.approx(state.dap_gy_cm2, rel=1e-9)
    assert s["runs"] == state.runs and s["alarms"] == state.alarm_count and s["saves"] == state.save_count
    assert state.alarm_count >= 1
    assert verify(conn).ok


def test_verify_reports_the_first_broken_link(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with Ledger(path) as ledger:
        scripted_session(ledger, frames=400, seed=2)
        ledger.end_session(1_700_000_500.0)
    conn = sqlite3.connect(path)
    n = conn.execute("SELECT count(*) FROM events").fetchone()[0]
    assert n > 50
    conn.execute("UPDATE events SET d_air_kerma_mgy = d_air_kerma_mgy * 0.5 WHERE id = 40")
    conn.commit()
    report = verify(open_readonly(path))
    assert not report.ok and report.first_bad_id == 40 and "changed" in report.message
    conn.execute("UPDATE events SET d_air_kerma_mgy = d_air_kerma_mgy * 2 WHERE id = 40")
    conn.execute("DELETE FROM events WHERE id = 30")
    conn.commit()
    report = verify(open_readonly(path))
    assert not report.ok and report.first_bad_id == 31
    # A session's totals edited as well: the first broken link is still the one reported.
    conn.execute("UPDATE sessions SET air_kerma_mgy = 0.001")
    conn.commit()
    report = verify(open_readonly(path))
    assert not report.ok and report.first_bad_id == 31, report.message


def test_edited_session_totals_are_detected(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with Ledger(path) as ledger:
        scripted_session(ledger, frames=400, seed=2)
        ledger.end_session(1_700_000_500.0)
    conn = sqlite3.connect(path)
    conn.execute("UPDATE sessions SET air_kerma_mgy = 0.001")
    conn.commit()
    report = verify(open_readonly(path))
    assert not report.ok and "air_kerma_mgy" in report.message


def test_second_writer_is_refused(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with Ledger(path):
        with pytest.raises(FluorosimError, match="another fluorosim process"):
            Ledger(path)


def test_full_or_readonly_disk_keeps_what_was_recorded(tmp_path):
    path = tmp_path / "ledger.sqlite"
    ledger = Ledger(path)
    scripted_session(ledger, frames=200, seed=4)
    before = session_sums(open_readonly(path), 1)
    # A tiny page limit stands in for a full disk: SQLite answers SQLITE_FULL, as on ENOSPC.
    pages = ledger._conn.execute("PRAGMA page_count").fetchone()[0]
    ledger._conn.execute(f"PRAGMA max_page_count = {pages}")
    console = Console(II, KEYMAP, t0=0.0)
    console.handle(InputEvent(0.0, "pedal", "pedal", True))
    big = console.tick(5000.0)
    with pytest.raises(FluorosimError, match="free disk space"):
        ledger.record(big)
    ledger.close()
    after = session_sums(open_readonly(path), 1)
    assert tuple(after) == tuple(before)
    assert verify(open_readonly(path)).ok


def _child(path: Path, write_fd: int, seed: int) -> None:
    try:
        ledger = Ledger(path)
        scripted_session(ledger, report=write_fd, seed=seed)
    finally:
        os._exit(0)


@pytest.fixture
def memory_backed_dir(tmp_path):
    """A folder on tmpfs where the machine has one. A SIGKILL leaves the page cache intact, so
    what a killed process committed is the same on tmpfs as on disk; tmpfs only spares the
    test the fsync waits of 200 runs (power-loss durability is synchronous=FULL, checked above)."""
    if not os.path.isdir("/dev/shm"):
        yield tmp_path
        return
    import tempfile
    folder = Path(tempfile.mkdtemp(prefix="fluorosim-ledger-", dir="/dev/shm"))
    yield folder
    import shutil
    shutil.rmtree(folder, ignore_errors=True)


def test_kill_9_at_100_random_moments_loses_nothing_committed(memory_backed_dir):
    path = memory_backed_dir / "ledger.sqlite"
    rng = random.Random(2024)
    sessions_seen = runs_cut = 0
    checked = None
    Ledger(path).close()   # the schema exists before the first kill (creation itself is one transaction)
    conn = open_readonly(path)   # a reader beside the writers, as `fluorosim logs verify` would be
    for i in range(100):
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(r)
            _child(path, w, seed=i)
        os.close(w)
        head = b""
        if rng.random() < 0.25:
            time.sleep(rng.uniform(0.0, 0.02))          # while the child opens the ledger and starts a session
        else:
            while b"session" not in head:               # or once its session is open, mid-session
                chunk = os.read(r, 4096)
                if not chunk:
                    break
                head += chunk
            time.sleep(rng.uniform(0.0, 0.03))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        with os.fdopen(r, "rb") as f:
            lines = (head + f.read()).decode().splitlines()
        commits = [l.split() for l in lines if not l.startswith("session")]
        # What the killed child committed is all there, and the chain holds.
        # Rows before `checked` were verified after an earlier kill and are never rewritten.
        report = verify(conn, resume=checked)
        assert report.ok, report.message
        open_ids = [row[0] for row in conn.execute("SELECT id FROM sessions WHERE ended_wall IS NULL")]
        if commits:
            last_ft, last_k, last_d = map(float, commits[-1][:3])
            assert len(open_ids) == 1
            ft, k, d, _ = session_sums(conn, open_ids[0])
            # The child may die between its commit and its report: never less than reported.
            assert ft >= last_ft - 1e-9 and k >= last_k - 1e-12 and d >= last_d - 1e-12
        # Reopening closes the interrupted session with totals = the sum of its events.
        with Ledger(path) as ledger:
            recovered = ledger.recovered
        assert recovered == open_ids
        for sid in recovered:
            s = conn.execute("SELECT * FROM sessions WHERE id = ?", (sid,)).fetchone()
            ft, k, d, _ = session_sums(conn, sid)
            assert s["end_reason"] == "recovered"
            assert math.isclose(s["fluoro_time_s"], ft, rel_tol=1e-9, abs_tol=1e-12)
            assert math.isclose(s["air_kerma_mgy"], k, rel_tol=1e-9, abs_tol=1e-12)
            assert math.isclose(s["dap_gy_cm2"], d, rel_tol=1e-9, abs_tol=1e-12)
            last = conn.execute("SELECT fluoro_time_s, air_kerma_mgy FROM events WHERE session_id = ? "
                                "AND kind != 'session_end' ORDER BY id DESC LIMIT 1", (sid,)).fetchone()
            assert math.isclose(last[0], ft, rel_tol=1e-9, abs_tol=1e-12)
            kinds = [row[0] for row in conn.execute("SELECT kind FROM events WHERE session_id = ?", (sid,))]
            assert kinds.count("fluoro_on") == kinds.count("fluoro_off")
            cut = conn.execute("SELECT detail FROM events WHERE session_id = ? AND kind = 'fluoro_off' "
                               "ORDER BY id DESC LIMIT 1", (sid,)).fetchone()
            if cut is not None and json.loads(cut[0])["reason"] == "recovered":
                runs_cut += 1
            sessions_seen += 1
        report = verify(conn, resume=report.last)
        assert report.ok, report.message
        checked = report.last
    conn.close()
    assert verify(open_readonly(path)).ok
    assert sessions_seen > 70 and runs_cut > 15      # most kills land mid-session, many mid-run


def test_unreadable_or_newer_ledger_gives_one_clear_error(tmp_path):
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database, it is a text file" * 100)
    with pytest.raises(FluorosimError, match="cannot open the ledger"):
        Ledger(junk)
    assert junk.read_bytes().startswith(b"this is not a database")     # left as it was
    newer = tmp_path / "newer.sqlite"
    Ledger(newer).close()
    conn = sqlite3.connect(newer)
    conn.execute("PRAGMA user_version = 99")
    conn.commit()
    conn.close()
    with pytest.raises(FluorosimError, match="newer than this fluorosim knows"):
        Ledger(newer)
    with pytest.raises(FluorosimError, match="newer than this fluorosim knows"):
        open_readonly(newer)


def test_a_damaged_ledger_is_called_damaged_not_a_permissions_problem(tmp_path):
    """A ledger cut short (a copy that stopped, a disk that failed) is not a permissions problem."""
    whole = tmp_path / "whole.sqlite"
    with Ledger(whole) as led:
        led.start_session("Dr A", "case", "C-arm", t_wall=1_700_000_000.0, t_monotonic=0.0)
        led.end_session(t_wall=1_700_000_010.0)
    cut = tmp_path / "cut.sqlite"
    cut.write_bytes(whole.read_bytes()[:3000])       # the header and part of the first page
    with pytest.raises(FluorosimError) as e:
        open_readonly(cut)
    message = str(e.value)
    assert "damaged or is not a ledger" in message and "permissions" not in message and "\n" not in message


def test_the_wal_beside_the_ledger_stays_small(tmp_path):
    """The ledger's footprint on a nearly full disk: SQLite's default checkpoint lets the WAL grow to
    1000 frames (4 MiB) beside the file; checkpointed every 64 pages it stays near 64 frames of
    4096 + 24 bytes (264 KiB) plus the transaction that crossed the mark."""
    from appliance.console.state import ConsoleEvent

    path = tmp_path / "ledger.sqlite"
    wal = tmp_path / "ledger.sqlite-wal"
    largest = 0
    with Ledger(path) as led:
        led.start_session("Dr A", "case", "C-arm", t_wall=1_700_000_000.0, t_monotonic=0.0)
        t = kerma = 0.0
        for n in range(300):           # 300 small transactions, as the records worker writes them
            batch = []
            for _ in range(4):
                t, kerma = t + 1.0, kerma + 0.01
                batch.append(ConsoleEvent(t, "fluoro_off", {"run": n}, t, kerma, kerma / 10, 1.0, 0.01, 0.001))
            led.record(batch)
            largest = max(largest, wal.stat().st_size)
    assert largest < 400 * 1024, largest
    conn = open_readonly(path)
    assert conn.execute("SELECT count(*) FROM events").fetchone()[0] == 1 + 1200 and verify(conn).ok
    conn.close()
