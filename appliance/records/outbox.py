"""A persistent outbox: objects to deliver to named destinations, kept in the ledger's SQLite file.

One item is one object of a `kind` ("dicom" for images and dose reports; "xapi" for learning
statements) with a key unique within that kind (a SOP Instance UID, a statement id), its
bytes, and one delivery row per destination. Guarantees:

- Durable: `put` commits (WAL, synchronous=FULL) before it returns, so a queued object
  survives kill -9 and power loss; putting the same key again adds nothing.
- Never twice after a success: a delivery marked sent is never handed out again.
- One sender at a time per delivery: `claim` leases what it hands out until `lease_until`
  to its process. A lease whose process is gone (kill -9, power loss: the file is local, so
  a process id means this machine) or that expired is handed out again at once; the
  receiver may then see the object that was in flight a second time, under the same key,
  which a DICOM store files as the same instance.
- Backoff: each failure of a delivery doubles its wait, from `first_delay_s` up to
  `max_delay_s`.

Times are Unix times (s). Another process (the `fluorosim dicom send` command beside the
running appliance) may use the same file: every change is one short transaction.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from ..errors import FluorosimError
from .ledger import open_writer

T = TypeVar("T")


@dataclass(frozen=True)
class Item:
    """One delivery handed out by `claim`: an object for one destination."""

    item_id: int
    key: str
    label: str
    destination: str
    payload: bytes
    attempts: int


@dataclass(frozen=True)
class Pending:
    """One delivery not yet made, for `fluorosim dicom queue`."""

    item_id: int
    key: str
    label: str
    session_id: int | None
    destination: str
    attempts: int
    next_try_wall: float
    last_error: str | None
    leased: bool


@dataclass
class RoundReport:
    """What one round of a sender did."""

    sent: dict[str, int] = field(default_factory=dict)          # destination -> objects confirmed
    errors: list[str] = field(default_factory=list)              # one line each


class FailureStreaks:
    """Rounds in a row each destination failed, for a sender's banner and its one log line.

    After `warn_after` failed rounds in a row a destination counts as failing: one warning
    goes to the log and `problems()` names it (a few stable words, for the banner) until it
    answers again, which is logged once too. `counts` is kept across a profile reload."""

    def __init__(self, what: str, warn_after: int, logger: logging.Logger,
                 counts: dict[str, tuple[int, str]] | None = None):
        self.what, self.warn_after, self.log = what, warn_after, logger
        #: Destination -> (failed rounds in a row, the last error's short reason).
        self.counts: dict[str, tuple[int, str]] = dict(counts or {})

    def failed(self, name: str, message: str, short: str) -> None:
        n = self.counts.get(name, (0, ""))[0] + 1
        self.counts[name] = (n, short)
        if n == self.warn_after:
            self.log.warning("%s destination keeps failing (%d attempts in a row); objects stay queued: %s", self.what, n, message)

    def answered(self, name: str) -> None:
        if self.counts.get(name, (0, ""))[0] >= self.warn_after:
            self.log.info("%s destination '%s' answers again; its queue is being sent", self.what, name)
        self.counts.pop(name, None)

    def problems(self) -> list[str]:
        """A few words per destination that keeps failing; the same while it fails the same way."""
        return [f"{self.what} send to '{name}' failing ({short})" for name, (n, short) in sorted(self.counts.items())
                if n >= self.warn_after]


def _alive(pid: int | None) -> bool:
    if pid is None or pid == os.getpid():
        return pid is not None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True     # someone else's process: alive
    return True


def pending_in(conn: sqlite3.Connection, kind: str, now: float) -> list[Pending]:
    """Every delivery of `kind` not yet made, oldest object first (any connection, read-only too)."""
    rows = conn.execute(
        "SELECT i.id, i.item_key, i.label, i.session_id, d.destination, d.attempts, d.next_try_wall, d.last_error, "
        "d.lease_until, d.lease_owner FROM outbox_deliveries d JOIN outbox_items i ON i.id = d.item_id "
        "WHERE i.kind = ? AND d.sent_wall IS NULL ORDER BY i.id, d.destination", (kind,)).fetchall()
    return [Pending(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8] is not None and r[8] >= now and _alive(r[9]))
            for r in rows]


def backoff_s(attempts: int, first_delay_s: float, max_delay_s: float) -> float:
    """Wait after the `attempts`-th consecutive failure (1-based): first, 2 x first, 4 x first... (s)."""
    return min(max_delay_s, first_delay_s * 2.0 ** min(max(attempts - 1, 0), 60))


class Outbox:
    """The deliveries of one `kind` in the ledger file at `path`."""

    def __init__(self, path: str | Path, kind: str):
        self.path = Path(path)
        self.kind = kind
        self._conn = open_writer(self.path)

    def _write(self, work: Callable[[], T]) -> T:
        try:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                result = work()
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            self._conn.execute("COMMIT")
            return result
        except sqlite3.OperationalError as e:
            raise FluorosimError(f"{self.path}: cannot write the send queue ({e}); free disk space or fix permissions; "
                                 "nothing already queued is lost") from None

    def put(self, key: str, label: str, payload: bytes, destinations: list[str], *, session_id: int | None = None,
            now: float | None = None) -> bool:
        """Queue `payload` under `key` for each destination; True if anything new was queued.
        An object already queued keeps its deliveries (a sent one stays sent); a destination
        it was not yet queued for is added."""
        return self.put_many([(key, label, payload)], destinations, session_id=session_id, now=now) > 0

    def put_many(self, objects: list[tuple[str, str, bytes]], destinations: list[str], *,
                 session_id: int | None = None, now: float | None = None) -> int:
        """Queue several (key, label, payload) objects in one transaction, all or none; returns
        how many objects had anything new queued (as `put`)."""
        now = time.time() if now is None else now

        def one(key: str, label: str, payload: bytes) -> bool:
            cur = self._conn.execute(
                "INSERT OR IGNORE INTO outbox_items (kind, item_key, session_id, label, payload, created_wall) "
                "VALUES (?, ?, ?, ?, ?, ?)", (self.kind, key, session_id, label, sqlite3.Binary(payload), now))
            added = cur.rowcount > 0
            item_id = self._conn.execute("SELECT id FROM outbox_items WHERE kind = ? AND item_key = ?",
                                         (self.kind, key)).fetchone()[0]
            for name in destinations:
                cur = self._conn.execute("INSERT OR IGNORE INTO outbox_deliveries (item_id, destination, next_try_wall) "
                                         "VALUES (?, ?, ?)", (item_id, name, now))
                added = added or cur.rowcount > 0
            return added
        return self._write(lambda: sum(one(*o) for o in objects))

    def has(self, key: str) -> bool:
        """Whether an object `key` was ever queued (sent or not)."""
        return self._conn.execute("SELECT 1 FROM outbox_items WHERE kind = ? AND item_key = ?",
                                  (self.kind, key)).fetchone() is not None

    def claim(self, destination: str, *, now: float | None = None, lease_s: float, limit: int = 16,
              ignore_backoff: bool = False, key: str | None = None) -> list[Item]:
        """Hand out up to `limit` due deliveries to `destination`, oldest first, leased for `lease_s`
        (only the object `key`, if given)."""
        now = time.time() if now is None else now

        def work() -> list[Item]:
            rows = self._conn.execute(
                "SELECT i.id, i.item_key, i.label, d.attempts, d.lease_until, d.lease_owner FROM outbox_deliveries d "
                "JOIN outbox_items i ON i.id = d.item_id WHERE i.kind = ? AND d.destination = ? AND d.sent_wall IS NULL "
                "AND (? OR d.next_try_wall <= ?) AND (? IS NULL OR i.item_key = ?) ORDER BY i.id",
                (self.kind, destination, int(ignore_backoff), now, key, key))
            free = [r for r in rows if r[4] is None or r[4] < now or not _alive(r[5])][:limit]
            self._conn.executemany("UPDATE outbox_deliveries SET lease_until = ?, lease_owner = ? "
                                   "WHERE item_id = ? AND destination = ?",
                                   [(now + lease_s, os.getpid(), r[0], destination) for r in free])
            payloads = {r[0]: bytes(r[1]) for r in self._conn.execute(
                f"SELECT id, payload FROM outbox_items WHERE id IN ({', '.join('?' * len(free))})", [r[0] for r in free])}
            return [Item(r[0], r[1], r[2], destination, payloads[r[0]], r[3]) for r in free]
        return self._write(work)

    def delivered(self, item: Item, *, now: float | None = None) -> None:
        """Record that the destination confirmed `item`; it is never handed out again."""
        now = time.time() if now is None else now
        self._write(lambda: self._conn.execute(
            "UPDATE outbox_deliveries SET sent_wall = ?, last_try_wall = ?, attempts = attempts + 1, last_error = NULL, "
            "lease_until = NULL, lease_owner = NULL WHERE item_id = ? AND destination = ? AND sent_wall IS NULL",
            (now, now, item.item_id, item.destination)))

    def failed(self, item: Item, error: str, *, first_delay_s: float, max_delay_s: float,
               now: float | None = None) -> float:
        """Record a failed attempt; returns when the delivery is due again (Unix time, s)."""
        now = time.time() if now is None else now
        attempts = item.attempts + 1
        due = now + backoff_s(attempts, first_delay_s, max_delay_s)
        self._write(lambda: self._conn.execute(
            "UPDATE outbox_deliveries SET attempts = ?, next_try_wall = ?, last_try_wall = ?, last_error = ?, "
            "lease_until = NULL, lease_owner = NULL WHERE item_id = ? AND destination = ? AND sent_wall IS NULL",
            (attempts, due, now, error, item.item_id, item.destination)))
        return due

    def release(self, item: Item) -> None:
        """Give back a claimed delivery that was not attempted (the sender is stopping)."""
        self._write(lambda: self._conn.execute(
            "UPDATE outbox_deliveries SET lease_until = NULL, lease_owner = NULL "
            "WHERE item_id = ? AND destination = ? AND sent_wall IS NULL",
            (item.item_id, item.destination)))

    def pending(self, *, now: float | None = None) -> list[Pending]:
        """Every delivery not yet made, oldest object first."""
        return pending_in(self._conn, self.kind, time.time() if now is None else now)

    def sent_keys(self, destination: str) -> list[str]:
        """Keys delivered to `destination`, in the order they were confirmed."""
        return [r[0] for r in self._conn.execute(
            "SELECT i.item_key FROM outbox_deliveries d JOIN outbox_items i ON i.id = d.item_id "
            "WHERE i.kind = ? AND d.destination = ? AND d.sent_wall IS NOT NULL ORDER BY d.sent_wall, i.id",
            (self.kind, destination))]

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> Outbox:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
