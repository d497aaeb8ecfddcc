"""`fluorosim dicom identity|echo|send|queue`: the appliance on the hospital's DICOM network."""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

from ..command_options import add_command, appliance_profile, config_option
from ..config import ApplianceProfile
from ..errors import FluorosimError
from . import dicom, dicom_network, rdsr
from .dicom_sender import KIND, DicomSender, queue_object
from .export import events_of
from .identity import device_uid, identity_path
from .ledger import SESSION_COLUMNS, open_readonly
from .outbox import Outbox, pending_in


def _destinations(config: Path, appliance: ApplianceProfile) -> None:
    if not appliance.dicom.destinations:
        raise FluorosimError(f"{config}: no destinations under dicom: in the appliance profile; add the PACS and the "
                             "dose registry (name, ae_title, host, port, objects)")


def run_identity(args: argparse.Namespace) -> int:
    config, appliance, data_dir = appliance_profile(args)
    path = identity_path(config, data_dir, appliance.dicom)
    print(f"{path}: Device Observer UID {device_uid(path)}")
    return 0


def run_echo(args: argparse.Namespace) -> int:
    config, appliance, _ = appliance_profile(args)
    _destinations(config, appliance)
    failed = 0
    for dest in appliance.dicom.destinations:
        try:
            ms = dicom_network.echo(appliance.dicom, dest, config.parent)
        except dicom_network.DestinationError as e:
            print(f"fluorosim: {e}", file=sys.stderr)
            failed += 1
            continue
        print(f"destination {dest.label()}: answered C-ECHO in {ms:.0f} ms")
    return 1 if failed else 0


def _queue_session(outbox: Outbox, appliance: ApplianceProfile, data_dir: Path, session_id: int) -> int:
    """Queue a session's dose report and saved images again (new destinations get them; what a
    destination already confirmed is not sent to it twice). Returns the objects found."""
    conn = open_readonly(outbox.path)
    try:
        row = conn.execute(f"SELECT {', '.join(SESSION_COLUMNS)} FROM sessions WHERE id = ?", (session_id,)).fetchone()
        if row is None:
            raise FluorosimError(f"session {session_id}: not in the ledger {outbox.path}; see 'fluorosim logs list'")
        session, events = dict(row), events_of(conn, session_id)
    finally:
        conn.close()
    found = 0
    for path in sorted((data_dir / "images").glob(f"image-{session_id:06d}-*.dcm")):
        try:
            data = path.read_bytes()
        except OSError as e:
            raise FluorosimError(f"{path}: cannot read the saved image ({e.strerror or e})") from None
        queue_object(outbox, appliance.dicom, data, "image", f"image {path.stem.rsplit('-', 1)[1].lstrip('0')} of session "
                     f"{session_id}", session_id)
        found += 1
    if session["ended_wall"] is None:
        print(f"note: session {session_id} is still open; its dose report is queued when it ends", file=sys.stderr)
    else:
        report = dicom.encode(rdsr.session_report(session, events))
        queue_object(outbox, appliance.dicom, report, "dose_report", f"dose report of session {session_id}", session_id)
        found += 1
    return found


def run_send(args: argparse.Namespace) -> int:
    config, appliance, data_dir = appliance_profile(args)
    _destinations(config, appliance)
    with Outbox(data_dir / "ledger.sqlite", KIND) as outbox:
        if args.session is not None:
            n = _queue_session(outbox, appliance, data_dir, args.session)
            print(f"session {args.session}: {n} object(s) queued")
        sender = DicomSender(outbox, appliance.dicom, config.parent)
        totals: dict[str, int] = {}
        errors: list[str] = []
        while True:
            report = sender.run_round(ignore_backoff=True)
            for name, n in report.sent.items():
                totals[name] = totals.get(name, 0) + n
            errors += report.errors
            if not report.sent:
                break   # nothing more was sent: all done, or what is left failed this time
        for name, n in totals.items():
            print(f"destination '{name}': {n} object(s) sent")
        for line in dict.fromkeys(errors):
            print(f"fluorosim: {line}", file=sys.stderr)
        left = outbox.pending()
        if left:
            what = "1 delivery" if len(left) == 1 else f"{len(left)} deliveries"
            print(f"{what} still queued, tried again later; see 'fluorosim dicom queue'", file=sys.stderr)
            return 1
        if not totals:
            print("nothing queued; nothing sent")
        return 0


def _when(t: float) -> str:
    return dt.datetime.fromtimestamp(t, tz=dt.UTC).strftime("%Y-%m-%d %H:%M:%SZ")


def run_queue(args: argparse.Namespace) -> int:
    _, _, data_dir = appliance_profile(args)
    return print_queue(data_dir / "ledger.sqlite", KIND)


def print_queue(ledger: Path, kind: str) -> int:
    """What the send queue in `ledger` holds of `kind` and not yet delivered, one line each, with why."""
    if not ledger.is_file():
        print(f"nothing queued (no ledger yet in {ledger.parent})")
        return 0
    conn = open_readonly(ledger)
    try:
        pending = pending_in(conn, kind, time.time())
    finally:
        conn.close()
    if not pending:
        print("nothing queued")
        return 0
    print(f"{'session':>7}  {'object':<40} {'destination':<14} {'tries':>5}  {'next try (UTC)':<21} last error")
    for p in pending:
        state = "sending now" if p.leased else _when(p.next_try_wall)
        print(f"{p.session_id if p.session_id is not None else '-':>7}  {p.label[:40]:<40} {p.destination[:14]:<14} "
              f"{p.attempts:>5}  {state:<21} {p.last_error or ''}")
    return 0


def register(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from ..cli import command_group

    group = command_group(commands, "dicom", "send images and dose reports to the PACS and the dose registry")

    def session_option(p: argparse.ArgumentParser) -> None:
        p.add_argument("--session", type=int, metavar="N", help="queue session N's objects first (see 'fluorosim logs list')")

    commands_of_dicom = (
        ("identity", run_identity, (), "make (once) and show this appliance's Device Observer UID",
         "Generate the appliance's Device Observer UID into dicom.identity_file if it has none yet (provisioning "
         "runs this), and print it. An existing UID is never changed."),
        ("echo", run_echo, (), "C-ECHO every destination",
         "Check the link to every destination of the dicom: section with a C-ECHO. Exit 0 only if all answer; one "
         "line per destination that does not."),
        ("send", run_send, (session_option,), "send what is queued now (or a session's objects)",
         "Send every queued object now, without waiting for the retry delay. With --session N, first queue that "
         "session's saved images and dose report again (a destination that already confirmed an object does not get "
         "it twice). Exit 0 when nothing is left queued."),
        ("queue", run_queue, (), "what is waiting to be sent, and why",
         "One line per object and destination not yet delivered: tries so far, when it is tried next, and the last "
         "error."),
    )
    for name, run, own_options, help, description in commands_of_dicom:
        p = add_command(group, name, run, help, description, config_option("the dicom: section"))
        for option in own_options:
            option(p)
