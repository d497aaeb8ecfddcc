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


GRID = ROOT / "configs" / "calibration-phantoms" / "two-plane-grid-332.yaml"
A4_PX = (round(297 * PX_PER_MM), round(210 * PX_PER_MM))


def longest_run(values: np.ndarray) -> tuple[int, int]:
    """(length, start) of the longest run of True."""
    edges = np.diff(np.concatenate([[0], values.astype(int), [0]]))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    if not len(starts):
        return 0, 0
    i = int(np.argmax(ends - starts))
    return int(ends[i] - starts[i]), int(starts[i])


def test_a_plate_too_large_for_a4_prints_an_overview_then_one_to_one_tiles(tmp_path, capsys):
    """The 200 mm grid plate: page 1 says it is not to scale; the tiles carry the plan at 1:1,
    every ball where the YAML puts it, measured from the plate's edge found on the tile; the
    table runs over as many pages as its 332 rows need, and the CSV holds the same positions."""
    from appliance.calibration.drawing import TABLE_ROWS_PER_PAGE, drawing_pages

    assert main(["print-calibration-phantom", str(tmp_path / "grid"), "--phantom-model", str(GRID)]) == 0
    phantom = load_profile(GRID, CalibrationPhantomProfile)
    pages = [np.asarray(p.convert("L")) for p in drawing_pages(phantom)]
    pdf = (tmp_path / "grid.pdf").read_bytes()
    assert len(re.findall(rb"/Type\s*/Page\b", pdf)) == len(pages)
    assert all(p.shape == A4_PX for p in pages)
    table = -(-len(phantom.spheres) // TABLE_ROWS_PER_PAGE)       # 332 rows, 40 a page: 9 pages
    tiles = pages[1:len(pages) - table]
    assert len(tiles) >= 2
    assert np.array_equal(np.asarray(Image.open(tmp_path / "grid.png").convert("L")), pages[0])
    rows = (tmp_path / "grid.csv").read_text().splitlines()
    assert rows[0] == "id,line,x_mm,y_mm,z_mm,diameter_mm" and len(rows) == 1 + len(phantom.spheres)
    for row, s in zip(rows[1:], phantom.spheres):
        fields = row.split(",")
        assert int(fields[0]) == s.id and fields[1] == s.line
        np.testing.assert_allclose([float(v) for v in fields[2:]], [*s.centre_mm, s.diameter_mm])

    # The marker's outline (on the top plate) crosses the plan of a bottom-plate ball or two.
    T, h = phantom.T_phantom_from_marker(), phantom.marker.size_mm / 2
    local = lambda xy: np.abs(T[:2, :2].T @ (np.asarray(xy) - T[:2, 3]))  # noqa: E731
    under_outline = {s.id for s in phantom.spheres
                     if abs(local(s.centre_mm[:2]).max() - h) < s.diameter_mm / 2 + 0.5}
    seen: set[int] = set(under_outline)
    margin = 12 * PX_PER_MM
    for page in tiles:
        dark = page < 128
        # The plate's side edge: the column whose longest dark run is the plate's 200 mm width.
        runs = [longest_run(dark[:, c]) for c in range(page.shape[1])]
        edge_cols = [c for c, (n, _) in enumerate(runs) if abs(n / PX_PER_MM - 200) < 1.0]
        if not edge_cols:
            continue
        top = runs[edge_cols[0]][1]
        # The plate's top edge runs on from its left edge to the right, from its right edge to the left.
        left_edge = bool(dark[top, edge_cols[-1] + 30])
        col = edge_cols[0] if left_edge else edge_cols[-1]             # the outline's outer pixel
        edge_x = -100.0 if left_edge else 100.0
        for s in phantom.spheres:
            x, y, z = s.centre_mm
            u, v = round(col + (x - edge_x) * PX_PER_MM), round(top + (100 - y) * PX_PER_MM)
            if s.id in under_outline or not (margin < u < page.shape[1] - margin and margin < v < page.shape[0] - margin):
                continue
            r = s.diameter_mm / 2 * PX_PER_MM
            if z < 0:     # bottom-plate balls are rings: light at the centre, dark on the rim
                assert page[v, u] > 128 and page[v, round(u + r - 2)] < 128, s.id
            else:
                assert page[v - 2:v + 3, u - 2:u + 3].max() < 128, s.id
            seen.add(s.id)
    assert seen == {s.id for s in phantom.spheres} and len(under_outline) <= 2
