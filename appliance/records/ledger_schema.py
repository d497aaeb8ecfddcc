"""The ledger's file: its schema as numbered migrations (PRAGMA user_version), and the
connections to it — the one writer's, a writer for tables outside the event chain (the
outbox), and read-only ones safe while the daemon writes.

Durability: WAL journal with synchronous=FULL, so a committed transaction survives a power cut.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from ..errors import FluorosimError

#: Below this much free space an error opening or writing the ledger is the disk being full (bytes).
FULL_DISK_BYTES = 1 << 20
#: Checkpoint the WAL into the ledger every this many pages (4 KiB each), and cut the WAL file
#: back to WAL_LIMIT_BYTES after it. SQLite's default of 1000 pages lets the WAL take 4 MiB beside
#: the ledger: on a nearly full disk (the demo on a 4 MiB tmpfs) the held dose events, written
#: once space returned, filled that space with WAL frames and were lost at shutdown. Small
#: batches of events make few pages, so a checkpoint every 64 costs little.
WAL_CHECKPOINT_PAGES = 64
WAL_LIMIT_BYTES = 1 << 20


def _why(path: Path, e: Exception) -> str:
    """What a failed open or write of the ledger means for a person: a full disk, else the error."""
    import shutil

    try:
        free = shutil.disk_usage(path.parent if path.parent.exists() else Path(".")).free
    except OSError:
        free = None
    if free is not None and free < FULL_DISK_BYTES:
        return f"the disk is full ({free // 1024} KiB free); free space in {path.parent}"
    # SQLITE_NOTADB and SQLITE_CORRUPT (a file cut short, overwritten, or not SQLite at all) are
    # what the file holds, not who may read it; they arrive as DatabaseError, permissions as
    # OperationalError.
    if isinstance(e, sqlite3.DatabaseError) and not isinstance(e, sqlite3.OperationalError):
        return (f"{e}: the file is damaged or is not a ledger; keep it for the record and restore the ledger "
                "from its backup")
    return f"{e}; check the file and its folder's permissions"

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
    # 2 Outbox (DICOM network sending, reused for xAPI): objects to deliver and one delivery row
    # per destination, kept in the ledger's file so a queued object survives kill -9 and power
    # loss together with the session it belongs to. See records.outbox.
    """
    CREATE TABLE outbox_items (
        id INTEGER PRIMARY KEY,
        kind TEXT NOT NULL,
        item_key TEXT NOT NULL,
        session_id INTEGER,
        label TEXT NOT NULL,
        payload BLOB NOT NULL,
        created_wall REAL NOT NULL,
        UNIQUE (kind, item_key)
    );
    CREATE TABLE outbox_deliveries (
        item_id INTEGER NOT NULL REFERENCES outbox_items(id),
        destination TEXT NOT NULL,
        sent_wall REAL,
        attempts INTEGER NOT NULL DEFAULT 0,
        next_try_wall REAL NOT NULL,
        last_try_wall REAL,
        last_error TEXT,
        lease_until REAL,
        lease_owner INTEGER,
        PRIMARY KEY (item_id, destination)
    );
    CREATE INDEX outbox_due ON outbox_deliveries(sent_wall, next_try_wall);
    """,
    # 3 (tamper-evident ledger): each event's HMAC with the seal's key (records/seal.py); NULL
    # in rows written before sealing, which the first sealed row's MAC covers through its hash.
    """
    ALTER TABLE events ADD COLUMN mac TEXT;
    """,
)

EVENT_COLUMNS = ("id", "session_id", "t_wall", "t_monotonic", "kind", "fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2",
                 "d_fluoro_time_s", "d_air_kerma_mgy", "d_dap_gy_cm2", "detail", "prev_hash", "hash", "mac")
SESSION_COLUMNS = ("id", "operator", "case_title", "fluoroscope", "started_wall", "ended_wall", "end_reason",
                   "fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2", "runs", "alarms", "saves")


def migrate(conn: sqlite3.Connection, path: Path) -> None:
    version = conn.execute("PRAGMA user_version").fetchone()[0]
    if version > len(MIGRATIONS):
        raise FluorosimError(f"{path}: ledger schema {version} is newer than this fluorosim knows "
                             f"({len(MIGRATIONS)}); update fluorosim before opening it")
    for number in range(version, len(MIGRATIONS)):
        with conn:
            conn.executescript("BEGIN IMMEDIATE;" + MIGRATIONS[number] + f"; PRAGMA user_version = {number + 1};")


def connect(path: Path, readonly: bool) -> sqlite3.Connection:
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
            conn.execute(f"PRAGMA wal_autocheckpoint = {WAL_CHECKPOINT_PAGES}")
            conn.execute(f"PRAGMA journal_size_limit = {WAL_LIMIT_BYTES}")
        conn.execute("SELECT count(*) FROM sqlite_master").fetchone()
        return conn
    except sqlite3.DatabaseError as e:
        raise FluorosimError(f"{path}: cannot open the ledger ({_why(path, e)})") from None
    except OSError as e:
        raise FluorosimError(f"{path}: cannot create the ledger's folder ({e.strerror or e})") from None


def open_writer(path: str | Path) -> sqlite3.Connection:
    """A writing connection with the schema brought up to date, for tables outside the event
    chain (the outbox) that another process may write beside the one Ledger."""
    path = Path(path)
    conn = connect(path, readonly=False)
    try:
        migrate(conn, path)
    except BaseException:
        conn.close()
        raise
    return conn


def open_readonly(path: str | Path) -> sqlite3.Connection:
    """A read-only connection for `logs verify` and `logs export`, safe while the daemon writes."""
    path = Path(path)
    conn = connect(path, readonly=True)
    version = conn.execute("PRAGMA user_version").fetchone()[0]
    if version == 0:
        tables = conn.execute("SELECT count(*) FROM sqlite_master").fetchone()[0]
        conn.close()
        if tables == 0:
            raise FluorosimError(f"{path}: holds no ledger yet (the appliance was stopped while creating it?); "
                                 "start the appliance once to create it, or give the right --ledger")
        raise FluorosimError(f"{path}: not a fluorosim ledger (no schema)")
    if version > len(MIGRATIONS):
        raise FluorosimError(f"{path}: ledger schema {version} is newer than this fluorosim knows; update fluorosim")
    return conn
