"""Each dose report carries the ledger entry that ended its session (count, hash, MAC when
sealed), and `logs verify --rdsr` checks the ledger against it: a deleted tail or a rewritten
and re-chained ledger, which pass the ledger's own check when it is not sealed, show against
the reports already sent. Expected anchors are read from the ledger file with plain SQL."""

from __future__ import annotations

import json
import shutil
import sqlite3
import subprocess

import pydicom
import pytest
from dicom_session import record_session
from test_ledger_seal import rechain, seal, write_sessions  # noqa: F401 - the fixture

from appliance.cli import main
from appliance.records import rdsr_anchor


def last_event(path, session_id: int) -> tuple[int, str, str | None]:
    with sqlite3.connect(path) as conn:
        return conn.execute("SELECT id, hash, mac FROM events WHERE session_id = ? ORDER BY id DESC LIMIT 1",
                            (session_id,)).fetchone()


def export_reports(ledger, out) -> list:
    assert main(["logs", "export", "--ledger", str(ledger), "--format", "rdsr", "--out", str(out)]) == 0
    return sorted(out.glob("session-*.dcm"))


def test_each_exported_report_carries_the_entry_that_ended_its_session(tmp_path, capsys):
    ledger = tmp_path / "ledger.sqlite"
    write_sessions(ledger, None)
    reports = export_reports(ledger, tmp_path / "out")
    assert [p.name for p in reports] == ["session-000001.dcm", "session-000002.dcm", "session-000003.dcm"]
    for sid, path in enumerate(reports, start=1):
        event_id, event_hash, mac = last_event(ledger, sid)
        ds = pydicom.dcmread(path)
        # Five events a session (start, on, off, alarm, end): session N ends at event 5N.
        assert event_id == 5 * sid and mac is None
        assert rdsr_anchor.read(ds) == {"count": event_id, "hash": event_hash}
        assert ds[0x0009, 0x0010].value == "FLUOROSIM LEDGER ANCHOR" and ds[0x0009, 0x1011].VR == "LO"
    capsys.readouterr()
    assert main(["logs", "verify", "--ledger", str(ledger), "--rdsr", *map(str, reports)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 4 and out[3].endswith("session-000003.dcm: the ledger holds event 15 as the report recorded it")


def test_a_deleted_last_session_shows_against_its_report(tmp_path, capsys):
    ledger = tmp_path / "ledger.sqlite"
    write_sessions(ledger, None)
    first, second, third = export_reports(ledger, tmp_path / "out")
    with sqlite3.connect(ledger) as conn:
        removed = conn.execute("DELETE FROM events WHERE session_id = 3").rowcount
        conn.execute("DELETE FROM sessions WHERE id = 3")
    assert removed == 5
    capsys.readouterr()
    # The ledger alone (unsealed, no anchor file) is a valid shorter chain ...
    assert main(["logs", "verify", "--ledger", str(ledger)]) == 0
    # ... but the report sent for session 3 names an entry it no longer has.
    assert main(["logs", "verify", "--ledger", str(ledger), "--rdsr", str(first), str(third)]) == 1
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{third}: NOT INTACT against this dose report")
    assert "the anchor names event 15 but the ledger ends at event 10: the last 5 event(s) were removed" in err[0]
    assert f"{first}: the ledger holds event 5" in captured.out
    assert main(["logs", "verify", "--ledger", str(ledger), "--rdsr", str(second)]) == 0


def test_a_rewritten_and_rechained_session_shows_against_its_report(tmp_path, capsys):
    ledger = tmp_path / "ledger.sqlite"
    write_sessions(ledger, None)
    first, second, _ = export_reports(ledger, tmp_path / "out")
    with sqlite3.connect(ledger) as conn:
        conn.row_factory = sqlite3.Row
        # Halve session 2's kerma in its events, its row and its end record, then re-chain.
        conn.execute("UPDATE events SET air_kerma_mgy = air_kerma_mgy / 2, d_air_kerma_mgy = d_air_kerma_mgy / 2 "
                     "WHERE session_id = 2")
        conn.execute("UPDATE sessions SET air_kerma_mgy = air_kerma_mgy / 2 WHERE id = 2")
        for event_id, detail in conn.execute("SELECT id, detail FROM events WHERE session_id = 2").fetchall():
            d = json.loads(detail)
            if "air_kerma_mgy" in d:
                d["air_kerma_mgy"] /= 2
            conn.execute("UPDATE events SET detail = ? WHERE id = ?", (json.dumps(d, sort_keys=True), event_id))
        rechain(conn)
    capsys.readouterr()
    assert main(["logs", "verify", "--ledger", str(ledger), "--rdsr", str(first)]) == 0   # session 1 is untouched
    assert main(["logs", "verify", "--ledger", str(ledger), "--rdsr", str(second)]) == 1
    err = capsys.readouterr().err
    assert "event 10: differs from the anchor kept outside the ledger" in err


def test_a_sealed_ledgers_report_carries_the_mac_the_seal_anchored(tmp_path, seal, capsys):  # noqa: F811
    ledger = tmp_path / "ledger.sqlite"
    write_sessions(ledger, seal)
    reports = export_reports(ledger, tmp_path / "out")
    event_id, event_hash, mac = last_event(ledger, 3)
    assert mac is not None
    assert rdsr_anchor.read(pydicom.dcmread(reports[-1])) == {"count": event_id, "hash": event_hash, "mac": mac}
    # At the last session's end its last entry is the ledger's newest: the one the seal anchored.
    assert json.loads((tmp_path / "anchor.json").read_text()) == {"count": event_id, "hash": event_hash, "mac": mac}


def test_what_is_not_a_fluorosim_report_is_one_line(tmp_path, capsys):
    session = record_session(tmp_path / "var")
    text = tmp_path / "notes.txt"
    text.write_text("not DICOM\n")
    for path, why in ((text, "not a DICOM file"), (session.images[0], "carries no fluorosim ledger anchor"),
                      (tmp_path / "missing.dcm", "cannot read the dose report (No such file or directory)")):
        assert main(["logs", "verify", "--ledger", str(session.ledger), "--rdsr", str(path)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"fluorosim: {path}: {why}"), err


@pytest.mark.skipif(shutil.which("dsrdump") is None, reason="dsrdump (Debian package dcmtk) is not installed")
def test_dsrdump_reads_the_anchored_report_cleanly(tmp_path):
    session = record_session(tmp_path / "var")
    dump = subprocess.run(["dsrdump", str(session.report)], capture_output=True, text=True)
    assert dump.returncode == 0 and "rror" not in dump.stderr and "arning" not in dump.stderr, dump.stderr
