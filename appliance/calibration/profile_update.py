"""Write a calibration into the fluoroscope profile, in place, atomically, keeping the old file.

The YAML is edited round-trip so the technician's comments and layout survive; only the
intrinsics (and, when marker poses were given, the webcam transform) change. The edited
document is validated against the fluoroscope model before anything touches the disk,
and the previous version stays beside it as PROFILE.yaml.bak.
"""

from __future__ import annotations

import datetime
import io
from pathlib import Path

import numpy as np
from ruamel.yaml.comments import CommentedMap, CommentedSeq

from ..atomic_file import write_atomic
from ..config.fluoroscope import FluoroscopeProfile
from ..config.loading import validate_located
from ..config.yamlfile import Located, ProfileProblems, _plain, load, round_trip_yaml
from .fit import Fit


def _flow(values) -> CommentedSeq:
    seq = CommentedSeq(values)
    seq.fa.set_flow_style()
    return seq


def updated_profile_text(path: str | Path, fit: Fit, T_xray_from_webcam: np.ndarray | None,
                         today: datetime.date | None = None) -> str:
    """The profile's new text; raises ProfileProblems if the result would not validate."""
    located = load(path)
    tree = located.tree
    intr = tree["intrinsics"]
    intr["status"] = "calibrated"
    intr["fx"] = round(float(fit.K[0, 0]), 4)
    intr["fy"] = round(float(fit.K[1, 1]), 4)
    intr["cx"] = round(float(fit.K[0, 2]), 4)
    intr["cy"] = round(float(fit.K[1, 2]), 4)
    dist = CommentedMap((name, float(f"{v:.8g}")) for name, v in zip(("k1", "k2", "p1", "p2", "k3"), fit.dist))
    dist.fa.set_flow_style()
    intr["distortion"] = dist
    intr["calibrated_on"] = (today or datetime.date.today()).isoformat()
    intr["rms_px"] = round(fit.rms_px, 4)
    if T_xray_from_webcam is not None:
        if "webcam" not in tree or tree["webcam"] is None:
            tree["webcam"] = CommentedMap()
        tree["webcam"]["status"] = "calibrated"
        rows = CommentedSeq([_flow([round(float(x), 6) for x in row]) for row in T_xray_from_webcam])
        tree["webcam"]["T_xray_from_webcam"] = rows
    out = io.StringIO()
    yaml = round_trip_yaml()
    # The shipped profiles indent lists under their key; keep that, and never fold long lines.
    yaml.indent(mapping=2, sequence=4, offset=2)
    yaml.width = 4096
    yaml.dump(tree, out)
    text = out.getvalue()
    reparsed = round_trip_yaml().load(text)
    _, problems = validate_located(Located(located.path, located.display, _plain(reparsed), reparsed), FluoroscopeProfile)
    if problems:
        raise ProfileProblems(problems)
    return text


def write_profile(path: str | Path, fit: Fit, T_xray_from_webcam: np.ndarray | None,
                  today: datetime.date | None = None) -> Path:
    """Replace the profile atomically with the calibrated one; the old one is kept as PATH.bak."""
    text = updated_profile_text(path, fit, T_xray_from_webcam, today)
    return write_atomic(path, text.encode("utf-8"), backup=True)


__all__ = ["ProfileProblems", "updated_profile_text", "write_profile"]
