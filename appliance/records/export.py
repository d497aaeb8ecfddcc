"""Admin export of the ledger: CSV and JSON of sessions and events, DICOM RDSR per session.

Files written (in `out_dir`, which is created if missing):
  csv:  sessions.csv and events.csv
  json: ledger.json (sessions, each with its events)
  rdsr: session-<id>.dcm for each ended session
Nothing is ever overwritten: if any target exists the export refuses before writing. Each
file is written atomically; if one fails (disk full, no permission) the files this export
already wrote are removed, so a failed export leaves nothing behind.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import sqlite3
from collections.abc import Iterable, Sequence
from pathlib import Path

from ..atomic_file import write_atomic
from ..errors import FluorosimError
from . import dicom, rdsr
from .ledger import EVENT_COLUMNS, SESSION_COLUMNS, verify

FORMATS = ("csv", "json", "rdsr")

SESSION_CSV_COLUMNS = ("session_id", "operator", "case", "fluoroscope", "started_utc", "ended_utc", "end_reason",
                       "fluoro_time_s", "fluoro_time_min", "air_kerma_mgy", "dap_gy_cm2", "runs", "alarms", "saves")
EVENT_CSV_COLUMNS = ("event_id", "session_id", "time_utc", "kind", "fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2",
                     "d_fluoro_time_s", "d_air_kerma_mgy", "d_dap_gy_cm2", "detail", "hash")


def parse_when(text: str, *, end: bool = False) -> float:
    """Unix time of an ISO date or date-time. A bare date as `end` means the end of that day;
    a time without an offset is the appliance's local time."""
    try:
        if len(text) == 10:
            day = dt.date.fromisoformat(text)
            when = dt.datetime.combine(day + dt.timedelta(days=1) if end else day, dt.time())
        else:
            when = dt.datetime.fromisoformat(text)
    except ValueError:
        raise FluorosimError(f"'{text}' is not a date; write it as YYYY-MM-DD or YYYY-MM-DDTHH:MM[:SS][+HH:MM]") from None
    if when.tzinfo is None:
        when = when.astimezone()  # local time
    return when.timestamp()


def iso(t_wall: float | None) -> str:
    if t_wall is None:
        return ""
    return dt.datetime.fromtimestamp(t_wall, tz=dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def sessions_between(conn: sqlite3.Connection, since: float | None, until: float | None) -> list[dict]:
    """Sessions that started in [since, until), oldest first."""
    rows = conn.execute(f"SELECT {', '.join(SESSION_COLUMNS)} FROM sessions WHERE started_wall >= ? AND started_wall < ? "
                        "ORDER BY started_wall, id", (since if since is not None else float("-inf"),
                                                       until if until is not None else float("inf")))
    return [dict(r) for r in rows]


def events_of(conn: sqlite3.Connection, session_id: int) -> list[dict]:
    return [dict(r) for r in conn.execute(f"SELECT {', '.join(EVENT_COLUMNS)} FROM events WHERE session_id = ? ORDER BY id",
                                          (session_id,))]


def _csv_bytes(header: Sequence[str], rows: Iterable[Sequence[object]]) -> bytes:
    buffer = io.StringIO(newline="")
    writer = csv.writer(buffer, lineterminator="\r\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue().encode("utf-8")


def _session_fields(s: dict) -> dict:
    return {"session_id": s["id"], "operator": s["operator"], "case": s["case_title"], "fluoroscope": s["fluoroscope"],
            "started_utc": iso(s["started_wall"]), "ended_utc": iso(s["ended_wall"]), "end_reason": s["end_reason"] or "",
            "fluoro_time_s": s["fluoro_time_s"], "fluoro_time_min": s["fluoro_time_s"] / 60.0,
            "air_kerma_mgy": s["air_kerma_mgy"], "dap_gy_cm2": s["dap_gy_cm2"], "runs": s["runs"], "alarms": s["alarms"],
            "saves": s["saves"]}


def _event_fields(e: dict) -> dict:
    return {"event_id": e["id"], "session_id": e["session_id"], "time_utc": iso(e["t_wall"]), "kind": e["kind"],
            "fluoro_time_s": e["fluoro_time_s"], "air_kerma_mgy": e["air_kerma_mgy"], "dap_gy_cm2": e["dap_gy_cm2"],
            "d_fluoro_time_s": e["d_fluoro_time_s"], "d_air_kerma_mgy": e["d_air_kerma_mgy"],
            "d_dap_gy_cm2": e["d_dap_gy_cm2"], "detail": e["detail"], "hash": e["hash"]}


def build_files(conn: sqlite3.Connection, sessions: list[dict], fmt: str) -> tuple[dict[str, bytes], list[str]]:
    """{file name: contents} of an export, and notes on what was left out."""
    notes: list[str] = []
    if fmt == "csv":
        events = [e for s in sessions for e in events_of(conn, s["id"])]
        return ({"sessions.csv": _csv_bytes(SESSION_CSV_COLUMNS, ([_session_fields(s)[c] for c in SESSION_CSV_COLUMNS]
                                                                  for s in sessions)),
                 "events.csv": _csv_bytes(EVENT_CSV_COLUMNS, ([_event_fields(e)[c] for c in EVENT_CSV_COLUMNS]
                                                              for e in events))}, notes)
    if fmt == "json":
        chain = verify(conn)
        doc = {"format": "fluorosim ledger export 1", "exported_utc": iso(dt.datetime.now(dt.UTC).timestamp()),
               "chain": {"ok": chain.ok, "message": chain.message},
               "sessions": [{**_session_fields(s),
                             "events": [{**_event_fields(e), "detail": json.loads(e["detail"])} for e in events_of(conn, s["id"])]}
                            for s in sessions]}
        return {"ledger.json": (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode("utf-8")}, notes
    if fmt == "rdsr":
        files = {}
        for s in sessions:
            if s["ended_wall"] is None:
                notes.append(f"session {s['id']} is still open; no dose report until it ends")
                continue
            files[f"session-{s['id']:06d}.dcm"] = dicom.encode(rdsr.session_report(s, events_of(conn, s["id"])))
        return files, notes
    raise FluorosimError(f"unknown export format '{fmt}'; choose one of {', '.join(FORMATS)}")


def export(conn: sqlite3.Connection, since: float | None, until: float | None, fmt: str, out_dir: Path) -> tuple[list[Path], list[str]]:
    """Write the export; returns the files written and notes. Refuses to overwrite anything."""
    sessions = sessions_between(conn, since, until)
    files, notes = build_files(conn, sessions, fmt)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FluorosimError(f"{out_dir}: cannot create the export folder ({e.strerror or e}); choose a writable place") from None
    existing = [name for name in files if (out_dir / name).exists()]
    if existing:
        raise FluorosimError(f"{out_dir / existing[0]}: already exists; refusing to overwrite "
                             f"({len(existing)} of the export's files exist); choose an empty --out folder")
    written: list[Path] = []
    try:
        for name, data in files.items():
            written.append(write_atomic(out_dir / name, data, overwrite=False))
    except FluorosimError:
        for path in written:
            path.unlink(missing_ok=True)
        raise
    return written, notes
