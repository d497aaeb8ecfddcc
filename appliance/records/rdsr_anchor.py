"""The ledger's anchor in each dose report, and the auditor's check of a report against the ledger.

Each RDSR carries the ledger entry that ends its session: the event's count (its id, the
number of entries the ledger then held), its SHA-256 chain hash and, on a sealed ledger, its
MAC. At the session's end that entry is the ledger's newest, the one the seal's anchor then
names (records.seal). A report goes to the PACS and the dose registry, out of reach of
whoever can write the ledger file, so it is an anchor kept outside it: deleting the session
or the tail of its events, or rewriting any entry before it and recomputing the chain,
leaves a ledger that no longer holds that entry with that hash, and `fluorosim logs verify
--rdsr FILE` says so. The anchor is the session's own last entry rather than the ledger's
newest at the time the report is written, so a report rebuilt later (an export, a resend)
is the same object as the one first sent, under the same SOP Instance UID.

Where it sits: a private block (PS3.5 section 7.8) of the SR document's header, group 0009,
private creator "FLUOROSIM LEDGER ANCHOR":

    (0009,xx10) UL  ledger entry count (the session's last event id)
    (0009,xx11) LO  that entry's SHA-256 chain hash (64 hex digits)
    (0009,xx12) LO  its HMAC-SHA256 under the seal's key (64 hex digits; absent when unsealed)

Not in the content tree: TID 10001 has no row for it, and a content item outside the
template would make the report non-conformant to importers that check templates; a
private block is the standard's own place for a vendor's data, which readers that do not
know it skip (dciodvfy, dsrdump and dcentvfy stay clean).
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pydicom
from pydicom.datadict import add_private_dict_entries
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError

from ..errors import FluorosimError
from .seal import MacReport, anchor_problem

GROUP = 0x0009
CREATOR = "FLUOROSIM LEDGER ANCHOR"
COUNT, HASH, MAC = 0x10, 0x11, 0x12

# A receiver may store the report in Implicit VR (pynetdicom's storage SCP does, as received),
# where a private element carries no VR: the private dictionary gives readers it back.
add_private_dict_entries(CREATOR, {
    (GROUP << 16) | 0x1000 | COUNT: ("UL", "1", "Ledger Entry Count", "LedgerEntryCount"),
    (GROUP << 16) | 0x1000 | HASH: ("LO", "1", "Ledger Entry Hash", "LedgerEntryHash"),
    (GROUP << 16) | 0x1000 | MAC: ("LO", "1", "Ledger Entry MAC", "LedgerEntryMAC"),
})


def stamp(ds: Dataset, events: list[dict]) -> None:
    """Write the anchor of the session whose ledger rows are `events` (in order) into `ds`."""
    if not events:
        return
    last = events[-1]
    block = ds.private_block(GROUP, CREATOR, create=True)
    block.add_new(COUNT, "UL", int(last["id"]))
    block.add_new(HASH, "LO", str(last["hash"]))
    if last.get("mac"):
        block.add_new(MAC, "LO", str(last["mac"]))


def read(ds: Dataset) -> dict | None:
    """The anchor {"count", "hash", "mac"?} a report carries, None if it carries none."""
    try:
        block = ds.private_block(GROUP, CREATOR)
    except KeyError:
        return None
    try:
        anchor: dict = {"count": int(block[COUNT].value), "hash": str(block[HASH].value)}
    except KeyError:
        return None
    if MAC in block:
        anchor["mac"] = str(block[MAC].value)
    return anchor


def read_file(path: Path) -> tuple[Dataset, dict]:
    """A dose report file and its anchor; FluorosimError (one line) if it is neither."""
    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except OSError as e:
        raise FluorosimError(f"{path}: cannot read the dose report ({e.strerror or e})") from None
    except InvalidDicomError:
        raise FluorosimError(f"{path}: not a DICOM file; give the dose report (RDSR) as sent or exported") from None
    anchor = read(ds)
    if anchor is None:
        raise FluorosimError(f"{path}: carries no fluorosim ledger anchor (not a fluorosim dose report, or one made "
                             "before reports carried it); nothing to check it against")
    return ds, anchor


def check(conn: sqlite3.Connection, anchor: dict) -> MacReport:
    """Whether the ledger still holds the entry a report's anchor names, unchanged."""
    problem = anchor_problem(conn, anchor)
    if problem is not None:
        return problem
    return MacReport(True, f"the ledger holds event {anchor['count']} as the report recorded it")
