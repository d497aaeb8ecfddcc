"""`fluorosim ARGS` run inside the test process: the same parser, command and error handling as
the installed command (appliance.cli.main), without a new interpreter importing numpy, OpenCV,
pyopencl and the rest again (about 2 s of CPU a call on this project's two-core machines).

Tests of what only a real process shows (no traceback reaches stderr, the exit status of the
interpreter, signals) keep running `python -m appliance` as a subprocess."""

from __future__ import annotations

import contextlib
import io
import os
import sys
from dataclasses import dataclass
from pathlib import Path

from appliance.cli import main


@dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str


def fluorosim(*args, cwd: Path, stdin: str = "") -> Result:
    """Run the command with `cwd` as the working directory, `stdin` as what a person types (an empty
    stdin, as `subprocess.run(input="")` gives: end of file at once); stdout and stderr captured."""
    out, err = io.StringIO(), io.StringIO()
    here, typed = os.getcwd(), sys.stdin
    os.chdir(cwd)
    sys.stdin = io.StringIO(stdin)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main([str(a) for a in args])
            except SystemExit as e:       # argparse's usage errors and --help
                code = e.code if isinstance(e.code, int) else 2
    finally:
        os.chdir(here)
        sys.stdin = typed
    return Result(code, out.getvalue(), err.getvalue())
