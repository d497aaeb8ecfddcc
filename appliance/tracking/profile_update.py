"""Write measured numbers back into phantom and webcam profiles, keeping their comments.

The file is edited as a ruamel round-trip tree (comments and layout stay), validated as
the profile model before anything is written, and replaced atomically with the previous
version kept as `.bak`.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from ruamel.yaml.comments import CommentedSeq

from ..atomic_file import write_atomic
from ..config.loading import validate_located
from ..config.phantom import PhantomProfile
from ..config.webcam import WebcamProfile
from ..config.yamlfile import Located, ProfileProblems, _plain, display_path, load, round_trip_yaml
from ..errors import FluorosimError


def _flow(values) -> CommentedSeq:
    seq = CommentedSeq(values)
    seq.fa.set_flow_style()
    return seq


def _rows(M: np.ndarray, decimals: int) -> CommentedSeq:
    return CommentedSeq([_flow([_num(v, decimals) for v in row]) for row in np.asarray(M)])


def _num(v: float, decimals: int) -> float | int:
    r = round(float(v), decimals)
    return 0.0 if r == 0 else r          # no "-0.0" in a profile


def _save(path: Path, located: Located, model) -> None:
    buf = io.StringIO()
    round_trip_yaml().dump(located.tree, buf)
    text = buf.getvalue()
    tree = round_trip_yaml().load(text)
    check = Located(path=path, display=located.display, data=_plain(tree), tree=tree)
    _, problems = validate_located(check, model)
    if problems:
        raise ProfileProblems(problems)
    write_atomic(path, text.encode("utf-8"), backup=True)


def write_phantom_layout(path: str | Path, layout: dict[int, np.ndarray]) -> None:
    """Set T_phantom_from_marker (mm) and calibrated: true for each marker in `layout`."""
    path = Path(path)
    located = load(path)
    markers = located.tree.get("markers") if hasattr(located.tree, "get") else None
    if not isinstance(markers, list):
        raise FluorosimError(f"{display_path(path)}: has no markers list to write the calibration into")
    written = set()
    for m in markers:
        i = m.get("id")
        if i in layout:
            # Rotations to 1e-6 keep the matrix rigid within the loader's tolerance; translations to 1 um.
            T = np.asarray(layout[i])
            rows = [[_num(v, 6) for v in T[r, :3]] + [_num(T[r, 3], 3)] for r in range(3)] + [[0, 0, 0, 1]]
            m["T_phantom_from_marker"] = CommentedSeq([_flow(r) for r in rows])
            m["calibrated"] = True
            written.add(i)
    missing = set(layout) - written
    if missing:
        raise FluorosimError(f"{display_path(path)}: marker(s) {sorted(missing)} are not in the profile's markers list")
    _save(path, located, PhantomProfile)


def write_webcam_intrinsics(path: str | Path, K: np.ndarray, dist: np.ndarray, rms_px: float,
                            width: int, height: int) -> None:
    """Set K, dist, rms_px, width, height and status: calibrated in a webcam profile."""
    path = Path(path)
    located = load(path)
    tree = located.tree
    tree["width"], tree["height"] = int(width), int(height)
    tree["K"] = _rows(K, 4)
    tree["dist"] = _flow([_num(v, 6) for v in np.asarray(dist).reshape(-1)[:5]])
    tree["status"] = "calibrated"
    tree["rms_px"] = _num(rms_px, 4)
    _save(path, located, WebcamProfile)
