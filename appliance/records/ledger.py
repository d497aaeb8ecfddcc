"""The dose and session ledger: SQLite, one writer, every event chained by a hash.

Durability: WAL journal with synchronous=FULL, so a committed event survives a power cut;
each `record()` call is one transaction, so a kill leaves whole batches or nothing.
Tamper evidence: each event row carries `hash = sha256(prev_hash + canonical row)`, the
first event chaining to 64 zeros; `verify()` reports the first row whose link is broken.
Recovery: opening the ledger finds sessions that never ended (power loss, kill -9), closes
an exposure left open, and ends the session with totals equal to the sum of its events'
increments. Schema changes are numbered migrations run at open (PRAGMA user_version).

Times: `t_wall` is Unix time (s); `t_monotonic` is the console's clock (s), mapped to wall
time through the anchor given at `start_session`.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import math
import os
import sqlite3
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from ..console.state import ConsoleEvent
from ..errors import FluorosimError

GENESIS = "0" * 64

MIGRATIONS = (
    # 1: sessions, chained events, running totals.
    """
    CREATE TABLE sessions (
        id INTEGER PRIMARY KEY,
        operator TEXT NOT NULL,
        case_title TEXT NOT NULL,
        fluoroscope TEXT NOT NULL,
        started_wall REAL NOT NULL,
        ended_wall REAL,
        end_reason TEXT,
        fluoro_time_s REAL NOT NULL DEFAULT 0,
        air_kerma_mgy REAL NOT NULL DEFAULT 0,
        dap_gy_cm2 REAL NOT NULL DEFAULT 0,
        runs INTEGER NOT NULL DEFAULT 0,
        alarms INTEGER NOT NULL DEFAULT 0,
        saves INTEGER NOT NULL DEFAULT 0
    );
    CREATE TABLE events (
        id INTEGER PRIMARY KEY,
        session_id INTEGER NOT NULL REFERENCES sessions(id),
        t_wall REAL NOT NULL,
        t_monotonic REAL,
        kind TEXT NOT NULL,
        fluoro_time_s REAL NOT NULL,
        air_kerma_mgy REAL NOT NULL,
        dap_gy_cm2 REAL NOT NULL,
        d_fluoro_time_s REAL NOT NULL,
        d_air_kerma_mgy REAL NOT NULL,
        d_dap_gy_cm2 REAL NOT NULL,
        detail TEXT NOT NULL,
        prev_hash TEXT NOT NULL,
        hash TEXT NOT NULL
    );
    CREATE INDEX events_by_session ON events(session_id, id);
    CREATE INDEX sessions_by_start ON sessions(started_wall);
    """,
)

EVENT_COLUMNS = ("id", "session_id", "t_wall", "t_monotonic", "kind", "fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2",
                 "d_fluoro_time_s", "d_air_kerma_mgy", "d_dap_gy_cm2", "detail", "prev_hash", "hash")
SESSION_COLUMNS = ("id", "operator", "case_title", "fluoroscope", "started_wall", "ended_wall", "end_reason",
                   "fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2", "runs", "alarms", "saves")


def _canonical_detail(detail: dict) -> str:
    return json.dumps(detail, sort_keys=True, separators=(",", ":"), allow_nan=False)


def event_hash(prev_hash: str, row: dict) -> str:
    """The chain link of one event row (every column but `hash`)."""
    body = [row["id"], row["session_id"], row["t_wall"], row["t_monotonic"], row["kind"], row["fluoro_time_s"],
            row["air_kerma_mgy"], row["dap_gy_cm2"], row["d_fluoro_time_s"], row["d_air_kerma_mgy"],
            row["d_dap_gy_cm2"], row["detail"], prev_hash]
    text = json.dumps(body, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _migrate(conn: sqlite3.Connection, path: Path) -> None:
    version = conn.execute("PRAGMA user_version").fetchone()[0]
    if version > len(MIGRATIONS):
        raise FluorosimError(f"{path}: ledger schema {version} is newer than this fluorosim knows "
                             f"({len(MIGRATIONS)}); update fluorosim before opening it")
    for number in range(version, len(MIGRATIONS)):
        with conn:
            conn.executescript("BEGIN IMMEDIATE;" + MIGRATIONS[number] + f"; PRAGMA user_version = {number + 1};")


def _connect(path: Path, readonly: bool) -> sqlite3.Connection:
    try:
        if readonly:
            if not path.is_file():
                raise FluorosimError(f"{path}: no ledger there; give --ledger PATH or check data_dir in the appliance profile")
            conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True, isolation_level=None, check_same_thread=False)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
        conn.row_factory = sqlite3.Row
        conn.execute("PRAGMA busy_timeout = 5000")
        if not readonly:
            conn.execute("PRAGMA journal_mode = WAL")
            conn.execute("PRAGMA synchronous = FULL")
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.DatabaseError as e:
        raise FluorosimError(f"{path}: cannot open the ledger ({e}); check the file and its folder's permissions") from None
    except OSError as e:
        raise FluorosimError(f"{path}: cannot create the ledger's folder ({e.strerror or e})") from None


def open_readonly(path: str | Path) -> sqlite3.Connection:
    """A read-only connection for `logs verify` and `logs export`, safe while the daemon writes."""
    path = Path(path)
    conn = _connect(path, readonly=True)
    version = conn.execute("PRAGMA user_version").fetchone()[0]
    if version == 0:
        raise FluorosimError(f"{path}: not a fluorosim ledger (no schema)")
    if version > len(MIGRATIONS):
        raise FluorosimError(f"{path}: ledger schema {version} is newer than this fluorosim knows; update fluorosim")
    return conn


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
    return ChainReport(True, count, None, f"{count} events, chain intact", last)


class Ledger:
    """The one writer of the ledger file."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._conn = _connect(self.path, readonly=False)
        # One writer: a second process would otherwise "recover" a session that is still live.
        self._lock_fd = os.open(self.path, os.O_RDONLY)
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._lock_fd)
            self._conn.close()
            raise FluorosimError(f"{self.path}: the ledger is open in another fluorosim process; stop it first") from None
        self.session_id: int | None = None
        self._anchor = (0.0, 0.0)
        try:
            _migrate(self._conn, self.path)
            last = self._conn.execute("SELECT hash FROM events ORDER BY id DESC LIMIT 1").fetchone()
            self._head = last["hash"] if last else GENESIS
            self.recovered: list[int] = self._recover()
        except BaseException:
            self.close()
            raise

    # --- writing ------------------------------------------------------------------
    def _insert(self, session_id: int, t_wall: float, t_mono: float | None, kind: str, totals: tuple, deltas: tuple,
                detail: dict) -> None:
        next_id = (self._conn.execute("SELECT max(id) FROM events").fetchone()[0] or 0) + 1
        row = {"id": next_id, "session_id": session_id, "t_wall": float(t_wall),
               "t_monotonic": None if t_mono is None else float(t_mono), "kind": kind,
               "fluoro_time_s": float(totals[0]), "air_kerma_mgy": float(totals[1]), "dap_gy_cm2": float(totals[2]),
               "d_fluoro_time_s": float(deltas[0]), "d_air_kerma_mgy": float(deltas[1]), "d_dap_gy_cm2": float(deltas[2]),
               "detail": _canonical_detail(detail), "prev_hash": self._head}
        row["hash"] = event_hash(self._head, row)
        self._conn.execute(f"INSERT INTO events ({', '.join(EVENT_COLUMNS)}) VALUES ({', '.join('?' * len(EVENT_COLUMNS))})",
                           [row[c] for c in EVENT_COLUMNS])
        self._conn.execute(
            "UPDATE sessions SET fluoro_time_s = fluoro_time_s + ?, air_kerma_mgy = air_kerma_mgy + ?, "
            "dap_gy_cm2 = dap_gy_cm2 + ?, runs = runs + ?, alarms = alarms + ?, saves = saves + ? WHERE id = ?",
            (row["d_fluoro_time_s"], row["d_air_kerma_mgy"], row["d_dap_gy_cm2"], int(kind == "fluoro_off"),
             int(kind == "alarm"), int(kind == "save"), session_id))
        self._head = row["hash"]

    def _transaction(self, work: Callable[[], object]) -> None:
        head = self._head
        try:
            self._conn.execute("BEGIN IMMEDIATE")
            work()
            self._conn.execute("COMMIT")
        except BaseException as e:
            self._head = head
            if self._conn.in_transaction:
                try:
                    self._conn.execute("ROLLBACK")
                except sqlite3.Error:
                    pass  # SQLite rolls back an unfinished transaction on its own at the next open
            if isinstance(e, sqlite3.OperationalError):
                raise FluorosimError(f"{self.path}: cannot write the ledger ({e}); free disk space or fix permissions; "
                                     "nothing already recorded is lost") from None
            raise

    def start_session(self, operator: str, case: str, fluoroscope: str, t_wall: float,
                      t_monotonic: float | None = None, equipment: dict | None = None,
                      patient: dict | None = None) -> int:
        """Open a session; console times map to wall time as t_wall + (t - t_monotonic).
        Without `t_monotonic`, the anchor is time.monotonic() now. `equipment` (manufacturer,
        model, serial) and `patient` (the case's demographics) are kept with the session for
        the dose reports (see records.rdsr.equipment_of and patient_of)."""
        if self.session_id is not None:
            raise RuntimeError("a session is already open; end it first")
        self._anchor = (float(t_wall), time.monotonic() if t_monotonic is None else float(t_monotonic))
        holder: dict[str, int] = {}

        def work() -> None:
            cur = self._conn.execute("INSERT INTO sessions (operator, case_title, fluoroscope, started_wall) VALUES (?, ?, ?, ?)",
                                     (operator, case, fluoroscope, float(t_wall)))
            session_id = cur.lastrowid
            assert session_id is not None  # an INSERT into a rowid table always gives one
            holder["id"] = session_id
            self._insert(session_id, t_wall, self._anchor[1], "session_start", (0, 0, 0), (0, 0, 0),
                         {"operator": operator, "case": case, "fluoroscope": fluoroscope, "equipment": equipment or {},
                          "patient": patient or {}})
        self._transaction(work)
        self.session_id = holder["id"]
        return holder["id"]

    def wall(self, t_monotonic: float) -> float:
        return self._anchor[0] + (t_monotonic - self._anchor[1])

    def record(self, events: Sequence[ConsoleEvent]) -> None:
        """Append console events to the open session, all in one transaction."""
        if not events:
            return
        session_id = self.session_id
        if session_id is None:
            raise RuntimeError("no open session; call start_session first")

        def work() -> None:
            for ev in events:
                detail = dict(ev.detail)
                if "start_t" in detail:
                    detail["start_wall"] = self.wall(detail["start_t"])
                self._insert(session_id, self.wall(ev.t_monotonic), ev.t_monotonic, ev.kind,
                             (ev.fluoro_time_s, ev.air_kerma_mgy, ev.dap_gy_cm2),
                             (ev.d_fluoro_time_s, ev.d_air_kerma_mgy, ev.d_dap_gy_cm2), detail)
        self._transaction(work)

    def _close_session(self, session_id: int, t_wall: float, reason: str) -> None:
        """Inside a transaction: end an open run, then the session, totals from the events."""
        events = [dict(r) for r in self._conn.execute(
            f"SELECT {', '.join(EVENT_COLUMNS)} FROM events WHERE session_id = ? ORDER BY id", (session_id,))]
        last = events[-1]
        totals = (last["fluoro_time_s"], last["air_kerma_mgy"], last["dap_gy_cm2"])
        open_run = None
        for e in events:
            if e["kind"] == "fluoro_on":
                open_run = e
            elif e["kind"] == "fluoro_off":
                open_run = None
        if open_run is not None:
            # The exposure was cut off: close it with what its committed events account for.
            on = json.loads(open_run["detail"])
            within = [e for e in events if e["id"] > open_run["id"]]
            detail = {**on, "reason": reason, "start_t": open_run["t_monotonic"], "start_wall": open_run["t_wall"],
                      "duration_s": sum(e["d_fluoro_time_s"] for e in within),
                      "air_kerma_mgy": sum(e["d_air_kerma_mgy"] for e in within),
                      "dap_gy_cm2": sum(e["d_dap_gy_cm2"] for e in within),
                      "pulses": sum(1 for e in within if e["kind"] == "pulse")}
            self._insert(session_id, last["t_wall"], last["t_monotonic"], "fluoro_off", totals, (0, 0, 0), detail)
        sums = self._conn.execute(
            "SELECT sum(d_fluoro_time_s), sum(d_air_kerma_mgy), sum(d_dap_gy_cm2), "
            "sum(kind = 'fluoro_off'), sum(kind = 'alarm'), sum(kind = 'save') FROM events WHERE session_id = ?",
            (session_id,)).fetchone()
        ft, k, d, runs, alarms, saves = (sums[0] or 0.0, sums[1] or 0.0, sums[2] or 0.0, sums[3] or 0, sums[4] or 0, sums[5] or 0)
        self._insert(session_id, t_wall, None, "session_end", totals, (0, 0, 0),
                     {"reason": reason, "fluoro_time_s": ft, "air_kerma_mgy": k, "dap_gy_cm2": d,
                      "runs": runs, "alarms": alarms, "saves": saves})
        self._conn.execute("UPDATE sessions SET ended_wall = ?, end_reason = ?, fluoro_time_s = ?, air_kerma_mgy = ?, "
                           "dap_gy_cm2 = ?, runs = ?, alarms = ?, saves = ? WHERE id = ?",
                           (float(t_wall), reason, ft, k, d, runs, alarms, saves, session_id))

    def end_session(self, t_wall: float) -> None:
        """Close the open session with totals from its events. Record `Console.end(now)` first,
        so an exposure still in progress is accounted to its last instant."""
        if self.session_id is None:
            return
        sid = self.session_id
        self._transaction(lambda: self._close_session(sid, t_wall, "ended"))
        self.session_id = None

    def _recover(self) -> list[int]:
        """Close every session a crash left open, at the time of its last committed event."""
        open_ids = [r[0] for r in self._conn.execute("SELECT id FROM sessions WHERE ended_wall IS NULL ORDER BY id")]
        for sid in open_ids:
            last = self._conn.execute("SELECT max(t_wall) FROM events WHERE session_id = ?", (sid,)).fetchone()[0]
            if last is None:  # a session row without its start event cannot come from this code; keep it visible
                last = self._conn.execute("SELECT started_wall FROM sessions WHERE id = ?", (sid,)).fetchone()[0]
                self._transaction(partial(
                    self._conn.execute,
                    "UPDATE sessions SET ended_wall = ?, end_reason = 'recovered-empty' WHERE id = ?", (last, sid)))
                continue
            self._transaction(partial(self._close_session, sid, last, "recovered"))
        return open_ids

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None  # type: ignore[assignment]  # closed: every later call fails, as sqlite3's would
            os.close(self._lock_fd)

    def __enter__(self) -> Ledger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
