"""`fluorosim report session N` and `fluorosim report trainee NAME`: the instructor's reports."""

from __future__ import annotations

import os
from pathlib import Path

from ..command_options import add_command, appliance_profile, config_option, date_range_options, ledger_options
from ..errors import FluorosimError
from ..records.commands import ledger_path
from ..records.export import parse_when
from ..records.ledger import open_readonly


def _out(args, path: Path) -> Path:
    return Path(args.out) if args.out else path.parent / "reports"


def run_session(args) -> int:
    from .report import write_session_report

    path = ledger_path(args)
    conn = open_readonly(path)
    try:
        index = write_session_report(conn, args.session, _out(args, path), images_dir=path.parent / "images")
    finally:
        conn.close()
    print(os.path.normpath(index))
    return 0


def run_trainee(args) -> int:
    from .report import write_trainee_report

    since = parse_when(args.since) if args.since else None
    until = parse_when(args.until, end=True) if args.until else None
    if since is not None and until is not None and until <= since:
        raise FluorosimError(f"--until {args.until} is not after --since {args.since}")
    path = ledger_path(args)
    conn = open_readonly(path)
    try:
        index = write_trainee_report(conn, args.name, _out(args, path), since, until)
    finally:
        conn.close()
    print(os.path.normpath(index))
    return 0


def run_lrs_send(args) -> int:
    from ..records.outbox import Outbox
    from .xapi import KIND, XapiSender, queue_ended_sessions

    config, appliance, data_dir = appliance_profile(args)
    lrs = appliance.teaching.lrs
    if lrs is None:
        raise FluorosimError(f"{config}: no teaching.lrs section; add the LRS's endpoint, username, password_file "
                             "and account_home_page to send results")
    path = data_dir / "ledger.sqlite"
    conn = open_readonly(path)
    try:
        # The running appliance's send queue, in the ledger's file: a statement it sent is not sent again.
        with Outbox(path, KIND) as outbox:
            sessions = queue_ended_sessions(conn, outbox, lrs)
            report = XapiSender(outbox, lrs, config).run_round(ignore_backoff=True)
            waiting = len(outbox.pending())
    finally:
        conn.close()
    if report.errors:
        raise FluorosimError(report.errors[0])
    print(f"{sessions} session(s) queued, {sum(report.sent.values())} statement(s) sent to {lrs.endpoint}; "
          f"{waiting} waiting")
    return 0


def run_lrs_queue(args) -> int:
    from ..records.dicom_commands import print_queue
    from .xapi import KIND

    return print_queue(appliance_profile(args)[2] / "ledger.sqlite", KIND)


def register(commands, benches) -> None:
    from ..cli import command_group

    report = command_group(commands, "report", "instructor reports: one session, or one trainee across sessions")
    s = add_command(report, "session", run_session, "HTML report of one session with plots, verdicts and CSV/JSON figures",
                    "Metrics of session N (exposures, blank exposures, fluoroscopy time, K_a,r, DAP, collimation, zoom, "
                    "pulsed share, last-image-hold, tasks met) against the exercise's references, a dose plot and the "
                    "saved images with their verdicts; written to --out (default: reports/ beside the ledger) as "
                    "session-NNNNNN/index.html and CSV/JSON.", ledger_options)
    s.add_argument("session", type=int, metavar="N", help="session id (`fluorosim logs list` shows them)")
    s.add_argument("--out", metavar="DIR", help="folder to write into (default: reports/ beside the ledger)")
    t = add_command(report, "trainee", run_trainee, "one trainee's sessions and their trends",
                    "One row per session of trainee NAME (the name entered at the session's start) that started in "
                    "[--since, --until], with trend plots; written to --out as trainee-NAME/index.html, sessions.csv "
                    "and report.json.", ledger_options)
    t.add_argument("name", metavar="NAME", help="the trainee's name as entered (case does not matter)")
    date_range_options(t)
    t.add_argument("--out", metavar="DIR", help="folder to write into (default: reports/ beside the ledger)")
    lrs = command_group(commands, "lrs", "send trainees' results to the Learning Record Store (xAPI)")
    add_command(lrs, "send", run_lrs_send, "queue every ended session's xAPI statements and send what is queued",
                "Queues the xAPI statements of each ended session not queued before (in the ledger's send queue, "
                "which the running appliance sends from too) and sends what is waiting to teaching.lrs now, ignoring "
                "the retry wait. A refusal or an unreachable LRS is one line, exit 2, and nothing is lost: the "
                "statements stay queued for the next run; none is ever stored twice.",
                config_option("the teaching.lrs section"))
    add_command(lrs, "queue", run_lrs_queue, "the statements not yet taken by the LRS, and why",
                "One line per statement in the send queue that the LRS has not confirmed: its session, tries, when it "
                "is tried next and the last error.", config_option("the teaching.lrs section (its data_dir holds the ledger)"))
