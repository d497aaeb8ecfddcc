"""`make mutation-console` / `make mutation-display`: mutmut over one group of modules with its own fast tests.

The whole [tool.mutmut] selection runs the saved-image, export and DICOM tests for each mutant of
the state machine or the compositor too (they call them): hours on two cores. Each group's own
tests (the table below) run in about a second a mutant and kill what those do. mutmut reads its
settings from pyproject.toml only, so this runs it in a copy of the tree (build/mutation-<group>)
whose [tool.mutmut] names these modules and these tests, then prints the score from there
(tests/mutation_score.py).

    python tests/mutation_module.py GROUP [CHILDREN] [MUTANT-GLOB ...]

With globs (mutmut's names, "appliance.display.text.x_wrap_text__mutmut_*") it runs only those
mutants, in a copy of its own (build/mutation-<group>-some), so a full run can go on beside it.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

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
}


def toml_list(names: list[str]) -> str:
    return "[" + ", ".join(f'"{n}"' for n in names) + "]"


def main() -> int:
    if len(sys.argv) < 2 or sys.argv[1] not in GROUPS:
        print(f"usage: mutation_module.py {{{','.join(GROUPS)}}} [CHILDREN] [MUTANT-GLOB ...]", file=sys.stderr)
        return 2
    group = sys.argv[1]
    children = sys.argv[2] if len(sys.argv) > 2 else "1"
    modules, tests = GROUPS[group]
    some = sys.argv[3:]
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
    globs = some or [m.removesuffix(".py").replace("/", ".") + ".*" for m in modules]
    with open(work / "mutation.log", "w") as log:
        run = subprocess.run([str(mutmut), "run", "--max-children", children, *globs], cwd=work,
                             stdout=log, stderr=subprocess.STDOUT)
    if run.returncode != 0:
        print((work / "mutation.log").read_text()[-2000:], file=sys.stderr)
        return 1
    return subprocess.run([sys.executable, str(REPO / "tests" / "mutation_score.py"), *some], cwd=work).returncode


if __name__ == "__main__":
    sys.exit(main())
