"""Open the files a profile names, as `fluorosim validate` does before anything runs them.

A profile can be valid while the input script it names holds a NaN time, the trajectory an
infinite angle, or the CT a gap: each is checked here with the same reader the appliance
uses, cheaply (volume headers, a NIfTI's byte count, a few slices of other volumes: see
patient/volume_sampling.py), and reported at the line
of the profile that names it. Volumes may also give warnings (unusual but possible).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import FluorosimError


def script_problem(path: Path, keymap_path: Path | None) -> str | None:
    """Why the keypad script cannot be run on this keymap, or None."""
    from drivers.scripted_input import ScriptedInput, ScriptProblem

    from ..console.keys import action_for, typed_by_badge_reader
    from .keymap import KeymapProfile
    from .loading import load_profile
    from .yamlfile import ProfileProblems

    known = None
    if keymap_path is not None:
        try:
            keymap = load_profile(keymap_path, KeymapProfile)
            known = lambda name: action_for(keymap, name) is not None or typed_by_badge_reader(name)  # noqa: E731
        except ProfileProblems:
            pass  # the keymap's own problems are reported where it is checked
    try:
        ScriptedInput(path, known=known)
    except ScriptProblem as e:
        return str(e)
    return None


def trajectory_problem(path: Path) -> str | None:
    from ..tracking.trajectory import load_trajectory

    try:
        load_trajectory(path)
    except FluorosimError as e:
        return str(e)
    return None


def volume_problems(path: Path) -> tuple[list[str], list[str]]:
    from ..patient.volume_io import check_volume

    return check_volume(path)
