"""A small, fast, real appliance for tests: the shipped profiles plus a tiny CT case.

The case is a 192 mm water cylinder with a bone rod on a coarse grid, written as a real
MetaImage file and loaded through the same volume reader as a user's CT; the renderer
draws a small matrix. Everything else (synthetic webcam, tracker, console, ledger, file
framebuffer) is the appliance's own code.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from ruamel.yaml import YAML

from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.xray.pixel_geometry import at_resolution

REPO = Path(__file__).resolve().parents[1]

#: The test cases' placement and materials: where the nominal webcam-to-X-ray transform puts the
#: beam's axis with the box straight below, and the HU thresholds of a CT of water and bone.
CASE_PLACEMENT = """T_phantom_from_ct:
  - [1, 0, 0, -150]
  - [0, 1, 0, 0]
  - [0, 0, 1, 0]
  - [0, 0, 0, 1]
materials:
  air_max_hu: -800
  bone_min_hu: 300
"""

CASE_YAML = """title: Test cylinder
phases:
  - {volume: cylinder-0.mha, time_s: 0}
  - {volume: cylinder-1.mha, time_s: 2}
at_end: loop
""" + CASE_PLACEMENT


def write_cylinder(path: Path, rod_offset_mm: float = 0.0) -> None:
    """64^3 voxels of 3 mm: air, a water cylinder (r 80 mm) along z, a bone rod (r 12 mm)."""
    n, spacing = 64, 3.0
    c = (np.arange(n) - (n - 1) / 2) * spacing
    z, y, x = np.meshgrid(c, c, c, indexing="ij")
    hu = np.full((n, n, n), -1000, np.int16)
    hu[x**2 + y**2 <= 80.0**2] = 0
    hu[(x - 30.0 - rod_offset_mm) ** 2 + y**2 <= 12.0**2] = 1000
    image = sitk.GetImageFromArray(hu)
    image.SetSpacing((spacing,) * 3)
    image.SetOrigin((float(c[0]),) * 3)
    sitk.WriteImage(image, str(path), True)


def make_appliance(tmp: Path, *, camera: str = "synthetic", script: list[str] | None = None,
                   clock_rate: float = 1.0, render_px: int = 64, display=(320, 256), stall_timeout_s: float = 5.0,
                   base: str = "appliance-bench.yaml", keypad: str | None = None, pedal: str | None = None,
                   abc: bool = False) -> Path:
    """configs/ copied under `tmp` with a tiny case; returns the appliance profile's path."""
    configs = tmp / "configs"
    shutil.copytree(REPO / "configs", configs)
    cases = configs / "cases"
    write_cylinder(cases / "cylinder-0.mha")
    write_cylinder(cases / "cylinder-1.mha", rod_offset_mm=6.0)
    (cases / "cylinder.yaml").write_text(CASE_YAML)
    yaml = YAML(typ="rt")
    data = yaml.load((configs / base).read_text())
    data["case"] = "cases/cylinder.yaml"
    data["data_dir"] = str(tmp / "data")
    data["devices"]["display"]["width"], data["devices"]["display"]["height"] = display
    if camera != "synthetic":
        data["devices"]["camera"]["source"] = camera
    if script is not None:
        data["devices"]["keypad"]["script"] = "scripts/test-session.jsonl"
    if keypad is not None:
        data["devices"]["keypad"] = {"source": keypad}
    if pedal is not None:
        data["devices"]["pedal"] = {"source": pedal, "silence_timeout_s": 0.5}
    d = data["daemon"]
    d["clock_rate"], d["render_matrix_px"], d["stall_timeout_s"] = clock_rate, render_px, stall_timeout_s
    # Most tests read the screen's brightness against the profile's fixed window and level
    # (with automatic brightness control any uniform object would sit at mid-grey) and the
    # dose against the reference rates, so they run without it.
    # The detector is read out at twice the render matrix (its field and intrinsics scaled), so
    # saved images take the native re-render path at a cost a test can afford.
    fluoroscope = configs / data["fluoroscope"]
    native = at_resolution(load_profile(fluoroscope, FluoroscopeProfile), 2 * render_px, 2 * render_px)
    profile = native.model_dump(mode="json", exclude_none=True)
    profile["abc"]["enabled"] = abc
    with open(fluoroscope, "w") as f:
        yaml.dump(profile, f)
    path = configs / "appliance-test.yaml"
    with open(path, "w") as f:
        yaml.dump(data, f)
    if script is not None:
        (configs / "scripts" / "test-session.jsonl").write_text("\n".join(script) + "\n")
    return path
