"""Reading a JSONL file a person wrote: one JSON object per line, blank lines and `#` comments skipped.

Keypad scripts and webcam trajectories are both written this way; each caller checks its own
fields, and this module owns what every such line shares: the line numbers in messages,
comments, and refusing NaN and Infinity, which `json.loads` would otherwise accept as floats.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number; every value on the line must be finite")


def json_lines(lines: Iterable[str], display: str, problem: type[Exception],
               hint: str = "") -> Iterator[tuple[str, object]]:
    """(where, value) of every line that is not blank or a comment; `where` is "FILE:LINE".

    A line that is not JSON raises `problem` naming the file and line, followed by `hint`
    (what the caller's lines should look like).
    """
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        where = f"{display}:{number}"
        try:
            value = json.loads(line, parse_constant=_refuse_constant)
        except json.JSONDecodeError as e:
            raise problem(f"{where}: not valid JSON ({e.msg}){hint}") from None
        except (ValueError, RecursionError) as e:
            raise problem(f"{where}: {e}") from None
        yield where, value
