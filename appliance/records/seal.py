"""Authenticating the ledger's chain with a key the service user cannot read.

The ledger's SHA-256 chain shows a changed or removed row, but anyone who can write the
file can also recompute it. Each event therefore also carries

    mac_i = HMAC-SHA256(key, "i|mac_{i-1}|hash_i")

where hash_i is the row's SHA-256 link (which covers every column and the previous hash,
so the first sealed event authenticates all unsealed history before it). Without the key
no edited row gets a valid MAC, and the newest entry's count and hash are kept outside the
file, in the anchor, so deleting the tail (the last events or whole sessions) shows too.

Why a privileged helper rather than a machine secret: anything the service can derive
(machine-id, a file it can read) a person with the service user's shell can derive too. So
the key is a root-only file (0400) read only by `fluorosim seal serve`, a small root service
listening on a Unix socket that only the service's group may use. It answers three requests:

    mac      MAC for event i; refused for i at or below the anchor (history cannot be re-signed)
    advance  read the ledger itself (root may), check every MAC after the anchor, move the anchor
    verify   check the whole chain against key and anchor, for `logs verify` and exports

The anchor (a JSON file written atomically by the helper, root-owned, world-readable) names
the ledger's newest authenticated entry: count (its event id), hash and MAC. `anchor_entry()`
gives count and hash to anyone, so a dose report can carry them (the dicom branch's RDSR).

Where no helper is configured (development, the demo, tests) a `KeySeal` does the same in
process with a key file it may read; with neither, events are hash-chained only and
`logs verify` says so.
"""

from __future__ import annotations

import errno
import hashlib
import hmac
import json
import os
import secrets
import socket
import sqlite3
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from ..atomic_file import write_atomic
from ..errors import FluorosimError

#: Environment of the service naming its seal (set in the unit, not in a profile: the service
#: user must not be able to point itself at a key or anchor of its own making).
SOCKET_ENV, KEY_ENV, ANCHOR_ENV = "FLUOROSIM_SEAL_SOCKET", "FLUOROSIM_SEAL_KEY", "FLUOROSIM_SEAL_ANCHOR"
#: Where provisioning puts them.
DEFAULT_ANCHOR = Path("/var/lib/fluorosim-seal/anchor.json")
KEY_BYTES = 32
#: One request to the helper is a line of JSON; an answer comes within this (s).
HELPER_TIMEOUT_S = 5.0


def mac_of(key: bytes, index: int, prev_mac: str, row_hash: str) -> str:
    return hmac.new(key, f"{index}|{prev_mac}|{row_hash}".encode("ascii"), hashlib.sha256).hexdigest()


def make_key(path: Path) -> None:
    """Write a new random key, readable by its owner only (provisioning runs this as root)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o400)
    with os.fdopen(fd, "wb") as f:
        f.write(secrets.token_bytes(KEY_BYTES))


def load_key(path: Path) -> bytes:
    try:
        info = path.stat()
        key = path.read_bytes()
    except OSError as e:
        raise FluorosimError(f"{path}: cannot read the ledger key ({e.strerror or e}); "
                             "run this as root or through the seal helper") from None
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise FluorosimError(f"{path}: the ledger key is readable by others (mode {stat.S_IMODE(info.st_mode):o}); "
                             "make it 0400 and owned by root")
    if len(key) < 16:
        raise FluorosimError(f"{path}: the ledger key is {len(key)} bytes; it must be at least 16")
    return key


def read_anchor(path: Path) -> dict | None:
    """The anchor {"count", "hash", "mac"}, or None where none was written yet."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        raise FluorosimError(f"{path}: cannot read the ledger's anchor ({e}); restore it from the backup") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("count"), int) or not isinstance(doc.get("hash"), str):
        raise FluorosimError(f"{path}: the ledger's anchor is not a fluorosim anchor; restore it from the backup")
    return doc


def anchor_entry(path: Path | None = None) -> tuple[int, str] | None:
    """(count, hash) of the newest authenticated ledger entry, for a dose report or an export
    to carry outside the ledger; None where the ledger is not sealed."""
    path = path or Path(os.environ.get(ANCHOR_ENV) or DEFAULT_ANCHOR)
    doc = read_anchor(path)
    return None if doc is None else (doc["count"], doc["hash"])


@dataclass(frozen=True)
class MacReport:
    ok: bool
    message: str
    first_bad_id: int | None = None


def check_macs(key: bytes, conn: sqlite3.Connection, anchor: dict | None, after: int = 0,
               prev_mac: str | None = None) -> tuple[MacReport, tuple[int, str, str] | None]:
    """Check every MAC of events with id > `after`, and the ledger against the anchor.

    Returns the report and (id, hash, mac) of the newest event checked. Events before the
    first sealed one are allowed (a ledger from before sealing); a gap after it is not.
    """
    prev = prev_mac if prev_mac is not None else ""
    sealed = prev_mac is not None
    newest = None
    for r in conn.execute("SELECT id, hash, mac FROM events WHERE id > ? ORDER BY id", (after,)):
        if r["mac"] is None:
            if sealed:
                return MacReport(False, f"event {r['id']}: has no MAC after authenticated events (it was inserted "
                                        "or rewritten without the key)", r["id"]), newest
            continue
        if not hmac.compare_digest(mac_of(key, r["id"], prev, r["hash"]), r["mac"]):
            return MacReport(False, f"event {r['id']}: its MAC does not match (the event, or one before it, was "
                                    "changed and its hashes recomputed)", r["id"]), newest
        sealed, prev, newest = True, r["mac"], (r["id"], r["hash"], r["mac"])
    problem = anchor_problem(conn, anchor)
    if problem is not None:
        return problem, newest
    return MacReport(True, "MACs intact" + (f", anchored at event {anchor['count']}" if anchor else "")), newest


def anchor_problem(conn: sqlite3.Connection, anchor: dict | None) -> MacReport | None:
    """Whether the ledger still holds the entry the anchor names, unchanged; needs no key."""
    if anchor is None:
        return None
    row = conn.execute("SELECT id, hash, mac FROM events WHERE id = ?", (anchor["count"],)).fetchone()
    if row is None:
        top = conn.execute("SELECT max(id) FROM events").fetchone()[0] or 0
        return MacReport(False, f"the anchor names event {anchor['count']} but the ledger ends at event {top}: "
                                f"the last {anchor['count'] - top} event(s) were removed")
    if row["hash"] != anchor["hash"] or (anchor.get("mac") and row["mac"] != anchor["mac"]):
        return MacReport(False, f"event {anchor['count']}: differs from the anchor kept outside the ledger "
                                "(the ledger was replaced or rewritten)", anchor["count"])
    return None


class Seal(Protocol):
    def mac(self, index: int, prev_mac: str, row_hash: str) -> str: ...
    def advance(self, conn: sqlite3.Connection) -> None: ...
    def verify(self, conn: sqlite3.Connection) -> MacReport: ...


class KeySeal:
    """The seal in this process: key file and anchor file it may read and write (the helper's
    own implementation, and the one for development and tests)."""

    def __init__(self, key_path: Path, anchor_path: Path):
        self.key = load_key(Path(key_path))
        self.anchor_path = Path(anchor_path)

    def mac(self, index: int, prev_mac: str, row_hash: str) -> str:
        anchor = read_anchor(self.anchor_path)
        if anchor is not None and index <= anchor["count"]:
            raise FluorosimError(f"ledger event {index} is already anchored (at {anchor['count']}); "
                                 "authenticated history cannot be signed again")
        return mac_of(self.key, index, prev_mac, row_hash)

    def advance(self, conn: sqlite3.Connection) -> None:
        """Move the anchor to the newest event, once every MAC after it checks out."""
        anchor = read_anchor(self.anchor_path)
        report, newest = check_macs(self.key, conn, anchor, after=anchor["count"] if anchor else 0,
                                    prev_mac=anchor.get("mac") if anchor else None)
        if not report.ok:
            raise FluorosimError(f"ledger anchor not moved: {report.message}")
        if newest is not None:
            doc = {"count": newest[0], "hash": newest[1], "mac": newest[2]}
            write_atomic(self.anchor_path, (json.dumps(doc) + "\n").encode("ascii"))

    def verify(self, conn: sqlite3.Connection) -> MacReport:
        return check_macs(self.key, conn, read_anchor(self.anchor_path))[0]


class HelperSeal:
    """The seal through `fluorosim seal serve`, the root helper that alone reads the key."""

    def __init__(self, socket_path: Path):
        self.socket_path = Path(socket_path)

    def _ask(self, request: dict) -> dict:
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(HELPER_TIMEOUT_S)
                s.connect(str(self.socket_path))
                s.sendall((json.dumps(request) + "\n").encode("ascii"))
                answer = s.makefile("rb").readline()
        except OSError as e:
            raise FluorosimError(f"{self.socket_path}: the ledger's seal helper does not answer ({e.strerror or e}); "
                                 "check `systemctl status fluorosim-seal.socket`") from None
        try:
            doc = json.loads(answer)
        except ValueError:
            raise FluorosimError(f"{self.socket_path}: the seal helper gave no answer") from None
        if not isinstance(doc, dict):
            raise FluorosimError(f"{self.socket_path}: the seal helper gave no answer")
        if "error" in doc:
            raise FluorosimError(str(doc["error"]))
        return doc

    def mac(self, index: int, prev_mac: str, row_hash: str) -> str:
        return str(self._ask({"op": "mac", "index": index, "prev": prev_mac, "hash": row_hash})["mac"])

    def advance(self, conn: sqlite3.Connection) -> None:
        self._ask({"op": "advance"})

    def verify(self, conn: sqlite3.Connection) -> MacReport:
        doc = self._ask({"op": "verify"})
        return MacReport(bool(doc["ok"]), str(doc["message"]), doc.get("first_bad_id"))


def seal_from_environment() -> Seal | None:
    """The seal the unit configured: the helper's socket, else a key file, else none."""
    if os.environ.get(SOCKET_ENV):
        return HelperSeal(Path(os.environ[SOCKET_ENV]))
    if os.environ.get(KEY_ENV):
        return KeySeal(Path(os.environ[KEY_ENV]), Path(os.environ.get(ANCHOR_ENV) or DEFAULT_ANCHOR))
    return None


def serve(sock: socket.socket, seal: KeySeal, ledger_path: Path, *, once: bool = False) -> None:
    """Answer requests on a listening Unix socket (from systemd's socket activation or our own).

    The ledger the helper reads is the one it was started with, never one a client names.
    """
    while True:
        try:
            conn_sock, _ = sock.accept()
        except OSError as e:
            if e.errno in (errno.EBADF, errno.EINVAL):
                return      # the listening socket was closed: the helper is stopping
            raise
        with conn_sock:
            conn_sock.settimeout(HELPER_TIMEOUT_S)
            try:
                request = json.loads(conn_sock.makefile("rb").readline() or b"{}")
                answer = _answer(request, seal, ledger_path)
            except FluorosimError as e:
                answer = {"error": str(e)}
            except (ValueError, KeyError, TypeError, OSError) as e:
                answer = {"error": f"seal helper: bad request ({e})"}
            try:
                conn_sock.sendall((json.dumps(answer) + "\n").encode("ascii"))
            except OSError:
                pass  # the client went away; nothing was changed for it
        if once:
            return


def _answer(request: dict, seal: KeySeal, ledger_path: Path) -> dict:
    op = request.get("op")
    if op == "mac":
        return {"mac": seal.mac(int(request["index"]), str(request["prev"]), str(request["hash"]))}
    if op in ("advance", "verify"):
        from .ledger import open_readonly

        conn = open_readonly(ledger_path)
        try:
            if op == "advance":
                seal.advance(conn)
                return {"ok": True}
            report = seal.verify(conn)
            return {"ok": report.ok, "message": report.message, "first_bad_id": report.first_bad_id}
        finally:
            conn.close()
    return {"error": f"seal helper: unknown request {op!r}"}
