"""`fluorosim validate` and `fluorosim profile edit`."""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from ..atomic_file import write_atomic
from ..errors import FluorosimError
from .loading import KIND_OF_FOLDER, KINDS, kind_of, validate_located, validate_paths
from .yamlfile import ProfileProblems, load


def default_config_dir() -> Path:
    """configs/ in the working directory, else the one shipped beside the package."""
    here = Path("configs")
    if here.is_dir():
        return here
    return Path(__file__).resolve().parents[2] / "configs"


def run_validate(args: argparse.Namespace) -> int:
    paths = [Path(p) for p in args.paths] or [default_config_dir()]
    for p in paths:
        if not p.exists():
            raise FluorosimError(f"{p}: no such file or folder")
    warnings: list = []
    problems = validate_paths(paths, warnings)
    for warning in warnings:
        print(f"warning: {warning}", file=sys.stderr)
    for problem in problems:
        print(problem, file=sys.stderr)
    if problems:
        print(f"{len(problems)} problem(s) found", file=sys.stderr)
        return 2
    print("all profiles valid: " + ", ".join(str(p) for p in paths))
    return 0


def _editor() -> list[str]:
    # An editor the person named and that is missing is their mistake to hear about, not a
    # reason to drop them into another editor they did not ask for.
    for variable in ("VISUAL", "EDITOR"):
        named = os.environ.get(variable, "").strip()
        if named:
            try:
                argv = shlex.split(named)
            except ValueError:
                argv = []
            if not argv or not shutil.which(argv[0]):
                raise FluorosimError(f"{variable}={named}: no such program; install it or set {variable} to an editor "
                                     "that exists (for example EDITOR=nano)")
            return argv
    # The fallbacks are terminal editors: without a terminal they wait for keys that never come.
    if not sys.stdin.isatty():
        raise FluorosimError("EDITOR is not set and standard input is not a terminal, so no text editor can run "
                             "here; run `fluorosim profile edit` in a terminal, or set EDITOR to a program that "
                             "edits the file it is given")
    for candidate in ("editor", "nano", "vi"):
        if shutil.which(candidate):
            print(f"EDITOR is not set: editing with {candidate}", file=sys.stderr)
            return [candidate]
    raise FluorosimError("no text editor found; set EDITOR (for example EDITOR=nano)")


def _kind_for(path: Path) -> str:
    if path.resolve().parent.name in KIND_OF_FOLDER:
        return KIND_OF_FOLDER[path.resolve().parent.name]
    try:
        kind = kind_of(load(path))
    except ProfileProblems:
        kind = None
    if kind is None:
        raise FluorosimError(f"{path}: cannot tell what kind of profile this is; edit profiles under configs/<kind>s/")
    return kind


def run_edit(args: argparse.Namespace) -> int:
    path = Path(args.path)
    if not path.is_file():
        raise FluorosimError(f"{path}: no such profile")
    kind = _kind_for(path)
    original = path.read_bytes()
    # The copy sits beside the original so paths it names resolve the same way.
    fd, copy_name = tempfile.mkstemp(prefix=f".{path.stem}.edit-", suffix=path.suffix, dir=path.parent)
    copy = Path(copy_name)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(original)
        while True:
            result = subprocess.run([*_editor(), str(copy)])
            if result.returncode != 0:
                print(f"editor exited with status {result.returncode}; {path} left unchanged", file=sys.stderr)
                return 1
            edited = copy.read_bytes()
            if edited == original:
                print(f"no changes; {path} left unchanged")
                return 0
            try:
                located = load(copy)
                _, problems = validate_located(located, KINDS[kind])
                if not problems:
                    problems = [p for p in validate_paths([copy])]
            except ProfileProblems as e:
                problems = e.problems
            if not problems:
                write_atomic(path, edited, backup=True)
                print(f"{path}: saved (previous version kept as {path.name}.bak)")
                return 0
            for problem in problems:
                print(str(problem).replace(copy.name, path.name), file=sys.stderr)
            answer = _ask("The profile is not valid. [e]dit again or [a]bandon? ")
            if answer != "e":
                print(f"abandoned; {path} left unchanged", file=sys.stderr)
                return 2
    finally:
        copy.unlink(missing_ok=True)


def _ask(prompt: str) -> str:
    try:
        print(prompt, end="", file=sys.stderr, flush=True)
        return (sys.stdin.readline() or "a").strip().lower()[:1]
    except (OSError, EOFError):
        return "a"


def register(commands: argparse._SubParsersAction[argparse.ArgumentParser],
             benches: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = commands.add_parser("validate", help="check profiles and everything they refer to",
                            description="Check profiles (default: the whole configs/ tree) and every file they name. "
                                        "Prints one line per problem as FILE:LINE: FIELD: MESSAGE; exit 0 when valid, 2 otherwise.")
    p.add_argument("paths", nargs="*", metavar="PATH", help="profile files or folders (default: configs/)")
    p.set_defaults(run=run_validate)

    profile = commands.add_parser("profile", help="edit a profile safely",
                                  description="Work on profiles the way a service technician does.")
    actions = profile.add_subparsers(dest="action", metavar="ACTION", required=True)
    e = actions.add_parser("edit", help="edit a profile in $EDITOR, validate it, save it atomically",
                           description="Open a copy of PATH in $EDITOR. On save the copy is validated; an invalid one "
                                       "can be edited again or abandoned; a valid one replaces PATH atomically and the "
                                       "previous version is kept as PATH.bak.")
    e.add_argument("path", metavar="PATH")
    e.set_defaults(run=run_edit)
