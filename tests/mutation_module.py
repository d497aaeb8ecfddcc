"""`make mutation` and `make mutation-GROUP`: mutmut over each group of modules with its own fast tests.

The whole [tool.mutmut] selection in one mutmut run would run every test file of every group for
each mutant the files reach (the saved-image, export and DICOM tests call the state machine and
the compositor too): hours on two cores. Each group's own tests (the table below) run in about a
second a mutant and kill what those do. mutmut reads its settings from pyproject.toml only, so
this runs it in a copy of the tree (build/mutation-<group>) whose [tool.mutmut] names these
modules and these tests, then prints the score from there (tests/mutation_score.py). Which
functions of a module count is tests/mutation_score.py's TARGETS; only those are mutated.

    python tests/mutation_module.py GROUP [CHILDREN] [MUTANT-GLOB ...]
    python tests/mutation_module.py all [CHILDREN]

`all` (make mutation) runs every group in turn, prints each one's scores and exits 1 if any
group fails; it first checks that the groups cover every TARGETS entry and that pyproject's
[tool.mutmut] lists exactly the groups' modules and tests. With globs (mutmut's names,
"appliance.display.text.x_wrap_text__mutmut_*") it runs only those mutants of one group, in a
copy of its own (build/mutation-<group>-some), so a full run can go on beside it.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

from mutation_score import TARGETS

REPO = Path(__file__).resolve().parents[1]
#: group -> (the modules it mutates, the test files that guard them)
GROUPS: dict[str, tuple[list[str], list[str]]] = {
    "console": (["appliance/console/state.py"],
                ["tests/test_console.py", "tests/test_console_record.py", "tests/test_console_transitions.py",
                 "tests/test_console_adjustments.py", "tests/test_console_pulsed_alarm.py",
                 "tests/test_run_technique.py", "tests/test_crash_timer.py", "tests/test_breath_hold_overlay.py"]),
    "display": (["appliance/display/compositor.py", "appliance/display/text.py"],
                ["tests/test_compositor.py", "tests/test_compositor_banners.py", "tests/test_compositor_blades.py",
                 "tests/test_compositor_dose_lines.py", "tests/test_compositor_exact.py",
                 "tests/test_compositor_markers.py", "tests/test_compositor_corner_text.py", "tests/test_compositor_sizes.py",
                 "tests/test_teaching_overlay.py", "tests/test_text_cut_widths.py", "tests/test_screen_reuse.py"]),
    "dose": (["appliance/console/dose.py", "appliance/console/readout.py"],
             ["tests/test_console.py", "tests/test_console_record.py", "tests/test_console_transitions.py",
              "tests/test_console_adjustments.py", "tests/test_console_pulsed_alarm.py"]),
    "records": (["appliance/records/rdsr.py"],
                ["tests/test_rdsr_content.py", "tests/test_dicom_study.py", "tests/test_run_technique.py",
                 "tests/test_positioner.py", "tests/test_export.py"]),
    "geometry": (["appliance/geometry.py", "appliance/xray/pixel_geometry.py",
                  "appliance/calibration/xray_calibration.py"],
                 ["tests/test_geometry_properties.py", "tests/test_casting_geometry.py",
                  "tests/test_calibration_acceptance.py"]),
}


def toml_list(names: list[str]) -> str:
    return "[" + ", ".join(f'"{n}"' for n in names) + "]"


def dotted(module: str) -> str:
    return module.removesuffix(".py").replace("/", ".")


def target_globs(module: str) -> list[str]:
    """mutmut's names of the module's functions that count (TARGETS), as globs for `mutmut run`."""
    return [t for t in TARGETS if t.startswith(dotted(module) + ".")]


def selection_problems() -> list[str]:
    """What keeps the groups from being the whole selection: a TARGETS entry no group mutates, a
    module with no TARGETS entry, or a pyproject [tool.mutmut] list that is not the groups' union."""
    modules = [m for mods, _ in GROUPS.values() for m in mods]
    tests = [t for _, ts in GROUPS.values() for t in ts]
    problems = [f"{t} is in TARGETS but in no group's modules" for t in TARGETS
                if not any(t.startswith(dotted(m) + ".") for m in modules)]
    problems += [f"{m} is in a group but has no TARGETS entry" for m in modules if not target_globs(m)]
    problems += [f"{m} is in more than one group" for m in set(modules) if modules.count(m) > 1]
    mutmut = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["mutmut"]
    for key, union in (("only_mutate", modules), ("pytest_add_cli_args_test_selection", tests)):
        if set(mutmut[key]) != set(union):
            problems.append(f"pyproject.toml [tool.mutmut] {key} differs from the groups' union: "
                            f"only there {sorted(set(mutmut[key]) - set(union))}, "
                            f"only in the groups {sorted(set(union) - set(mutmut[key]))}")
    return problems


def run_group(group: str, children: str, some: list[str]) -> int:
    modules, tests = GROUPS[group]
    work = REPO / "build" / (f"mutation-{group}-some" if some else f"mutation-{group}")
    shutil.rmtree(work, ignore_errors=True)
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True, text=True,
                           check=True).stdout.split()
    for name in files:
        if (REPO / name).is_file():
            (work / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, work / name)
    toml = (work / "pyproject.toml").read_text()
    toml = re.sub(r"^only_mutate = \[.*?\]$", f"only_mutate = {toml_list(modules)}", toml, flags=re.M | re.S)
    toml = re.sub(r"^pytest_add_cli_args_test_selection = \[.*?\]$",
                  f"pytest_add_cli_args_test_selection = {toml_list(tests)}", toml, flags=re.M | re.S)
    (work / "pyproject.toml").write_text(toml)
    mutmut = Path(sys.executable).with_name("mutmut")
    globs = some or [g for m in modules for g in target_globs(m)]
    with open(work / "mutation.log", "w") as log:
        run = subprocess.run([str(mutmut), "run", "--max-children", children, *globs], cwd=work,
                             stdout=log, stderr=subprocess.STDOUT)
    if run.returncode != 0:
        print((work / "mutation.log").read_text()[-2000:], file=sys.stderr)
        return 1
    return subprocess.run([sys.executable, str(REPO / "tests" / "mutation_score.py"), *some], cwd=work).returncode


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1] not in (*GROUPS, "all") or (sys.argv[1] == "all" and len(sys.argv) > 3):
        print(f"usage: mutation_module.py {{{','.join(GROUPS)}}} [CHILDREN] [MUTANT-GLOB ...]\n"
              "       mutation_module.py all [CHILDREN]", file=sys.stderr)
        return 2
    children = sys.argv[2] if len(sys.argv) > 2 else "1"
    if sys.argv[1] != "all":
        return run_group(sys.argv[1], children, sys.argv[3:])
    problems = selection_problems()
    for problem in problems:
        print(f"mutation selection: {problem}", file=sys.stderr)
    if problems:
        return 2
    failed = []
    for group in GROUPS:
        print(f"== {group}: {' '.join(GROUPS[group][0])}", flush=True)
        if run_group(group, children, []) != 0:
            failed.append(group)
    print(f"mutation: groups failing the bar: {' '.join(failed)}" if failed else "mutation: every group passes the bar")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
