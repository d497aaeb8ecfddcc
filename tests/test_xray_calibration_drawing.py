"""The workshop drawing is at 1:1: a ball drawn where the profile says, measured on the page."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from PIL import Image

from appliance.cli import main
from appliance.config import load_profile
from appliance.config.calibration_phantom import CalibrationPhantomProfile

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "configs" / "calibration-phantoms" / "two-plane-36.yaml"
PX_PER_MM = 300 / 25.4


def test_drawing_is_a4_at_one_to_one_with_every_ball_in_place(tmp_path, capsys):
    assert main(["print-calibration-phantom", str(tmp_path / "phantom.pdf")]) == 0
    pdf = (tmp_path / "phantom.pdf").read_bytes()
    assert pdf.startswith(b"%PDF") and len(re.findall(rb"/Type\s*/Page\b", pdf)) == 2  # plan and table
    page = np.asarray(Image.open(tmp_path / "phantom.png").convert("L"))
    assert page.shape == (round(297 * PX_PER_MM), round(210 * PX_PER_MM))
    phantom = load_profile(PHANTOM, CalibrationPhantomProfile)
    # The plate outline is the longest dark run of columns and rows: find its box independently.
    dark = page < 128
    plate_cols = np.nonzero(dark.sum(axis=0) > 0.9 * 180 * PX_PER_MM)[0]  # the plate's two long edges
    left, right = plate_cols.min(), plate_cols.max()
    column = np.concatenate([[0], dark[:, left].astype(int), [0]])
    starts, ends = np.nonzero(np.diff(column) == 1)[0], np.nonzero(np.diff(column) == -1)[0]
    longest = np.argmax(ends - starts)
    top, bottom = starts[longest], ends[longest] - 1
    assert abs((right - left) / PX_PER_MM - 120) < 0.5 and abs((bottom - top) / PX_PER_MM - 180) < 0.5
    u0, v0 = (left + right) / 2, (top + bottom) / 2
    for s in phantom.spheres:
        x, y, z = s.centre_mm
        u, v = round(u0 + x * PX_PER_MM), round(v0 - y * PX_PER_MM)  # plan view from +z: y up the page
        ring = z < 0
        r = s.diameter_mm / 2 * PX_PER_MM
        if ring:  # bottom-plate balls are rings: dark on the rim, light at the centre
            assert page[v, u] > 128 and page[v, round(u + r - 1)] < 128, s.id
        else:
            assert page[v - 2:v + 3, u - 2:u + 3].max() < 128, s.id
