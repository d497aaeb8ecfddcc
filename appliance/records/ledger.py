"""The dose and session ledger: SQLite, one writer, every event chained by a hash.

Durability: WAL journal with synchronous=FULL, so a committed event survives a power cut;
each `record()` call is one transaction, so a kill leaves whole batches or nothing.
Tamper evidence: each event row carries `hash = sha256(prev_hash + canonical row)`, the
first event chaining to 64 zeros; `verify()` reports the first row whose link is broken
(ledger_chain.py).
Where a seal is configured (records/seal.py) each row also carries an HMAC with a key the
service cannot read, and the newest entry is anchored outside the file; the sessions rows
are checked against the chained session_start and session_end events.
Recovery: opening the ledger finds sessions that never ended (power loss, kill -9), closes
an exposure left open, and ends the session with totals equal to the sum of its events'
increments. Schema changes are numbered migrations run at open (PRAGMA user_version;
ledger_schema.py, with the connections).

Times: `t_wall` is Unix time (s); `t_monotonic` is the console's clock (s), mapped to wall
time through the anchor given at `start_session`.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import sqlite3
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path

from ..console.run import recovered_technique
from ..console.state import ConsoleEvent
from ..errors import FluorosimError
from .ledger_chain import GENESIS, ChainReport, canonical_detail, event_hash, session_rows_problem, verify
from .ledger_schema import (
    EVENT_COLUMNS,
    FULL_DISK_BYTES,
    MIGRATIONS,
    SESSION_COLUMNS,
    connect,
    migrate,
    open_readonly,
    open_writer,
)
from .seal import Seal, seal_from_environment

# The ledger's schema, connections and chain live in ledger_schema.py and ledger_chain.py;
# every command and test that reads the ledger imports them from here, with the writer.
__all__ = ["EVENT_COLUMNS", "FULL_DISK_BYTES", "GENESIS", "MIGRATIONS", "SESSION_COLUMNS", "ChainReport", "Ledger",
           "LedgerBusy", "carry_from", "event_hash", "open_readonly", "open_writer", "session_rows_problem", "verify"]

log = logging.getLogger(__name__)

class LedgerBusy(FluorosimError):
    """Another fluorosim process holds the ledger: nothing else may be opened."""


class _FromEnvironment:
    """The default seal: the one the service's environment names."""


_FROM_ENVIRONMENT = _FromEnvironment()


class Ledger:
    """The one writer of the ledger file; `seal` authenticates each event (default: the one
    the service's environment names, see records/seal.py; None: hash chain only)."""

    def __init__(self, path: str | Path, seal: Seal | None | _FromEnvironment = _FROM_ENVIRONMENT):
        self.path = Path(path)
        self.seal = seal_from_environment() if isinstance(seal, _FromEnvironment) else seal
        self._conn = connect(self.path, readonly=False)
        # One writer: a second process would otherwise "recover" a session that is still live.
        self._lock_fd = os.open(self.path, os.O_RDONLY)
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(self._lock_fd)
            self._conn.close()
            raise LedgerBusy(f"{self.path}: the ledger is open in another fluorosim process; stop it first") from None
        self.session_id: int | None = None
        self._anchor = (0.0, 0.0)
        try:
            migrate(self._conn, self.path)
            last = self._conn.execute("SELECT hash, mac FROM events ORDER BY id DESC LIMIT 1").fetchone()
            self._head = last["hash"] if last else GENESIS
            self._mac_head = (last["mac"] if last else None) or ""
            self.recovered: list[int] = self._recover()
            self._carried = carry_from(self._conn, self.recovered[-1]) if self.recovered else None
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
               "detail": canonical_detail(detail), "prev_hash": self._head}
        row_hash = event_hash(self._head, row)
        row["hash"] = row_hash
        row["mac"] = None if self.seal is None else self.seal.mac(next_id, self._mac_head, row_hash)
        self._conn.execute(f"INSERT INTO events ({', '.join(EVENT_COLUMNS)}) VALUES ({', '.join('?' * len(EVENT_COLUMNS))})",
                           [row[c] for c in EVENT_COLUMNS])
        self._conn.execute(
            "UPDATE sessions SET fluoro_time_s = fluoro_time_s + ?, air_kerma_mgy = air_kerma_mgy + ?, "
            "dap_gy_cm2 = dap_gy_cm2 + ?, runs = runs + ?, alarms = alarms + ?, saves = saves + ? WHERE id = ?",
            (row["d_fluoro_time_s"], row["d_air_kerma_mgy"], row["d_dap_gy_cm2"], int(kind == "fluoro_off"),
             int(kind == "alarm"), int(kind == "save"), session_id))
        self._head = row["hash"]
        self._mac_head = row["mac"] or self._mac_head

    def _transaction(self, work: Callable[[], object]) -> None:
        head, mac_head = self._head, self._mac_head
        try:
            self._conn.execute("BEGIN IMMEDIATE")
            work()
            self._conn.execute("COMMIT")
        except BaseException as e:
            self._head, self._mac_head = head, mac_head
            if self._conn.in_transaction:
                try:
                    self._conn.execute("ROLLBACK")
                except sqlite3.Error:
                    pass  # SQLite rolls back an unfinished transaction on its own at the next open
            if isinstance(e, sqlite3.OperationalError):
                raise FluorosimError(f"{self.path}: cannot write the ledger ({e}); free disk space or fix permissions; "
                                     "nothing already recorded is lost") from None
            raise
        if self.seal is not None:
            try:
                self.seal.advance(self._conn)
            except FluorosimError as e:
                # The events are committed and sealed; the anchor catches up at the next advance.
                log.warning("%s: %s", self.path, e)

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
                          "patient": patient or {}, **({"carried": self._carried} if self._carried else {})})
        self._transaction(work)
        self.session_id = holder["id"]
        self._carried = None  # carried into this session; the next one starts from its own record
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
            technique = recovered_technique(on, [{**e, "detail": json.loads(e["detail"])} for e in within])
            detail = {**on, **technique, "reason": reason, "start_t": open_run["t_monotonic"], "start_wall": open_run["t_wall"],
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

    def session_rows(self, session_id: int) -> tuple[dict, list[dict]]:
        """A session's row and its events in order, to build its DICOM objects (records.study)."""
        session = dict(self._conn.execute(f"SELECT {', '.join(SESSION_COLUMNS)} FROM sessions WHERE id = ?",
                                          (session_id,)).fetchone())
        events = [dict(r) for r in self._conn.execute(
            f"SELECT {', '.join(EVENT_COLUMNS)} FROM events WHERE session_id = ? ORDER BY id", (session_id,))]
        return session, events

    def carry_over(self) -> dict | None:
        """What the console continues from after a crash (21 CFR 1020.32: the cumulative timer is
        reset only by a person): {"fluoro_time_s", "alarms", "from_session"}, or None."""
        return self._carried

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None  # type: ignore[assignment]  # closed: every later call fails, as sqlite3's would
            os.close(self._lock_fd)

    def __enter__(self) -> Ledger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def carry_from(conn: sqlite3.Connection, session_id: int) -> dict | None:
    """Cumulative fluoroscopy time and alarm count a crashed session leaves to the next: its
    own since a person last reset the timer, plus what it had carried from one before."""
    rows = [dict(r) for r in conn.execute(
        "SELECT kind, d_fluoro_time_s, detail FROM events WHERE session_id = ? ORDER BY id", (session_id,))]
    time_s, alarms = 0.0, 0
    for r in rows:
        detail = json.loads(r["detail"])
        if r["kind"] == "session_start":
            carried = detail.get("carried") or {}
            time_s, alarms = float(carried.get("fluoro_time_s", 0.0)), int(carried.get("alarms", 0))
        elif r["kind"] == "alarm_reset" and detail.get("timer") == "reset":
            time_s, alarms = 0.0, 0
        time_s += r["d_fluoro_time_s"]
        alarms += r["kind"] == "alarm"
    if time_s <= 0 and alarms == 0:
        return None
    return {"fluoro_time_s": time_s, "alarms": alarms, "from_session": session_id}
