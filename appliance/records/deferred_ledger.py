"""A ledger that opens when it can: the appliance starts on a full disk and says so.

SQLite cannot open a WAL database on a disk with no free block (its -wal and -shm files need
space), yet refusing to start would leave the trainee with no image and the events of the
session nowhere. `open_ledger` therefore gives the real `Ledger` when it opens, and otherwise
this stand-in, which tries again at each call: until then every call raises the one-line
reason, so the records worker keeps the events in memory and the screen shows its banner,
and the first call after space returns opens the ledger (recovering what a crash left open)
and writes them. Another process holding the ledger still stops the start.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..console.state import ConsoleEvent
from ..errors import FluorosimError
from .ledger import FULL_DISK_BYTES, Ledger, LedgerBusy

log = logging.getLogger(__name__)


class DeferredLedger:
    """Stands in for `Ledger` (start_session, record, end_session, close) until it opens."""

    def __init__(self, path: Path, problem: str):
        self.path = Path(path)
        self.problem: str | None = problem
        self._ledger: Ledger | None = None

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
        return None if self._ledger is None else self._ledger.carry_over()

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


def disk_full(path: Path) -> bool:
    try:
        return shutil.disk_usage(path.parent).free < FULL_DISK_BYTES
    except OSError:
        return False
