"""`fluorosim report session N` and `fluorosim report trainee NAME`: the instructor's reports."""

from __future__ import annotations

import os
from pathlib import Path

from ..command_options import add_command, config_option, date_range_options, ledger_options
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
    from ..config import ApplianceProfile, load_profile, resolve
    from .xapi import XapiQueue, queue_ended_sessions, read_password, send_pending

    config = Path(args.config)
    if not config.is_file():
        raise FluorosimError(f"{config}: no appliance profile there; give --config PATH")
    appliance = load_profile(config, ApplianceProfile)
    lrs = appliance.teaching.lrs
    if lrs is None:
        raise FluorosimError(f"{config}: no teaching.lrs section; add the LRS's endpoint, username, password_file "
                             "and account_home_page to send results")
    data_dir = resolve(config, appliance.data_dir)
    conn = open_readonly(data_dir / "ledger.sqlite")
    queue = XapiQueue(data_dir / "xapi-outbox.sqlite")
    try:
        sessions = queue_ended_sessions(conn, queue, lrs)
        sent = send_pending(queue, lrs, read_password(resolve(config, lrs.password_file)))
        print(f"{sessions} session(s) queued, {sent} statement(s) sent to {lrs.endpoint}; {queue.count_pending()} waiting")
    finally:
        queue.close()
        conn.close()
    return 0


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
                "Queues the xAPI statements of each ended session not queued before (in xapi-outbox.sqlite in "
                "data_dir) and sends what is waiting to teaching.lrs. A refusal or an unreachable LRS is one line, "
                "exit 2, and nothing is lost: the statements stay queued for the next run; none is ever stored twice.",
                config_option("the teaching.lrs section"))
