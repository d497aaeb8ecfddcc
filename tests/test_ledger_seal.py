"""The authenticated ledger: forgeries that pass a plain hash chain are caught.

Each attack is the one a person with write access to the file would make, done with the
public algorithm (recomputing every SHA-256 link), but without the key. The figures of the
sessions are hand-made (a 60 s run of 2 mGy), not produced by the code under test.
"""

from __future__ import annotations

import csv
import json
import socket
import sqlite3
import threading
from pathlib import Path

import pydicom
import pytest

from appliance.cli import main
from appliance.console.state import ConsoleEvent
from appliance.errors import FluorosimError
from appliance.records import integrity
from appliance.records.ledger import EVENT_COLUMNS, GENESIS, Ledger, event_hash, open_readonly, verify
from appliance.records.seal import HelperSeal, KeySeal, anchor_entry, make_key, serve

DAY = 1_700_000_000.0


@pytest.fixture
def seal(tmp_path):
    key = tmp_path / "ledger.key"
    make_key(key)
    return KeySeal(key, tmp_path / "anchor.json")


def run(t0: float, kerma: float) -> list[ConsoleEvent]:
    """One 60 s exposure of `kerma` mGy (DAP 0.1 Gy cm2 per mGy) and an alarm."""
    return [ConsoleEvent(t0, "fluoro_on", {"mode": "continuous"}),
            ConsoleEvent(t0 + 60, "fluoro_off", {"run": 1, "reason": "released", "start_t": t0, "duration_s": 60.0,
                                                 "air_kerma_mgy": kerma, "dap_gy_cm2": kerma / 10, "pulses": 0,
                                                 "mode": "continuous", "zoom": 1},
                         60.0, kerma, kerma / 10, 60.0, kerma, kerma / 10),
            ConsoleEvent(t0 + 61, "alarm", {}, 60.0, kerma, kerma / 10)]


def write_sessions(path: Path, seal, sessions=(("Dr A", 2.0), ("Dr B", 3.0), ("Dr C", 5.0))) -> None:
    with Ledger(path, seal=seal) as ledger:
        for n, (operator, kerma) in enumerate(sessions):
            ledger.start_session(operator, "case", "C-arm", t_wall=DAY + 1000 * n, t_monotonic=0.0)
            ledger.record(run(1.0, kerma))
            ledger.end_session(t_wall=DAY + 1000 * n + 100)


def rechain(conn: sqlite3.Connection) -> None:
    """What a forger does after editing rows: recompute every SHA-256 link from the genesis."""
    prev = GENESIS
    for r in [dict(r) for r in conn.execute(f"SELECT {', '.join(EVENT_COLUMNS)} FROM events ORDER BY id")]:
        r["prev_hash"] = prev
        r["hash"] = event_hash(prev, r)
        conn.execute("UPDATE events SET prev_hash = ?, hash = ? WHERE id = ?", (r["prev_hash"], r["hash"], r["id"]))
        prev = r["hash"]
    conn.commit()


#: Halve session 2's kerma everywhere it is written: events, the session_end record, the sessions row.
HALVE_SESSION_2 = (
    "UPDATE events SET air_kerma_mgy = air_kerma_mgy / 2, d_air_kerma_mgy = d_air_kerma_mgy / 2 WHERE session_id = 2",
    "UPDATE events SET detail = json_set(detail, '$.air_kerma_mgy', json_extract(detail, '$.air_kerma_mgy') / 2) "
    "WHERE session_id = 2 AND kind = 'session_end'",
    "UPDATE sessions SET air_kerma_mgy = air_kerma_mgy / 2 WHERE id = 2",
)


def forge(path: Path, *statements: str) -> None:
    conn = sqlite3.connect(path)
    conn.row_factory = sqlite3.Row
    for sql in statements:
        conn.execute(sql)
    conn.commit()
    rechain(conn)
    conn.close()


def checked(path: Path, seal) -> integrity.Integrity:
    conn = open_readonly(path)
    try:
        return integrity.check(conn, seal, seal.anchor_path)
    finally:
        conn.close()


def test_intact_sealed_ledger_verifies_and_is_anchored(tmp_path, seal):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, seal)
    report = checked(path, seal)
    assert report.ok and report.authenticated, report.message
    conn = open_readonly(path)
    top = conn.execute("SELECT id, hash FROM events ORDER BY id DESC LIMIT 1").fetchone()
    conn.close()
    assert anchor_entry(seal.anchor_path) == (top["id"], top["hash"])
    # 3 sessions x (start, on, off, alarm, end) events.
    assert top["id"] == 15


def test_halving_a_sessions_kerma_and_rechaining_is_caught(tmp_path, seal):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, seal)
    forge(path, *HALVE_SESSION_2)
    conn = open_readonly(path)
    assert verify(conn).ok          # the plain hash chain is fooled...
    conn.close()
    report = checked(path, seal)    # ...the MACs are not
    # Event 8 is session 2's fluoro_off, the first event whose figures changed.
    assert not report.ok and "MAC does not match" in report.message and report.first_bad_id == 8


@pytest.mark.parametrize("where", ["session_id = 3", "id > 5"])
def test_deleting_the_tail_is_caught_without_the_key(tmp_path, seal, where):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, seal)
    forge(path, f"DELETE FROM events WHERE {where}", "DELETE FROM sessions WHERE id = 3",
          "DELETE FROM sessions WHERE id NOT IN (SELECT session_id FROM events)")
    conn = open_readonly(path)
    try:
        assert verify(conn).ok
        report = integrity.check(conn, None, seal.anchor_path)   # anchor only: what any user can check
    finally:
        conn.close()
    assert not report.ok and "event(s) were removed" in report.message


@pytest.mark.parametrize("column, value", [("operator", "'Dr Nobody'"), ("started_wall", "started_wall + 3600"),
                                           ("alarms", "0"), ("runs", "7"), ("saves", "2"), ("end_reason", "'ended?'")])
def test_sessions_rows_are_in_the_chain(tmp_path, seal, column, value):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, seal)
    forge(path, f"UPDATE sessions SET {column} = {value} WHERE id = 2")
    report = checked(path, seal)
    assert not report.ok and f"session 2: {column}" in report.message


def test_existing_ledger_is_migrated_and_its_history_covered(tmp_path, seal):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, None, sessions=(("Dr Old", 4.0),))        # before sealing: no MACs
    write_sessions(path, seal, sessions=(("Dr New", 1.0),))
    conn = open_readonly(path)
    macs = [r[0] for r in conn.execute("SELECT mac FROM events ORDER BY id")]
    conn.close()
    assert macs[:5] == [None] * 5 and all(macs[5:])
    assert checked(path, seal).ok
    # Rewriting the old, unsealed session and its hashes breaks the first sealed event's MAC.
    forge(path, "UPDATE events SET d_air_kerma_mgy = 0.4, air_kerma_mgy = 0.4 WHERE session_id = 1 AND kind = 'fluoro_off'")
    report = checked(path, seal)
    assert not report.ok and report.first_bad_id == 6


def test_key_readable_by_others_is_refused(tmp_path):
    key = tmp_path / "ledger.key"
    make_key(key)
    key.chmod(0o644)
    with pytest.raises(FluorosimError, match="readable by others"):
        KeySeal(key, tmp_path / "anchor.json")


def test_authenticated_history_cannot_be_signed_again(tmp_path, seal):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, seal)
    with pytest.raises(FluorosimError, match="already anchored"):
        seal.mac(3, "", "0" * 64)


def test_seal_helper_over_a_unix_socket(tmp_path, seal):
    """The service's side: every MAC and the anchor come from the helper; it reads the ledger itself."""
    path = tmp_path / "ledger.sqlite"
    sock_path = tmp_path / "seal.sock"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(sock_path))
    listener.listen(4)
    thread = threading.Thread(target=serve, args=(listener, seal, path), daemon=True)
    thread.start()
    helper = HelperSeal(sock_path)
    write_sessions(path, helper, sessions=(("Dr A", 2.0), ("Dr B", 3.0)))
    assert anchor_entry(seal.anchor_path)[0] == 10
    conn = open_readonly(path)
    assert integrity.check(conn, helper, seal.anchor_path).authenticated
    conn.close()
    with pytest.raises(FluorosimError, match="already anchored"):
        helper.mac(4, "", "0" * 64)
    forge(path, "UPDATE events SET d_fluoro_time_s = 6 WHERE id = 3")
    conn = open_readonly(path)
    assert not integrity.check(conn, helper, seal.anchor_path).ok
    conn.close()
    listener.close()


def test_helper_that_is_down_keeps_nothing_and_says_so(tmp_path):
    with pytest.raises(FluorosimError, match="seal helper does not answer"):
        with Ledger(tmp_path / "ledger.sqlite", seal=HelperSeal(tmp_path / "none.sock")) as ledger:
            ledger.start_session("Dr A", "case", "C-arm", t_wall=DAY, t_monotonic=0.0)


# --- The logs commands on a broken ledger ---------------------------------------------------------

@pytest.fixture
def broken(tmp_path, seal, monkeypatch):
    monkeypatch.setenv("FLUOROSIM_SEAL_KEY", str(tmp_path / "ledger.key"))
    monkeypatch.setenv("FLUOROSIM_SEAL_ANCHOR", str(seal.anchor_path))
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, seal)
    forge(path, *HALVE_SESSION_2)
    return path


def test_verify_fails_on_the_forgery(broken, capsys):
    assert main(["logs", "verify", "--ledger", str(broken)]) == 1
    assert "NOT INTACT" in capsys.readouterr().err


def test_export_refuses_a_broken_ledger(broken, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["logs", "export", "--ledger", str(broken), "--format", "csv", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "NOT INTACT" in err[0] and "--allow-broken" in err[0]
    assert not out.exists()


@pytest.mark.parametrize("fmt", ["csv", "json", "rdsr"])
def test_allow_broken_stamps_every_file(broken, tmp_path, capsys, fmt):
    out = tmp_path / "out"
    assert main(["logs", "export", "--ledger", str(broken), "--format", fmt, "--out", str(out), "--allow-broken"]) == 0
    files = sorted(out.iterdir())
    assert files
    for f in files:
        if f.suffix == ".csv":
            assert next(csv.reader(f.open()))[0].startswith("LEDGER NOT INTACT")
        elif f.suffix == ".json":
            assert json.loads(f.read_text())["NOT_INTACT"].startswith("LEDGER NOT INTACT")
        else:
            ds = pydicom.dcmread(f)
            assert ds.VerificationFlag == "UNVERIFIED" and ds.ImageComments.startswith("LEDGER NOT INTACT")
    assert "every file written says so" in capsys.readouterr().err


def test_list_warns_on_a_broken_ledger(broken, capsys):
    assert main(["logs", "list", "--ledger", str(broken)]) == 0
    captured = capsys.readouterr()
    assert "NOT INTACT" in captured.err and "Dr B" in captured.out


def test_seal_helper_as_its_own_process(tmp_path, seal):
    """`fluorosim seal serve` in its own process, as systemd runs it: the ledger is written through
    it, it refuses to re-sign history, and it verifies the ledger it was started with."""
    import subprocess
    import sys
    import time

    repo = Path(__file__).resolve().parents[1]
    path, sock = tmp_path / "ledger.sqlite", tmp_path / "seal.sock"
    proc = subprocess.Popen([sys.executable, "-m", "appliance", "seal", "serve", "--key", str(tmp_path / "ledger.key"),
                             "--anchor", str(seal.anchor_path), "--ledger", str(path), "--socket", str(sock)],
                            cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while not sock.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert sock.exists(), proc.stderr.read() if proc.poll() is not None else "no socket"
        helper = HelperSeal(sock)
        write_sessions(path, helper, sessions=(("Dr A", 2.0),))
        assert anchor_entry(seal.anchor_path)[0] == 5
        with pytest.raises(FluorosimError, match="already anchored"):
            helper.mac(5, "", "0" * 64)
        conn = open_readonly(path)
        assert integrity.check(conn, helper, seal.anchor_path).authenticated
        conn.close()
    finally:
        proc.terminate()
        proc.wait(10)
