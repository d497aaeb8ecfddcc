"""A case's `respiration:` section with command-line overrides, and the breathing CT at a time."""

from __future__ import annotations

from pathlib import Path

from pydantic import ValidationError

from ..config.case import CaseProfile, Respiration
from ..errors import FluorosimError
from .breathing_motion import BreathingAnatomy, load_labels
from .respiration import state_at
from .volume import Volume

#: Keys `--respiration` may set: the scalar fields of the section (label maps stay in the profile).
OVERRIDABLE = tuple(name for name, f in Respiration.model_fields.items() if name not in ("labels",))


def parse_overrides(text: str | None) -> dict[str, str]:
    """`KEY=VALUE[,KEY=VALUE...]` as a dict; one clear line for anything else."""
    if not text:
        return {}
    out: dict[str, str] = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not sep or not key or not value:
            raise FluorosimError(f"--respiration: '{item}' is not KEY=VALUE (e.g. --respiration diaphragm_mm=7.5,rate_per_min=20)")
        if key not in OVERRIDABLE:
            raise FluorosimError(f"--respiration: unknown key '{key}'; the keys are {', '.join(OVERRIDABLE)}")
        if key in out:
            raise FluorosimError(f"--respiration: '{key}' given twice")
        out[key] = value
    return out


def respiration_for(case: CaseProfile, overrides: dict[str, str], where: str) -> Respiration | None:
    """The case's section with `overrides` applied and validated; None when the case does not breathe."""
    if case.respiration is None and not overrides:
        return None
    base = case.respiration.model_dump(exclude_unset=True) if case.respiration is not None else {}
    merged = {**base, **overrides}
    if merged.get("label_map") in ("", "none"):
        merged["label_map"] = None
    try:
        params = Respiration.model_validate(merged)
    except ValidationError as e:
        err = e.errors()[0]
        field = ".".join(str(p) for p in err["loc"])
        raise FluorosimError(f"{where}: respiration.{field}: {err['msg']} (given {err.get('input')!r})") from None
    problems = list(params.problems())
    if problems:
        loc, message = problems[0]
        raise FluorosimError(f"{where}: respiration.{'.'.join(map(str, loc))}: {message}")
    return params


def breathing_ct(case_path: Path, params: Respiration, ct: Volume, materials, t_s: float) -> Volume:
    """The case's CT (end-expiration) with the breath of time `t_s` (s) applied."""
    labels = load_labels(case_path, params, ct)
    anatomy = BreathingAnatomy(ct, params, materials, labels, label_source=str(params.label_map))
    return anatomy.volume_at(state_at(params, t_s))
