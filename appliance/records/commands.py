"""`fluorosim logs verify` and `fluorosim logs export`, and the ledger benchmark."""

from __future__ import annotations

import argparse
import json
import sqlite3
import sys
from pathlib import Path

from ..command_options import add_command, appliance_profile, date_range_options, ledger_options
from ..errors import FluorosimError
from . import export as export_module
from . import integrity
from .ledger import open_readonly


def ledger_path(args: argparse.Namespace) -> Path:
    """--ledger PATH, else <data_dir>/ledger.sqlite of the appliance profile."""
    if args.ledger:
        return Path(args.ledger)
    return appliance_profile(args, instead="--ledger PATH")[2] / "ledger.sqlite"


def run_verify(args: argparse.Namespace) -> int:
    from . import rdsr_anchor

    path = ledger_path(args)
    anchors = [(Path(f), rdsr_anchor.read_file(Path(f))[1]) for f in args.rdsr or []]
    conn = open_readonly(path)
    try:
        report = integrity.check(conn, integrity.reading_seal())
        # Each dose report's anchor is a copy of a ledger entry kept outside the ledger: a removed
        # tail or a rewritten ledger that passes its own chain shows against it.
        against = [(f, rdsr_anchor.check(conn, anchor)) for f, anchor in anchors]
    finally:
        conn.close()
    intact = report.ok and all(r.ok for _, r in against)
    if report.ok:
        print(f"{path}: {report.message}")
    else:
        where = f"first broken link at event {report.first_bad_id}: " if report.first_bad_id is not None else ""
        print(f"{path}: NOT INTACT: {where}{report.message}", file=sys.stderr)
    for f, r in against:
        if r.ok:
            print(f"{f}: {r.message}")
        else:
            print(f"{f}: NOT INTACT against this dose report: {r.message}", file=sys.stderr)
    return 0 if intact else 1


def run_export(args: argparse.Namespace) -> int:
    since = export_module.parse_when(args.since) if args.since else None
    until = export_module.parse_when(args.until, end=True) if args.until else None
    if since is not None and until is not None and until <= since:
        raise FluorosimError(f"--until {args.until} is not after --since {args.since}")
    path = ledger_path(args)
    conn = open_readonly(path)
    try:
        report = integrity.check(conn, integrity.reading_seal())
        if not report.ok and not args.allow_broken:
            raise FluorosimError(f"{path}: NOT INTACT ({report.message}); nothing exported. Give --allow-broken to "
                                 "export it anyway, with every file stamped as from a broken ledger")
        stamp = None if report.ok else f"LEDGER NOT INTACT: {report.message}"
        written, notes = export_module.export(conn, since, until, args.format, Path(args.out), stamp=stamp)
    finally:
        conn.close()
    if stamp:
        print(f"warning: {path}: {stamp}; every file written says so", file=sys.stderr)
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    for p in written:
        print(p)
    if not written:
        print("no sessions in that period; nothing written", file=sys.stderr)
    return 0


def run_list(args: argparse.Namespace) -> int:
    since = export_module.parse_when(args.since) if args.since else None
    until = export_module.parse_when(args.until, end=True) if args.until else None
    path = ledger_path(args)
    conn = open_readonly(path)
    try:
        sessions = export_module.sessions_between(conn, since, until)
        trainees = trainees_of(conn)
        report = integrity.check(conn, integrity.reading_seal())
    finally:
        conn.close()
    if not report.ok:
        print(f"warning: {path}: NOT INTACT: {report.message}; these figures cannot be trusted "
              "(see `fluorosim logs verify`)", file=sys.stderr)
    print(f"{'id':>6}  {'started (UTC)':<24} {'operator':<16} {'trainee':<20} {'fluoro min':>10} {'kerma mGy':>10} "
          f"{'DAP Gy cm2':>11} {'runs':>5} {'alarms':>6}  end")
    for s in sessions:
        print(f"{s['id']:>6}  {export_module.iso(s['started_wall']):<24} {s['operator'][:16]:<16} "
              f"{trainees.get(s['id'], '-')[:20]:<20} "
              f"{s['fluoro_time_s'] / 60:>10.1f} {s['air_kerma_mgy']:>10.2f} {s['dap_gy_cm2']:>11.3f} "
              f"{s['runs']:>5} {s['alarms']:>6}  {s['end_reason'] or 'open'}")
    return 0


def trainees_of(conn: sqlite3.Connection) -> dict[int, str]:
    """Session id -> the trainee's name entered in it (the last, if changed; recorded by
    teaching through the console as a chained `trainee` event)."""
    out: dict[int, str] = {}
    for sid, detail in conn.execute("SELECT session_id, detail FROM events WHERE kind = 'trainee' ORDER BY id"):
        try:
            name = json.loads(detail).get("name")
        except (ValueError, AttributeError):
            continue
        if isinstance(name, str) and name.strip():
            out[sid] = name.strip()
    return out


def register(commands: argparse._SubParsersAction[argparse.ArgumentParser],
             benches: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from ..cli import command_group
    from .bench import register_bench
    from .dicom_commands import register as register_dicom
    from .seal_commands import register_seal

    logs = command_group(commands, "logs", "read, verify and export the dose and session ledger")
    ls = add_command(logs, "list", run_list, "list sessions with their fluoroscopy time and dose",
                     "One line per session that started in [--since, --until]: the operator, the trainee entered at "
                     "its start ('-' if none), fluoroscopy time (minutes), reference air kerma (mGy), dose-area product "
                     "(Gy cm2), runs, alarms.", ledger_options)
    date_range_options(ls)
    v = add_command(logs, "verify", run_verify, "check the ledger's hash chain",
                    "Walk the ledger's hash chain and the sessions' totals, and check the ledger against the anchor "
                    "each given dose report (RDSR) carries: the entry that ended its session, which the ledger must "
                    "still hold unchanged. Exit 0 when intact; 1 with the first broken link when an event was changed "
                    "or removed.", ledger_options)
    v.add_argument("--rdsr", nargs="+", metavar="FILE",
                   help="dose reports (as sent to the PACS or exported) whose ledger anchors to check")
    e = add_command(logs, "export", run_export, "export sessions and events as CSV, JSON or DICOM dose reports",
                    "Export the sessions that started in [--since, --until] (dates as YYYY-MM-DD, local time; a date "
                    "as --until includes that whole day) as CSV (sessions.csv, events.csv), JSON (ledger.json) or one "
                    "DICOM X-Ray Radiation Dose SR per ended session. Never overwrites: an --out folder that already "
                    "holds those files is refused.", ledger_options)
    e.add_argument("--since", metavar="DATE", help="first day (or date-time) to include; default: the beginning")
    e.add_argument("--until", metavar="DATE", help="last day to include (a date-time is exclusive); default: no limit")
    e.add_argument("--format", choices=export_module.FORMATS, required=True)
    e.add_argument("--out", required=True, metavar="DIR", help="folder to write into (created if missing)")
    e.add_argument("--allow-broken", action="store_true",
                   help="export a ledger that fails verification anyway; every file written is stamped as such")
    register_bench(benches)
    register_dicom(commands)
    register_seal(commands)
