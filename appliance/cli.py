"""The `fluorosim` command.

Each area of the appliance adds its subcommands through a `register(commands, benches)`
function in its `commands.py`; this module only builds the parser, runs the chosen
command and turns a person's mistake into one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import NoReturn

from . import __version__
from .config.yamlfile import ProfileProblems
from .errors import FluorosimError

#: Modules whose `register(commands, benches)` adds subcommands, in the order `--help` lists them.
COMMAND_MODULES = (
    "appliance.config.commands",
    "appliance.display.commands",
    "appliance.xray.commands",
    "appliance.tracking.commands",
    "appliance.calibration.commands",
    "appliance.records.commands",
    "appliance.patient.commands",
    "appliance.patient.case_commands",
    "appliance.daemon.commands",
    "appliance.teaching.commands",
)


def command_group(commands, name: str, help: str) -> argparse._SubParsersAction:
    """The subcommands of group `name` (e.g. `calibrate`), created on first use.

    Several areas add commands to one group (`calibrate webcam` from tracking, `calibrate
    xray` from X-ray calibration), so the group is made once and shared. The groups are kept
    on the parser they belong to: a table keyed by id() would hand a later parser, built at
    a recycled address, the groups of one already gone.
    """
    groups = commands.__dict__.setdefault("_fluorosim_groups", {})
    if name not in groups:
        parser = commands.add_parser(name, help=help, description=help)
        groups[name] = parser.add_subparsers(dest=f"{name}_command", metavar="WHAT", required=True)
    return groups[name]


class OneLineParser(argparse.ArgumentParser):
    """An argument mistake is one line, as every other refusal is, and exit status 2.

    argparse prints the whole usage block first; on a console's narrow screen that pushes the
    line that says what is wrong out of view. The line names the command, and where the usage
    is ('--help'). Subcommand parsers are made of the same class (argparse's default).
    """

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="fluorosim",
        description="Fluoroscopy training appliance: a tracked box phantom, a virtual 4D patient, "
                    "real-time X-ray rendering, a clinical console and a dose ledger.",
        epilog="Run 'fluorosim COMMAND --help' for the options of one command.",
    )
    parser.add_argument("--version", action="version", version=f"fluorosim {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    bench = commands.add_parser("bench", help="measure speed and accuracy figures",
                                description="Benchmarks on this machine; each prints medians and writes nothing outside --out.")
    benches = bench.add_subparsers(dest="bench", metavar="BENCHMARK", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(commands, benches)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except ProfileProblems as e:
        for problem in e.problems:
            print(problem, file=sys.stderr)
        return 2
    except FluorosimError as e:
        print(f"fluorosim: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("fluorosim: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
