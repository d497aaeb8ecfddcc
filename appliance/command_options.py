"""What the `fluorosim` subcommands share when they set up their arguments: one call makes a
subcommand with its help and the function it runs, and the options several commands take
(the appliance profile or the ledger file, a range of dates) are spelled once here.

`cli.py` builds the parser from each area's `register()`; the areas build their commands with these.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .config import ApplianceProfile

#: The appliance profile a command reads when none is given (relative to the working directory).
DEFAULT_CONFIG = "configs/appliance.yaml"

Options = Callable[[argparse.ArgumentParser], None]


def add_command(group: argparse._SubParsersAction, name: str, run: Callable[[argparse.Namespace], int],
                help: str, description: str | None = None, options: Options | None = None) -> argparse.ArgumentParser:
    """Subcommand `name` of `group` running `run(args)`: `help` is its line in the group's list,
    `description` the text of its own --help (default: the same line), `options` the options it
    shares with the others of its group. Returns the parser, for the options of its own."""
    p = group.add_parser(name, help=help, description=description or help)
    if options is not None:
        options(p)
    p.set_defaults(run=run)
    return p


def positive_number(text: str) -> float:
    """An argparse type: a finite number above 0 (a duration, say)."""
    return _number(text, above_zero=True)


def non_negative_number(text: str) -> float:
    """An argparse type: a finite number of 0 or more (a time along a trajectory, say)."""
    return _number(text, above_zero=False)


def _number(text: str, above_zero: bool) -> float:
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not math.isfinite(x) or x < 0 or (above_zero and x == 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a finite number {'above 0' if above_zero else 'of 0 or more'}")
    return x


def config_option(what: str, default: str = DEFAULT_CONFIG) -> Options:
    """The --config option of commands that read one section of the appliance profile, `what`
    saying which (e.g. "the dicom: section")."""

    def add(p: argparse.ArgumentParser) -> None:
        p.add_argument("--config", default=default, metavar="PATH", help=f"appliance profile with {what} (default {default})")

    return add


def appliance_profile(args: argparse.Namespace, instead: str = "") -> tuple[Path, ApplianceProfile, Path]:
    """(path, profile, data_dir) of the --config the command was given; `instead` names the
    option that could have been given in its place (e.g. "--ledger PATH")."""
    from .config import ApplianceProfile, load_profile, resolve
    from .errors import FluorosimError

    config = Path(args.config)
    if not config.is_file():
        alternative = f" or {instead}" if instead else ""
        raise FluorosimError(f"{config}: no appliance profile there; give --config PATH{alternative}")
    appliance = load_profile(config, ApplianceProfile)
    return config, appliance, resolve(config, appliance.data_dir)


def ledger_options(p: argparse.ArgumentParser) -> None:
    """Where the ledger is: the appliance profile whose data_dir holds it, or the file itself."""
    p.add_argument("--config", default=DEFAULT_CONFIG, metavar="PATH",
                   help=f"appliance profile whose data_dir holds ledger.sqlite (default {DEFAULT_CONFIG})")
    p.add_argument("--ledger", metavar="PATH", help="the ledger file itself, instead of --config")


def date_range_options(p: argparse.ArgumentParser) -> None:
    """--since and --until: the sessions that started in [since, until) (dates or date-times, local time)."""
    p.add_argument("--since", metavar="DATE", help="first day (or date-time) to include")
    p.add_argument("--until", metavar="DATE", help="last day (or date-time, exclusive) to include")
