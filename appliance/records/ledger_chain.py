"""The ledger's tamper evidence: each event row carries `hash = sha256(prev_hash + canonical
row)`, the first event chaining to GENESIS; `verify()` walks the chain and reports the first
broken link, and any sessions row that disagrees with its chained start and end events.
"""

from __future__ import annotations

import hashlib
import json
import math
import sqlite3
from dataclasses import dataclass

from .ledger_schema import EVENT_COLUMNS

GENESIS = "0" * 64


def canonical_detail(detail: dict) -> str:
    return json.dumps(detail, sort_keys=True, separators=(",", ":"), allow_nan=False)


def event_hash(prev_hash: str, row: dict) -> str:
    """The chain link of one event row (every column but `hash`)."""
    body = [row["id"], row["session_id"], row["t_wall"], row["t_monotonic"], row["kind"], row["fluoro_time_s"],
            row["air_kerma_mgy"], row["dap_gy_cm2"], row["d_fluoro_time_s"], row["d_air_kerma_mgy"],
            row["d_dap_gy_cm2"], row["detail"], prev_hash]
    text = json.dumps(body, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class ChainReport:
    ok: bool
    events: int
    first_bad_id: int | None
    message: str
    last: tuple[int, str] | None = None   # (id, hash) of the last event checked, to resume from


def verify(conn: sqlite3.Connection, resume: tuple[int, str] | None = None) -> ChainReport:
    """Walk the chain from the first event (or on from `resume`, an earlier report's `last`);
    report the first broken link, and any session whose recorded totals differ from its events."""
    prev = GENESIS if resume is None else resume[1]
    count = 0
    expected_id = None if resume is None else resume[0] + 1
    last = resume
    for r in conn.execute(f"SELECT {', '.join(EVENT_COLUMNS)} FROM events WHERE id > ? ORDER BY id",
                          (0 if resume is None else resume[0],)):
        row = dict(r)
        count += 1
        if expected_id is not None and row["id"] != expected_id:
            return ChainReport(False, count, row["id"], f"event {row['id']}: events {expected_id}..{row['id'] - 1} are missing")
        if row["prev_hash"] != prev:
            return ChainReport(False, count, row["id"], f"event {row['id']}: does not link to the event before it "
                                                         "(an event was removed or changed)")
        if event_hash(prev, row) != row["hash"]:
            return ChainReport(False, count, row["id"], f"event {row['id']}: its contents do not match its hash (it was changed)")
        prev = row["hash"]
        expected_id = row["id"] + 1
        last = (row["id"], row["hash"])
    # Sessions whose end was checked by an earlier report (before `resume`) are not checked again.
    for s in conn.execute("SELECT * FROM sessions WHERE ended_wall IS NOT NULL AND id NOT IN "
                          "(SELECT session_id FROM events WHERE kind = 'session_end' AND id <= ?) ORDER BY id",
                          (0 if resume is None else resume[0],)):
        end = conn.execute("SELECT detail FROM events WHERE session_id = ? AND kind = 'session_end' ORDER BY id DESC LIMIT 1",
                           (s["id"],)).fetchone()
        if end is None:
            return ChainReport(False, count, None, f"session {s['id']}: marked ended but has no session_end event")
        d = json.loads(end["detail"])
        for name in ("fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2"):
            if not math.isclose(d[name], s[name], rel_tol=1e-9, abs_tol=1e-12):
                return ChainReport(False, count, None, f"session {s['id']}: {name} {s[name]!r} differs from its "
                                                       f"chained session_end record {d[name]!r} (the sessions table was changed)")
    problem = session_rows_problem(conn, 0 if resume is None else resume[0])
    if problem:
        return ChainReport(False, count, None, problem)
    return ChainReport(True, count, None, f"{count} events, chain intact", last)


def session_rows_problem(conn: sqlite3.Connection, after: int = 0) -> str | None:
    """Why a sessions row disagrees with its chained events (operator, case, fluoroscope and start
    against session_start; end, totals, runs, alarms and saves against session_end), or None."""
    starts = {r["session_id"]: r for r in conn.execute(
        "SELECT session_id, t_wall, detail FROM events WHERE kind = 'session_start' AND id > ?", (after,))}
    for sid, start in starts.items():
        s = conn.execute("SELECT * FROM sessions WHERE id = ?", (sid,)).fetchone()
        if s is None:
            return f"session {sid}: its row was deleted from the sessions table (its events remain)"
        d = json.loads(start["detail"])
        for column, value in (("operator", d.get("operator")), ("case_title", d.get("case")),
                              ("fluoroscope", d.get("fluoroscope")), ("started_wall", start["t_wall"])):
            if s[column] != value:
                return (f"session {sid}: {column} {s[column]!r} differs from its chained session_start record "
                        f"{value!r} (the sessions table was changed)")
    ends = conn.execute("SELECT e.session_id, e.t_wall, e.detail, s.ended_wall, s.end_reason, s.runs, s.alarms, s.saves "
                        "FROM events e JOIN sessions s ON s.id = e.session_id "
                        "WHERE e.kind = 'session_end' AND e.id > ?", (after,))
    for e in ends:
        d = json.loads(e["detail"])
        for column, value in (("ended_wall", e["t_wall"]), ("end_reason", d.get("reason")), ("runs", d.get("runs")),
                              ("alarms", d.get("alarms")), ("saves", d.get("saves"))):
            if value is not None and e[column] != value:
                return (f"session {e['session_id']}: {column} {e[column]!r} differs from its chained session_end "
                        f"record {value!r} (the sessions table was changed)")
    return None
