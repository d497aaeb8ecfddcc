"""A ledger that opens when it can: the appliance starts on a full disk and says so.

SQLite cannot open a WAL database on a disk with no free block (its -wal and -shm files need
space), yet refusing to start would leave the trainee with no image and the events of the
session nowhere. `open_ledger` therefore gives the real `Ledger` when it opens, and otherwise
this stand-in, which tries again at each call: until then every call raises the one-line
reason, so the records worker keeps the events in memory and the screen shows its banner,
and the first call after space returns opens the ledger (recovering what a crash left open)
and writes them. Another process holding the ledger still stops the start.

A crash may have left the last session open, and 21 CFR 1020.32 lets only a person reset the
cumulative fluoroscopy timer: the stand-in reads what that session carries over through a
read-only connection (which needs no free block; it reads the crash's WAL as it is), so the
console's timer and alarm count go on from the start, not only once the disk lets the ledger
open. The ledger computes the same figures from the same session when it opens and records
them in the new session's start.
"""

from __future__ import annotations

import logging
import shutil
import sqlite3
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..console.state import ConsoleEvent
from ..errors import FluorosimError
from .ledger import FULL_DISK_BYTES, Ledger, LedgerBusy, carry_from, open_readonly

log = logging.getLogger(__name__)


class DeferredLedger:
    """Stands in for `Ledger` (start_session, record, end_session, close) until it opens."""

    def __init__(self, path: Path, problem: str):
        self.path = Path(path)
        self.problem: str | None = problem
        self._ledger: Ledger | None = None
        self._pending_carry = pending_carry_over(self.path)

    def _open(self) -> Ledger:
        if self._ledger is None:
            try:
                self._ledger = Ledger(self.path)
            except LedgerBusy:
                raise
            except FluorosimError as e:
                self.problem = str(e)
                raise
            log.info("%s: the ledger opened; events held in memory are written now", self.path)
            if self._ledger.carry_over() != self._pending_carry:
                log.warning("%s: the session a crash ended carries %s, the console started from %s; the ledger "
                            "records the carried figures", self.path, self._ledger.carry_over(), self._pending_carry)
            self.problem = None
        return self._ledger

    @property
    def opened(self) -> bool:
        """Whether the real ledger is open (and the send queue in its file can be used)."""
        return self._ledger is not None

    @property
    def session_id(self) -> int | None:
        return None if self._ledger is None else self._ledger.session_id

    @property
    def recovered(self) -> list[int]:
        return [] if self._ledger is None else self._ledger.recovered

    def carry_over(self) -> dict | None:
        """What the console continues from after a crash: read from the file until it opens."""
        return self._pending_carry if self._ledger is None else self._ledger.carry_over()

    def start_session(self, *args: Any, **kwargs: Any) -> int:
        return self._open().start_session(*args, **kwargs)

    def session_rows(self, session_id: int) -> tuple[dict, list[dict]]:
        return self._open().session_rows(session_id)

    def record(self, events: Sequence[ConsoleEvent]) -> None:
        self._open().record(events)

    def end_session(self, t_wall: float) -> None:
        self._open().end_session(t_wall)

    def close(self) -> None:
        if self._ledger is not None:
            self._ledger.close()


def open_ledger(path: Path) -> Ledger | DeferredLedger:
    """The ledger at `path`, or a stand-in that opens it later when the disk refuses now."""
    try:
        return Ledger(path)
    except LedgerBusy:
        raise
    except FluorosimError as e:
        if not disk_full(path):
            raise  # a corrupt or newer ledger is no reason to run without records
        log.error("%s; starting without it, events are kept in memory until it opens", e)
        return DeferredLedger(path, str(e))


def pending_carry_over(path: Path) -> dict | None:
    """What `Ledger(path)` will carry over when it opens (the timer and alarms of the last session
    a crash left open, see Ledger.carry_over), read without writing; None when there is none or
    the file cannot be read, which the log says."""
    if not path.is_file() or path.stat().st_size == 0:   # no ledger yet (a first open on a full disk leaves 0 bytes)
        return None
    try:
        conn = open_readonly(path)
    except FluorosimError as e:
        log.error("%s; the fluoroscopy timer starts from zero, not from the session a crash ended", e)
        return None
    try:
        last = conn.execute("SELECT max(id) FROM sessions WHERE ended_wall IS NULL").fetchone()[0]
        return None if last is None else carry_from(conn, int(last))
    except sqlite3.Error as e:
        log.error("%s: cannot read the session a crash ended (%s); the fluoroscopy timer starts from zero", path, e)
        return None
    finally:
        conn.close()


def disk_full(path: Path) -> bool:
    try:
        return shutil.disk_usage(path.parent).free < FULL_DISK_BYTES
    except OSError:
        return False
