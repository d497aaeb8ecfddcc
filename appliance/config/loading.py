"""Load profiles into their models and report every problem as `file:line: field: message`.

`load_profile` reads one file; `validate_paths` checks files and everything they refer to
(the profiles an appliance file names, the volumes of a case); `load_appliance` gives the
daemon one consistent set of profiles or one ProfileProblems naming what is wrong.
"""

from __future__ import annotations

import difflib
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from .appliance import ApplianceProfile
from .calibration_phantom import CalibrationPhantomProfile
from .case import CaseProfile
from .fluoroscope import FluoroscopeProfile
from .keymap import KeymapProfile
from .phantom import PhantomProfile
from .webcam import WebcamProfile
from .yamlfile import Located, Problem, ProfileProblems, load

M = TypeVar("M", bound=BaseModel)

#: Every kind of profile, by the name used in messages and on the command line.
KINDS: dict[str, type[BaseModel]] = {
    "appliance": ApplianceProfile,
    "fluoroscope": FluoroscopeProfile,
    "case": CaseProfile,
    "phantom": PhantomProfile,
    "keymap": KeymapProfile,
    "webcam": WebcamProfile,
    "calibration-phantom": CalibrationPhantomProfile,
}

#: Folder under configs/ -> kind of the profiles in it.
KIND_OF_FOLDER = {"fluoroscopes": "fluoroscope", "cases": "case", "phantoms": "phantom",
                  "keymaps": "keymap", "webcams": "webcam",
                  "calibration-phantoms": "calibration-phantom"}

#: A top-level key that only one kind has, to recognise a profile outside configs/.
_KIND_BY_KEY = {"devices": "appliance", "detector": "fluoroscope", "markers": "phantom",
                "keys": "keymap", "hid_usages": "keymap", "K": "webcam", "title": "case"}


def kind_of(located: Located) -> str | None:
    parent = located.path.resolve().parent.name
    if parent in KIND_OF_FOLDER:
        return KIND_OF_FOLDER[parent]
    if located.path.name.startswith("appliance"):
        return "appliance"
    for key, kind in _KIND_BY_KEY.items():
        if key in located.data:
            return kind
    return None


def _strip_optional(tp: Any) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else tp
    return tp


def _model_at(model: type[BaseModel], loc: tuple) -> type[BaseModel] | None:
    """The section model that `loc` points into, to list the keys it accepts."""
    tp: Any = model
    for part in loc:
        tp = _strip_optional(tp)
        if isinstance(tp, type) and issubclass(tp, BaseModel) and isinstance(part, str) and part in tp.model_fields:
            tp = tp.model_fields[part].annotation
        elif typing.get_origin(tp) in (list, dict) and typing.get_args(tp):
            tp = typing.get_args(tp)[-1]
        else:
            return None
    tp = _strip_optional(tp)
    return tp if isinstance(tp, type) and issubclass(tp, BaseModel) else None


def _field_path(loc: tuple) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _message(err: Any, model: type[BaseModel]) -> str:
    kind, msg = err["type"], err["msg"]
    if kind == "missing":
        return "is required but missing"
    if kind == "extra_forbidden":
        parent = _model_at(model, tuple(err["loc"][:-1]))
        key = str(err["loc"][-1])
        if parent is not None:
            allowed = list(parent.model_fields)
            near = difflib.get_close_matches(key, allowed, n=1)
            hint = f"did you mean '{near[0]}'?" if near else "allowed keys: " + ", ".join(allowed)
            return f"unknown key; {hint}"
        return "unknown key"
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, "):]
    msg = msg.replace("Input should be", "must be").replace("List should have", "must have").replace(" after validation", "")
    if kind not in ("value_error", "assertion_error") and "input" in err and not isinstance(err["input"], (dict, list)):
        shown = repr(err["input"])
        msg += f" (got {shown[:60]})"
    return str(msg)


def validate_located(located: Located, model: type[M]) -> tuple[M | None, list[Problem]]:
    try:
        obj = model.model_validate(located.data)
    except ValidationError as e:
        problems = []
        for err in e.errors():
            # Drop pydantic's own tags (function-after[...], literal[...]); keep document keys and indices.
            loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and "[" in p))
            problems.append(Problem(located.display, located.line_of(loc), _field_path(loc), _message(err, model)))
        return None, problems
    problems = [Problem(located.display, located.line_of(loc), _field_path(loc), msg)
                for loc, msg in getattr(obj, "problems", lambda: ())()]
    return (obj if not problems else None), problems


def load_profile(path: str | Path, model: type[M]) -> M:
    """Load and validate one profile, or raise ProfileProblems naming file, line and field."""
    located = load(path)
    obj, problems = validate_located(located, model)
    if problems or obj is None:
        raise ProfileProblems(problems)
    return obj


def resolve(base: Path, relative: str) -> Path:
    """A path written in a profile, taken relative to that profile's folder."""
    p = Path(relative).expanduser()
    return p if p.is_absolute() else (base.parent / p)


def _references(kind: str, obj: Any) -> list[tuple[tuple, str, str | None]]:
    """(location, path as written, kind it must be or None for a plain file/folder) of each reference."""
    if kind == "appliance":
        refs: list[tuple[tuple, str, str | None]] = [(("fluoroscope",), obj.fluoroscope, "fluoroscope"), (("case",), obj.case, "case"),
                (("phantom",), obj.phantom, "phantom"), (("keymap",), obj.keymap, "keymap"),
                (("devices", "camera", "webcam"), obj.devices.camera.webcam, "webcam")]
        if obj.devices.keypad.script:
            refs.append((("devices", "keypad", "script"), obj.devices.keypad.script, None))
        if obj.devices.camera.trajectory:
            refs.append((("devices", "camera", "trajectory"), obj.devices.camera.trajectory, None))
        return refs
    if kind == "case" and obj.phases:
        return [(("phases", i, "volume"), ph.volume, None) for i, ph in enumerate(obj.phases)]
    return []


def _cross_problems(kind: str, located: Located, obj: Any) -> list[Problem]:
    problems = []
    if kind == "appliance":
        keypad = obj.devices.keypad
        if keypad.source == "scripted" and not keypad.script:
            problems.append(Problem(located.display, located.line_of(("devices", "keypad", "source")),
                                    "devices.keypad.script", "is required when devices.keypad.source is 'scripted'"))
        if obj.devices.display.target == "file" and not obj.devices.display.path:
            problems.append(Problem(located.display, located.line_of(("devices", "display", "target")),
                                    "devices.display.path", "is required when devices.display.target is 'file'"))
    return problems


def validate_paths(paths: list[Path]) -> list[Problem]:
    """Every problem in `paths` and in the files they refer to, each file checked once."""
    problems: list[Problem] = []
    done: dict[Path, str | None] = {}  # resolved path -> kind it validated as (None: invalid)

    def check(path: Path, expected: str | None) -> None:
        key = path.resolve()
        if key in done:
            return
        try:
            located = load(path)
        except ProfileProblems as e:
            done[key] = None
            problems.extend(e.problems)
            return
        kind = expected or kind_of(located)
        done[key] = kind
        if kind is None:
            problems.append(Problem(located.display, 1, "", "cannot tell what kind of profile this is; put it under "
                                    "configs/<fluoroscopes|cases|phantoms|keymaps|webcams>/ or name it appliance*.yaml"))
            return
        obj, found = validate_located(located, KINDS[kind])
        problems.extend(found)
        if obj is None:
            return
        problems.extend(_cross_problems(kind, located, obj))
        for loc, written, ref_kind in _references(kind, obj):
            target = resolve(path, written)
            if not target.exists():
                problems.append(Problem(located.display, located.line_of(loc), _field_path(loc),
                                        f"{written} does not exist (looked for {target})"))
            elif ref_kind is not None:
                check(target, ref_kind)

    for path in paths:
        if path.is_dir():
            for p in sorted(path.rglob("*.yaml")) + sorted(path.rglob("*.yml")):
                check(p, None)
        else:
            check(path, None)
    return problems


@dataclass(frozen=True)
class ApplianceConfig:
    """One consistent set of active profiles, with the paths they came from."""

    path: Path
    appliance: ApplianceProfile
    fluoroscope: FluoroscopeProfile
    fluoroscope_path: Path
    case: CaseProfile
    case_path: Path
    phantom: PhantomProfile
    phantom_path: Path
    keymap: KeymapProfile
    webcam: WebcamProfile
    webcam_path: Path
    data_dir: Path

    def resolve(self, written: str) -> Path:
        """A path written in the appliance profile."""
        return resolve(self.path, written)


def load_appliance(path: str | Path) -> ApplianceConfig:
    """Load the appliance profile and every profile it names, or raise ProfileProblems."""
    path = Path(path)
    problems = validate_paths([path])
    if problems:
        raise ProfileProblems(problems)
    a = load_profile(path, ApplianceProfile)
    fl, ca, ph = resolve(path, a.fluoroscope), resolve(path, a.case), resolve(path, a.phantom)
    wc = resolve(path, a.devices.camera.webcam)
    return ApplianceConfig(
        path=path, appliance=a,
        fluoroscope=load_profile(fl, FluoroscopeProfile), fluoroscope_path=fl,
        case=load_profile(ca, CaseProfile), case_path=ca,
        phantom=load_profile(ph, PhantomProfile), phantom_path=ph,
        keymap=load_profile(resolve(path, a.keymap), KeymapProfile),
        webcam=load_profile(wc, WebcamProfile), webcam_path=wc,
        data_dir=resolve(path, a.data_dir),
    )
