"""`make mutation-console`: mutmut over the console state machine alone, with its own fast tests.

The whole [tool.mutmut] selection runs the saved-image, export and DICOM tests for each of the
state machine's ~1,040 mutants too (they call it): hours on two cores. Its own tests (below) run
in about a second a mutant and kill what those do. mutmut reads its settings from pyproject.toml
only, so this runs it in a copy of the tree (build/mutation-console) whose [tool.mutmut] names
this module and these tests, then prints the score from there (tests/mutation_score.py).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WORK = REPO / "build" / "mutation-console"
MODULE = "appliance/console/state.py"
TESTS = ["tests/test_console.py", "tests/test_console_record.py", "tests/test_console_transitions.py",
         "tests/test_console_adjustments.py", "tests/test_console_pulsed_alarm.py", "tests/test_run_technique.py",
         "tests/test_crash_timer.py", "tests/test_breath_hold_overlay.py"]


def main() -> int:
    children = sys.argv[1] if len(sys.argv) > 1 else "1"
    shutil.rmtree(WORK, ignore_errors=True)
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True, text=True,
                           check=True).stdout.split()
    for name in files:
        if (REPO / name).is_file():
            (WORK / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, WORK / name)
    toml = (WORK / "pyproject.toml").read_text()
    toml = re.sub(r"^only_mutate = \[.*?\]$", f'only_mutate = ["{MODULE}"]', toml, flags=re.M | re.S)
    toml = re.sub(r"^pytest_add_cli_args_test_selection = \[.*?\]$",
                  "pytest_add_cli_args_test_selection = [" + ", ".join(f'"{t}"' for t in TESTS) + "]", toml,
                  flags=re.M | re.S)
    (WORK / "pyproject.toml").write_text(toml)
    mutmut = Path(sys.executable).with_name("mutmut")
    with open(WORK / "mutation.log", "w") as log:
        run = subprocess.run([str(mutmut), "run", "--max-children", children, "appliance.console.state.*"], cwd=WORK,
                             stdout=log, stderr=subprocess.STDOUT)
    if run.returncode != 0:
        print((WORK / "mutation.log").read_text()[-2000:], file=sys.stderr)
        return 1
    return subprocess.run([sys.executable, str(REPO / "tests" / "mutation_score.py")], cwd=WORK).returncode


if __name__ == "__main__":
    sys.exit(main())
