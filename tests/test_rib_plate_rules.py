"""The plate rule's edges (`breathing_motion.plates`, respiration.rib_max_height_mm and
rib_plate_widen_mm) beside its shapes (tests/test_rib_plates.py): a run exactly as tall as the
limit is no plate, the widening is in millimetres along each axis with that axis's spacing,
and only bone is ever returned.

Ground truth: vertical runs and widened thicknesses worked by hand from the voxel spacing.
"""

from __future__ import annotations

import math

import numpy as np

from appliance.config.case import Respiration
from appliance.patient.breathing_motion import plates


def test_a_run_as_tall_as_the_limit_is_no_plate_and_one_slice_more_is():
    """"Taller than" rib_max_height_mm: 6 slices of 2.5 mm stand 15 mm, 7 stand 17.5 mm."""
    bone = np.zeros((20, 5, 5), bool)
    bone[2:8, 1, 1] = True                     # 15 mm
    bone[2:9, 3, 3] = True                     # 17.5 mm
    cut = plates(bone, -2.5, (1.0, 1.0), 15.0, 0.0)
    assert not cut[:, 1, 1].any()
    assert cut[2:9, 3, 3].all() and cut.sum() == 7


def leaning_plate(spacing_x: float, spacing_y: float) -> tuple[np.ndarray, np.ndarray]:
    """A plate 2 mm thick across y, 100 mm tall, leaning 15 degrees toward y, on a grid of 1 mm
    slices; its own vertical runs are 2 / tan 15 = 7.5 mm. Returns it and its middle (farther
    than 40 mm from its top and bottom, and 6 mm inside its sides)."""
    nz, ny, nx = 110, 60, int(round(60 / spacing_x))
    k, j, i = np.meshgrid(np.arange(nz) * 1.0, np.arange(ny) * spacing_y, np.arange(nx) * spacing_x, indexing="ij")
    face = 30.0 + math.tan(math.radians(15.0)) * (k - 55.0)
    plate = (np.abs(j - face) <= 1.0) & (np.abs(k - 55.0) <= 50.0) & (np.abs(i - 30.0) <= 24.0)
    middle = plate & (np.abs(k - 55.0) <= 10.0) & (np.abs(i - 30.0) <= 18.0)
    return plate, middle


def test_the_widening_across_the_plate_uses_the_spacing_along_that_axis():
    """Widened by 3 mm each way across y (1 mm rows: 3 rows) the plate is 8 mm thick, its runs
    8 / tan 15 = 29.9 mm, over a 20 mm limit: its middle is cut. On 3 mm columns along x the
    widening along x is one column, which changes nothing across the plate. Taking the columns'
    3 mm for the rows would widen it by one row only, (2 + 2) / tan 15 = 14.9 mm: not cut."""
    plate, middle = leaning_plate(spacing_x=3.0, spacing_y=1.0)
    assert middle.sum() > 200
    cut = plates(plate, 1.0, (3.0, 1.0), 20.0, 3.0)
    assert cut[middle].all()
    # The same plate on 1 mm columns is cut the same way: x's spacing does not enter across y.
    plate1, middle1 = leaning_plate(spacing_x=1.0, spacing_y=1.0)
    assert plates(plate1, 1.0, (1.0, 1.0), 20.0, 3.0)[middle1].all()
    # Widened by 1 mm only (rows of 1 mm), the runs are 14.9 mm: under the limit, nothing cut.
    assert not plates(plate, 1.0, (3.0, 1.0), 20.0, 1.0)[middle].any()


def test_only_bone_is_returned_though_the_widening_bridges_a_gap():
    """Two upright plates 60 mm tall, 1 mm thick, 2 mm apart: widened by 3 mm they merge across
    the gap, and the merged block stands tall; the gap's voxels are no bone and are not returned."""
    bone = np.zeros((80, 30, 20), bool)
    bone[10:70, 10, 4:16] = True
    bone[10:70, 13, 4:16] = True
    cut = plates(bone, 1.0, (1.0, 1.0), 15.0, 3.0)
    assert cut[20:60, 10, 6:14].all() and cut[20:60, 13, 6:14].all()
    assert not cut[~bone].any()


def test_a_short_piece_beside_a_plate_keeps_its_voxels_at_the_edge_of_the_bone():
    """A plate one column (1 mm) thick and 50 mm tall, and 3 mm beside it a piece 4 mm tall (a
    rib's end), the outermost bone along x. Widened by 3 mm the two touch, so the piece's
    columns stand tall; shrunk back, the columns 1-3 mm beyond the piece (outside the bone's
    extent) hold only the piece widened, 4 mm tall, so the piece is not cut. Measured as if
    the bone stopped at the piece (its far side mirrored), it would be cut with the plate."""
    bone = np.zeros((60, 20, 30), bool)
    bone[5:55, 5:16, 20] = True
    bone[28:32, 8:13, 23] = True
    cut = plates(bone, 1.0, (1.0, 1.0), 15.0, 3.0)
    assert cut[10:50, 5:16, 20].all()
    assert not cut[28:32, 8:13, 23].any()


def test_the_defaults_tell_a_sloping_rib_from_a_leaning_scapula():
    """respiration's defaults (a 15 mm limit, 3 mm widening) on 1 mm voxels. A rib 10 mm across
    rising 20 degrees: its vertical runs are 10 / cos 20 = 10.6 mm, and widened 3 mm each way
    along its run the rise adds 2 x 3 tan 20 = 2.2 mm: 12.8 mm, under the limit, so it is not
    cut. A scapula 2 mm thick leaning 15 degrees: widened, (2 + 6) / tan 15 = 29.9 mm, over it."""
    p = Respiration()
    k, j, i = np.meshgrid(np.arange(80) * 1.0, np.arange(40) * 1.0, np.arange(120) * 1.0, indexing="ij")
    axis_z = 40.0 + math.tan(math.radians(20.0)) * (i - 60.0)
    rib = (np.hypot((k - axis_z) * math.cos(math.radians(20.0)), j - 20.0) <= 5.0) & (np.abs(i - 60.0) <= 50.0)
    assert not plates(rib, 1.0, (1.0, 1.0), p.rib_max_height_mm, p.rib_plate_widen_mm).any()
    plate, middle = leaning_plate(spacing_x=1.0, spacing_y=1.0)
    assert plates(plate, 1.0, (1.0, 1.0), p.rib_max_height_mm, p.rib_plate_widen_mm)[middle].all()


def test_the_widening_rounds_to_the_nearest_whole_row():
    """3 mm on 0.8 mm rows is 3.75 rows: widened by 4 (3.2 mm) each way the 2 mm plate is 8.4 mm
    thick, its runs 8.4 / tan 15 = 31 mm, over a 28 mm limit; by 3 rows (2.4 mm) it would be
    6.8 mm, 25 mm: under it. So the middle is cut at 3 mm, as at 3.2 mm, and not at 2.4 mm."""
    plate, middle = leaning_plate(spacing_x=1.0, spacing_y=0.8)
    assert middle.sum() > 1000
    assert plates(plate, 1.0, (1.0, 0.8), 28.0, 3.0)[middle].all()
    assert plates(plate, 1.0, (1.0, 0.8), 28.0, 3.2)[middle].all()
    assert not plates(plate, 1.0, (1.0, 0.8), 28.0, 2.4)[middle].any()
