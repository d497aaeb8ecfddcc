"""Tamper evidence, one forgery at a time: every recorded figure is covered by the chain, a
removed event shows even when the chain is recomputed, and the seal's MACs and anchor catch
what a forger without the key can do after recomputing every SHA-256 link.

The ledgers are the hand-made sessions of test_ledger_seal (3 sessions of a 60 s run of
2, 3 and 5 mGy, 5 events each); each forgery is the SQL a person with write access runs.
"""

from __future__ import annotations

import json
import shutil
import sqlite3

import pytest
from test_ledger_seal import checked, forge, write_sessions

from appliance.records import integrity
from appliance.records.ledger import open_readonly, verify
from appliance.records.seal import KeySeal, make_key


def key_seal(folder):
    folder.mkdir(exist_ok=True)
    make_key(folder / "ledger.key")
    return KeySeal(folder / "ledger.key", folder / "anchor.json")


def chain_of(path):
    conn = open_readonly(path)
    try:
        return verify(conn)
    finally:
        conn.close()


def edit(path, sql: str) -> None:
    conn = sqlite3.connect(path)
    conn.execute(sql)
    conn.commit()
    conn.close()


# Event 8 is session 2's fluoro_off (start 6, fluoro_on 7, fluoro_off 8, alarm 9, end 10).
@pytest.mark.parametrize("column, value", [
    ("session_id", "1"), ("t_wall", "t_wall + 1"), ("t_monotonic", "t_monotonic - 10"), ("kind", "'alarm'"),
    ("fluoro_time_s", "30.0"), ("air_kerma_mgy", "1.5"), ("dap_gy_cm2", "0.15"), ("d_fluoro_time_s", "30.0"),
    ("d_air_kerma_mgy", "1.5"), ("d_dap_gy_cm2", "0.15"),
    ("detail", "json_set(detail, '$.dap_gy_cm2', 0.15)"),
])
def test_every_recorded_column_of_an_event_is_in_its_hash(tmp_path, column, value):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, None)
    assert chain_of(path).ok
    edit(path, f"UPDATE events SET {column} = {value} WHERE id = 8")
    report = chain_of(path)
    assert not report.ok and report.first_bad_id == 8 and "do not match its hash" in report.message, report.message


def test_an_event_removed_and_the_chain_recomputed_leaves_a_gap_that_is_reported(tmp_path):
    """Session 2's alarm (event 9) deleted and every link recomputed: each link checks out,
    but the ids jump from 8 to 10, and that is reported at the first event after the gap."""
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, None)
    forge(path, "DELETE FROM events WHERE id = 9")
    report = chain_of(path)
    assert not report.ok and report.first_bad_id == 10 and "events 9..9 are missing" in report.message, report.message


def test_a_gap_is_found_when_checking_on_from_an_earlier_report(tmp_path):
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, None, sessions=(("Dr A", 2.0),))
    first = chain_of(path)
    assert first.ok and first.last[0] == 5
    write_sessions(path, None, sessions=(("Dr B", 3.0),))
    forge(path, "DELETE FROM events WHERE id = 6")          # the second session's start
    conn = open_readonly(path)
    try:
        report = verify(conn, first.last)
    finally:
        conn.close()
    assert not report.ok and report.first_bad_id == 7 and "events 6..6 are missing" in report.message, report.message


@pytest.mark.parametrize("column", ["fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2"])
@pytest.mark.parametrize("factor", [0.5, 1.0001])
def test_a_sessions_total_edited_alone_is_reported_by_name(tmp_path, column, factor):
    """A session's total changed in the sessions table, even by one part in ten thousand,
    no longer matches its chained session_end record."""
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, None)
    edit(path, f"UPDATE sessions SET {column} = {column} * {factor} WHERE id = 2")
    report = chain_of(path)
    assert not report.ok and f"session 2: {column}" in report.message, report.message


def test_an_event_appended_without_the_key_is_caught_by_the_mac_check(tmp_path):
    """A forger adds a run after the sealed history (a copy of session 3's fluoro_off with
    half its kerma) and recomputes the chain: the plain chain is fooled, the seal is not."""
    seal = key_seal(tmp_path / "seal")
    path = tmp_path / "ledger.sqlite"
    write_sessions(path, seal)
    forge(path, "INSERT INTO events (id, session_id, t_wall, t_monotonic, kind, fluoro_time_s, air_kerma_mgy, dap_gy_cm2, "
                "d_fluoro_time_s, d_air_kerma_mgy, d_dap_gy_cm2, detail, prev_hash, hash, mac) "
                "SELECT 16, session_id, t_wall + 1, t_monotonic + 1, kind, fluoro_time_s, air_kerma_mgy / 2, dap_gy_cm2, "
                "d_fluoro_time_s, d_air_kerma_mgy / 2, d_dap_gy_cm2, detail, '', '', NULL FROM events WHERE id = 13")
    assert chain_of(path).ok
    report = checked(path, seal)
    assert not report.ok and report.first_bad_id == 16 and "has no MAC" in report.message, report.message


def test_a_ledger_replaced_by_one_sealed_with_another_key_is_caught_by_the_anchor_alone(tmp_path):
    """The same sessions written again under a key the forger made: every hash is the same
    (the figures and times are), but the MACs differ from the ones the real anchor holds, which
    anyone can check without the key."""
    real, other = key_seal(tmp_path / "real"), key_seal(tmp_path / "other")
    path, forged = tmp_path / "ledger.sqlite", tmp_path / "forged.sqlite"
    write_sessions(path, real)
    write_sessions(forged, other)
    anchor = json.loads(real.anchor_path.read_text())
    conn = open_readonly(forged)
    row = conn.execute("SELECT hash, mac FROM events WHERE id = ?", (anchor["count"],)).fetchone()
    conn.close()
    assert row["hash"] == anchor["hash"] and row["mac"] != anchor["mac"]
    path.unlink()
    for suffix in ("-wal", "-shm"):
        (tmp_path / f"ledger.sqlite{suffix}").unlink(missing_ok=True)
    shutil.copy(forged, path)
    assert chain_of(path).ok
    conn = open_readonly(path)
    try:
        report = integrity.check(conn, None, real.anchor_path)
    finally:
        conn.close()
    assert not report.ok and "differs from the anchor" in report.message, report.message

