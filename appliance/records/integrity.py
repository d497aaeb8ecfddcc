"""One answer to "can this ledger be trusted?": hash chain, sessions rows, MACs and anchor.

`logs verify` prints it, `logs export` refuses a ledger it finds broken (unless told
`--allow-broken`, which stamps every file written), and `logs list` warns above its table.
Without access to the key (not root, no seal helper) the MACs cannot be checked, but the
world-readable anchor still shows a removed tail or a replaced ledger.
"""

from __future__ import annotations

import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path

from ..errors import FluorosimError
from . import seal as seal_module
from .ledger import verify

#: Where the seal helper listens on a provisioned appliance (systemd/fluorosim-seal.socket).
DEFAULT_SOCKET = Path("/run/fluorosim-seal.sock")


@dataclass(frozen=True)
class Integrity:
    ok: bool
    message: str
    first_bad_id: int | None = None
    authenticated: bool = False


def reading_seal() -> seal_module.Seal | None:
    """The seal an admin's command can use: the environment's, else the provisioned helper's
    socket where it exists, else None (hash chain and anchor only)."""
    found = seal_module.seal_from_environment()
    if found is None and DEFAULT_SOCKET.exists():
        found = seal_module.HelperSeal(DEFAULT_SOCKET)
    return found


def anchor_path() -> Path:
    return Path(os.environ.get(seal_module.ANCHOR_ENV) or seal_module.DEFAULT_ANCHOR)


def check(conn: sqlite3.Connection, seal: seal_module.Seal | None = None, anchor: Path | None = None) -> Integrity:
    chain = verify(conn)
    if not chain.ok:
        return Integrity(False, chain.message, chain.first_bad_id)
    if seal is not None:
        try:
            macs = seal.verify(conn)
        except FluorosimError as e:
            note = f"MACs not checked ({e})"
        else:
            if not macs.ok:
                return Integrity(False, macs.message, macs.first_bad_id)
            return Integrity(True, f"{chain.message}; {macs.message}", authenticated=True)
    else:
        note = "MACs not checked (no access to the key: run as root or where the seal helper listens)"
    doc = seal_module.read_anchor(anchor or anchor_path())
    problem = seal_module.anchor_problem(conn, doc) if doc is not None else None
    if problem is not None:
        return Integrity(False, problem.message, problem.first_bad_id)
    return Integrity(True, f"{chain.message}; {note}" + (f"; anchored at event {doc['count']}" if doc else ""))
