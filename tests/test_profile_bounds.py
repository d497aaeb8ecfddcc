"""The bounds of the fluoroscope profile's `ct_sampling` and `energy_nodes` sections, each at
its edge: the value on the bound is taken, the value just past it is refused with one line
naming the file, the line and the field (config/energy_nodes.py, config/ct_sampling.py).

Ground truth: the bounds as each field's description and unit state them (a fraction of I/I0
up to 5 %, at most the spectrum's 24 bins, a transmission strictly between 0 and 1, areal
densities from 0 or above 0), and the line found in the edited file's own text.
"""

from pathlib import Path

import pytest

from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.config.yamlfile import ProfileProblems

SHIPPED = Path(__file__).resolve().parents[1] / "configs" / "fluoroscopes" / "generic-flat-detector.yaml"

#: (section, field, the shipped line's value text, value to write, taken?)
EDGES = [
    ("energy_nodes", "enabled", "true", "maybe", False),
    ("energy_nodes", "max_relative_error", "0.002", "0", False),
    ("energy_nodes", "max_relative_error", "0.002", "0.05", True),
    ("energy_nodes", "max_relative_error", "0.002", "0.051", False),
    ("energy_nodes", "max_nodes", "12", "0", False),
    ("energy_nodes", "max_nodes", "12", "1", True),
    ("energy_nodes", "max_nodes", "12", "24", True),
    ("energy_nodes", "max_nodes", "12", "25", False),
    ("energy_nodes", "max_nodes", "12", "2.5", False),
    ("energy_nodes", "min_transmission", "1.0e-5", "0", False),
    ("energy_nodes", "min_transmission", "1.0e-5", "0.999", True),
    ("energy_nodes", "min_transmission", "1.0e-5", "1", False),
    ("energy_nodes", "air_max_g_per_cm2", "0.2", "0", True),
    ("energy_nodes", "air_max_g_per_cm2", "0.2", "-0.1", False),
    ("energy_nodes", "air_max_g_per_cm2", "0.2", "10", True),
    ("energy_nodes", "air_max_g_per_cm2", "0.2", "10.5", False),
    ("energy_nodes", "soft_tissue_max_g_per_cm2", "45", "0", False),
    ("energy_nodes", "soft_tissue_max_g_per_cm2", "45", "200", True),
    ("energy_nodes", "soft_tissue_max_g_per_cm2", "45", "201", False),
    ("energy_nodes", "bone_max_g_per_cm2", "23", "0", True),
    ("energy_nodes", "bone_max_g_per_cm2", "23", "-1", False),
    ("energy_nodes", "bone_max_g_per_cm2", "23", "100", True),
    ("energy_nodes", "bone_max_g_per_cm2", "23", "101", False),
    ("energy_nodes", "contrast_max_g_per_cm2", "4", "0", True),
    ("energy_nodes", "contrast_max_g_per_cm2", "4", "-1", False),
    ("energy_nodes", "contrast_max_g_per_cm2", "4", "100", True),
    ("energy_nodes", "contrast_max_g_per_cm2", "4", "101", False),
    ("ct_sampling", "voxel_edge_px", "4.0", "64", True),
    ("ct_sampling", "voxel_edge_px", "4.0", "64.5", False),
    ("ct_sampling", "voxel_edge_px", "4.0", "0.01", True),
    ("ct_sampling", "voxel_edge_px", "4.0", "null", True),
]


@pytest.mark.parametrize("section, field, shipped, value, taken", EDGES,
                         ids=[f"{f}={v}" for _, f, _, v, _ in EDGES])
def test_each_bound_takes_its_edge_and_refuses_past_it(tmp_path, section, field, shipped, value, taken):
    text = SHIPPED.read_text()
    old = f"\n  {field}: {shipped}"
    at = text.index(old, text.index(f"\n{section}:"))          # the field in its own section
    edited = text[:at] + f"\n  {field}: {value}" + text[at + len(old):]
    line = edited[:at].count("\n") + 2
    path = tmp_path / "fluoroscope.yaml"
    path.write_text(edited)
    if taken:
        got = getattr(getattr(load_profile(path, FluoroscopeProfile), section), field)
        assert got == (None if value == "null" else float(value))
        return
    with pytest.raises(ProfileProblems) as err:
        load_profile(path, FluoroscopeProfile)
    (problem,) = err.value.problems
    message = str(problem)
    assert "\n" not in message and message.startswith(f"{path}:{line}: ") and f"{section}.{field}" in message


def test_an_unknown_key_in_the_energy_nodes_section_is_refused_on_its_line(tmp_path):
    text = SHIPPED.read_text().replace("  max_nodes: 12 ", "  max_node: 12 ", 1)
    line = text[:text.index("  max_node: 12")].count("\n") + 1
    path = tmp_path / "fluoroscope.yaml"
    path.write_text(text)
    with pytest.raises(ProfileProblems) as err:
        load_profile(path, FluoroscopeProfile)
    messages = [str(p) for p in err.value.problems]
    assert any(m.startswith(f"{path}:{line}: ") and "energy_nodes.max_node" in m for m in messages), messages
