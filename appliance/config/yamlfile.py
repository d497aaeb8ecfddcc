"""Read a YAML profile keeping where every key and item came from.

ruamel's round-trip loader records (line, column) of each mapping key and sequence item;
`Located` keeps that document beside the plain Python data so a validation error at
`zoom_levels[2].fov_mm` can be reported as `file:14`. ruamel counts lines from 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from ruamel.yaml import YAML
from ruamel.yaml.comments import CommentedMap, CommentedSeq
from ruamel.yaml.error import MarkedYAMLError, YAMLError

#: A profile is a few kilobytes; anything far larger is a wrong file, not a profile.
MAX_PROFILE_BYTES = 1_000_000


@dataclass
class Problem:
    """One thing wrong with a profile, printed as `file:line: field: message`."""

    file: str
    line: int | None
    field: str
    message: str

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line else self.file
        return f"{where}: {self.field}: {self.message}" if self.field else f"{where}: {self.message}"


class ProfileProblems(Exception):
    """Raised with every problem found in one profile (or a tree of them)."""

    def __init__(self, problems: list[Problem]):
        super().__init__("\n".join(str(p) for p in problems))
        self.problems = problems


@dataclass
class Located:
    """A loaded YAML document: plain data plus the round-trip tree that knows line numbers."""

    path: Path
    display: str
    data: Any
    tree: Any

    def line_of(self, loc: tuple) -> int | None:
        """1-based line of the deepest part of `loc` (keys and list indices) found in the file."""
        node, line = self.tree, None
        for part in loc:
            if isinstance(node, CommentedMap) and part in node:
                line = node.lc.key(part)[0] + 1
                node = node[part]
            elif isinstance(node, CommentedSeq) and isinstance(part, int) and 0 <= part < len(node):
                line = node.lc.item(part)[0] + 1
                node = node[part]
            elif isinstance(part, str) and not isinstance(node, (CommentedMap, CommentedSeq)):
                continue  # a pydantic union or validator tag, not a document key
            else:
                break
        if line is None and isinstance(self.tree, CommentedMap) and self.tree.lc.line is not None:
            line = self.tree.lc.line + 1
        return line


def display_path(path: Path) -> str:
    """The path as a person typed it: relative to the working directory when inside it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _plain(node: Any) -> Any:
    if isinstance(node, dict):
        return {(str(k) if not isinstance(k, (int, float, bool)) else k): _plain(v) for k, v in node.items()}
    if isinstance(node, list):
        return [_plain(v) for v in node]
    if isinstance(node, bool):
        return bool(node)
    if isinstance(node, int):
        return int(node)
    if isinstance(node, float):
        return float(node)
    if isinstance(node, str):
        return str(node)
    return node


def round_trip_yaml() -> YAML:
    yaml = YAML(typ="rt")
    yaml.allow_duplicate_keys = False
    yaml.preserve_quotes = True
    return yaml


def load(path: str | Path) -> Located:
    """Read and parse `path`, raising ProfileProblems with one clear line for any failure."""
    path = Path(path)
    shown = display_path(path)

    def fail(message: str, line: int | None = None) -> NoReturn:
        raise ProfileProblems([Problem(shown, line, "", message)])

    try:
        size = path.stat().st_size
        if path.is_dir():
            fail("is a folder, not a YAML profile")
        if size > MAX_PROFILE_BYTES:
            fail(f"is {size / 1e6:.1f} MB; a profile is at most {MAX_PROFILE_BYTES // 1000} kB (is this the right file?)")
        raw = path.read_bytes()
    except FileNotFoundError:
        fail("does not exist (check the path)")
    except PermissionError:
        fail("cannot be read (permission denied); check its owner and mode")
    except OSError as e:
        fail(f"cannot be read ({e.strerror or e})")
    if b"\x00" in raw:
        fail("is a binary file, not a YAML profile")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        fail(f"is not UTF-8 text (bad byte at offset {e.start}); save it as UTF-8")
    if not text.strip() or all(l.strip().startswith("#") or not l.strip() for l in text.splitlines()):
        fail("is empty; a profile needs at least its required keys (see the shipped examples in configs/)")
    try:
        tree = round_trip_yaml().load(text)
    except MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line = mark.line + 1 if mark is not None else None
        what = (e.problem or e.context or "invalid YAML").strip()
        fail(f"YAML syntax error: {what}", line)
    except YAMLError as e:
        fail(f"YAML syntax error: {str(e).splitlines()[0] if str(e) else 'invalid YAML'}")
    if not isinstance(tree, CommentedMap):
        kind = "a list" if isinstance(tree, list) else f"a single value ({str(tree)[:40]!r})"
        fail(f"must be a mapping of keys to values, but the file holds {kind}", 1)
    return Located(path=path, display=shown, data=_plain(tree), tree=tree)
