"""`make mutation` runs tests/mutation_module.py's groups in turn: together they must mutate
every function tests/mutation_score.py counts, each module in one group, and pyproject's
[tool.mutmut] (what mutmut itself reads) must list exactly their modules and test files."""

from __future__ import annotations

from pathlib import Path

import mutation_module
from mutation_score import TARGETS

REPO = Path(__file__).resolve().parents[1]


def test_the_groups_are_the_whole_selection():
    assert mutation_module.selection_problems() == []
    globs = [g for modules, _ in mutation_module.GROUPS.values() for m in modules for g in mutation_module.target_globs(m)]
    assert sorted(globs) == sorted(TARGETS)
    for _, tests in mutation_module.GROUPS.values():
        assert all((REPO / t).is_file() for t in tests), tests


def test_a_module_left_out_of_every_group_is_named(monkeypatch):
    groups = dict(mutation_module.GROUPS)
    _, tests = groups["records"]
    groups["records"] = ([], tests)
    monkeypatch.setattr(mutation_module, "GROUPS", groups)
    problems = mutation_module.selection_problems()
    assert "appliance.records.rdsr.* is in TARGETS but in no group's modules" in problems
    assert any(p.startswith("pyproject.toml [tool.mutmut] only_mutate differs") and "appliance/records/rdsr.py" in p
               for p in problems)
