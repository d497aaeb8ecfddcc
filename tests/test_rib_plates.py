"""Ribs told from scapulae by shape: a rib is a thin tube running round the chest, a scapula a
plate standing tall (`breathing_motion.plates`, respiration.rib_max_height_mm).

Ground truth: vertical runs of shapes drawn here in closed form (columns of known height, a
leaning plate, a tube touching it). On real-shaped anatomy: tests/test_ribs_and_scapulae.py
(the rib cage), tests/test_adult_chest.py (the adult chest), tests/test_builtin_patient.py
(the built-in child).
"""

from __future__ import annotations

import math

import numpy as np

from appliance.patient.breathing_motion import plates, vertical_run_mm


def test_vertical_run_is_the_height_of_the_unbroken_column():
    m = np.zeros((20, 3, 4), bool)
    m[2:9, 1, 1] = True           # 7 voxels
    m[10:11, 1, 1] = True         # 1 voxel, after a gap of one
    m[:, 2, 3] = True             # the whole column
    run = vertical_run_mm(m, -2.5)
    assert np.all(run[2:9, 1, 1] == 17.5) and run[10, 1, 1] == 2.5 and run[9, 1, 1] == 0.0
    assert np.all(run[:, 2, 3] == 50.0) and run[~m].max() == 0.0


def test_a_leaning_plate_stands_tall_and_a_tube_touching_it_does_not():
    """A 2 mm plate 100 mm tall leaning 15 degrees, like a scapula on the back (its own vertical
    runs 2 / tan 15 = 7.5 mm, lower than a rib's), and a horizontal tube 8 mm across touching it.
    Widened by W = 3 mm the plate's runs are (2 + 2W) / tan 15 = 30 mm, above the 15 mm limit,
    except near its ends: within 15 mm of an end a column may leave the plate before 15 mm, and
    the shrinking back by W costs W / tan 15 = 11 mm more. So every plate voxel farther than
    27 mm from its ends is cut, and no tube voxel more than 2 mm (two voxels) off the plate is."""
    sp = 1.0
    k, j, i = np.meshgrid(*[np.arange(n) * sp for n in (110, 60, 50)], indexing="ij")
    x, y, z = i, j, k
    lean = math.tan(math.radians(15.0))
    face = 30.0 + lean * (z - 55.0)
    plate = (np.abs(y - face) <= 1.0) & (np.abs(z - 55.0) <= 50.0) & (np.abs(x - 25) <= 20)
    tube = (np.hypot(y - (30.0 + 1.0 + 4.0), z - 55.0) <= 4.0) & (np.abs(x - 25) <= 24)
    bone = plate | tube
    assert vertical_run_mm(plate, sp)[plate].max() <= 2.0 / lean + 1.0
    cut = plates(bone, sp, (sp, sp, sp), 15.0, 3.0)
    middle = plate & (np.abs(z - 55.0) <= 50.0 - 27.0) & (np.abs(x - 25) <= 20 - 3)
    assert middle.sum() > 3000 and cut[middle].all()
    off_plate = tube & (np.abs(y - face) > 1.0 + 2.0)
    assert off_plate.sum() > 1000 and not cut[off_plate].any()
    # Without the widening the leaning plate is as low as a rib: the rule needs it.
    assert not plates(bone, sp, (sp, sp, sp), 15.0, 0.0)[middle].any()
