"""Score of a `mutmut run`, per module: killed / (all - equivalent), and every unexplained survivor.

`make mutation` (tests/mutation_module.py) runs mutmut over each group of modules and then
this, in that group's copy of the tree. A survivor is either a missing test (write it) or an equivalent mutant (the change cannot
alter any result): those are listed with the reason in tests/mutation-equivalent.txt, one
`mutant-name  reason` per line. Exit 1 when a module scores under the bar, a survivor is
unexplained or a listed mutant is killed (a stale line: mutmut numbers a function's mutants in
order, so editing the function moves them), so the target fails until each is killed or
justified and the list says why of the mutants it names.
"""

from __future__ import annotations

import fnmatch
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

BAR = 0.90
HERE = Path(__file__).resolve().parent
#: mutmut's names of the functions whose mutants count ("ǁ" joins a class and its method).
TARGETS = (
    "appliance.console.dose.*",
    "appliance.console.state.*",
    "appliance.console.readout.*",        # the state machine's readout, split from state.py
    "appliance.display.text.*",           # the compositor's text, split from compositor.py
    "appliance.geometry.*",
    "appliance.display.compositor.*",
    "appliance.records.rdsr.*",
    "appliance.calibration.xray_calibration.x_acceptance_failures__mutmut_*",
    *(f"appliance.xray.pixel_geometry.x_{name}__mutmut_*" for name in (
        "at_resolution", "zoomed_K", "pixel_pitch_at_zoom_mm", "ray_directions", "field_radius_px", "field_mask",
        "measuring_field")),
)
RESULT = re.compile(r"^\s*(?P<name>[\w.]+?)\.x_?(?P<func>\w+?)__mutmut_\d+: (?P<status>[\w ]+)$")


def equivalent_mutants(path: Path = HERE / "mutation-equivalent.txt") -> dict[str, str]:
    reasons = {}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                name, _, reason = line.partition(" ")
                reasons[name] = reason.strip()
    return reasons


def main() -> int:
    if sys.argv[1:] == ["--targets"]:
        print(" ".join(TARGETS))
        return 0
    out = subprocess.run([sys.executable, "-m", "mutmut", "results", "--all", "true"], capture_output=True, text=True)
    if out.returncode != 0:
        print(f"mutmut results failed: {out.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
        return 2
    # Mutant names given (a run of only some, tests/mutation_module.py): only those count.
    targets = tuple(sys.argv[1:]) or TARGETS
    equivalent = equivalent_mutants()
    per_module: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    for line in out.stdout.splitlines():
        m = RESULT.match(line)
        if m and any(fnmatch.fnmatchcase(line.strip().split(":")[0], glob) for glob in targets):
            per_module[m["name"]][m["status"].strip()].append(line.strip().split(":")[0])
    if not per_module:
        print("no mutation results: run `mutmut run` first", file=sys.stderr)
        return 2
    ok = True
    print(f"{'module':40s} {'mutants':>7s} {'run':>6s} {'killed':>7s} {'equiv':>6s} {'other':>6s} {'score':>6s}")
    for module, by_status in sorted(per_module.items()):
        total = sum(len(v) for v in by_status.values())
        # A run stopped part way (or a mutant mutmut never reached) leaves "not checked": those
        # are counted apart, as not run, and the score is over the mutants that ran; the target
        # still fails until every one has run.
        not_run = len(by_status.get("not checked", []))
        # A mutant whose tests hang or crash the interpreter (segfault: OpenCV handed None for an
        # array) is caught as surely as one that fails them.
        caught = ("killed", "timeout", "segfault")
        killed = sum(len(by_status.get(s, [])) for s in caught)
        survivors = [n for s, names in by_status.items() if s not in (*caught, "not checked") for n in names]
        equiv = [n for n in survivors if n in equivalent]
        unexplained = [n for n in survivors if n not in equivalent]
        # A listed mutant that the tests kill: its number has moved (the module changed) or a
        # test now kills it; either way its line no longer says why a survivor is equivalent.
        stale = [n for s in caught for n in by_status.get(s, []) if n in equivalent]
        # Every mutant that ran equivalent (a run of only the listed ones): nothing to kill, so 100 %.
        counted = total - not_run - len(equiv)
        score = killed / counted if counted else 1.0
        print(f"{module:40s} {total:7d} {total - not_run:6d} {killed:7d} {len(equiv):6d} {len(unexplained):6d} {score:6.1%}")
        for name in unexplained:
            print(f"    unexplained: {name} ({next(s for s, v in by_status.items() if name in v)})")
        for name in stale:
            print(f"    stale: {name} is listed in mutation-equivalent.txt but the tests kill it")
        if not_run:
            print(f"    not run: {not_run} mutants")
        ok &= score >= BAR and not unexplained and not stale and not not_run
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
