"""ProfileKeeper: SIGHUP reload keeps the last good profiles; a bad profile at start is one error."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from appliance.config import ProfileProblems
from appliance.daemon.reload import ProfileKeeper

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture
def configs(tmp_path):
    shutil.copytree(CONFIGS, tmp_path / "configs")
    return tmp_path / "configs"

def test_bad_edit_keeps_the_last_good_profiles(configs):
    keeper = ProfileKeeper(configs / "appliance.yaml")
    good = keeper.current
    fl = configs / "fluoroscopes" / "generic-ii-carm.yaml"
    text = fl.read_text()
    lines = text.splitlines()
    line_no = next(i for i, l in enumerate(lines) if "source_to_image_mm:" in l) + 1
    fl.write_text(text.replace("source_to_image_mm: 1000", "source_to_image_mm: -5"))
    config, changed = keeper.reload()
    assert not changed and config is good
    assert f"generic-ii-carm.yaml:{line_no}: geometry.source_to_image_mm" in keeper.problem
    fl.write_text(text.replace("name: Generic II C-arm", "name: Renamed C-arm"))
    config, changed = keeper.reload()
    assert changed and keeper.problem is None
    assert config.fluoroscope.name == "Renamed C-arm" and keeper.generation == 2

def test_a_bad_profile_at_start_is_one_clear_error(configs):
    (configs / "appliance.yaml").write_text((configs / "appliance.yaml").read_text().replace("operator: trainee", "operater: x"))
    with pytest.raises(ProfileProblems) as e:
        ProfileKeeper(configs / "appliance.yaml")
    assert "did you mean 'operator'" in str(e.value)

def test_case_override_replaces_only_the_case(configs):
    other = configs / "cases" / "other.yaml"
    other.write_text((configs / "cases" / "child-torso-vcug.yaml").read_text().replace(
        "title: Child torso - VCUG and breathing", "title: Another case"))
    keeper = ProfileKeeper(configs / "appliance.yaml", case=other)
    assert keeper.current.case.title == "Another case" and keeper.current.case_path == other
    assert keeper.current.fluoroscope.name == "Generic II C-arm"
    other.write_text(other.read_text().replace("period_s: 4.0", "period_s: -4.0"))
    config, changed = keeper.reload()
    assert not changed and "other.yaml" in keeper.problem and "breathing.period_s" in keeper.problem
    with pytest.raises(ProfileProblems):
        ProfileKeeper(configs / "appliance.yaml", case=configs / "cases" / "missing.yaml")
