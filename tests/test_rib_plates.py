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


def test_the_breathing_anatomy_widens_by_the_profiles_rib_plate_widen_mm():
    """On the synthetic chest, a scapula-like plate 5 mm thick across y leaning 25 degrees,
    joined to the left middle rib by a bony patch one slice (2.5 mm) tall. Its own vertical runs
    are 5 / tan 25 = 10.7 mm (at most 12.5 mm on 2.5 mm slices, 15 mm with the patch): not
    taller than the 15 mm limit, so bone unwidened would move it with the rib. Widened by the
    default 3 mm (one 2.5 mm row each way) it is 10 mm thick, its runs 10 / tan 25 = 21 mm: a
    plate, so it stays still and the rib still turns."""
    import synthetic_chest as sc

    from appliance.config.case import Materials, Respiration
    from appliance.patient.breathing_motion import BreathingAnatomy
    from appliance.patient.volume import Volume

    T, x, y, z = sc.grid()
    face = 30.0 + math.tan(math.radians(25.0)) * (z - 62.0)
    plate = (np.abs(y - face) <= 2.5) & (z >= 45) & (z <= 90) & (x >= 50) & (x <= 80)
    patch = (x >= 55) & (x <= 60) & (y >= 16) & (y <= 29) & (np.abs(z - 61.25) <= 1.0)
    assert vertical_run_mm(plate | patch, sc.SPACING)[plate].max() <= 15.0
    hu = sc.chest().hu.copy()
    hu[plate | patch] = 700
    ct = Volume(hu, T, source="synthetic chest with a leaning plate")

    def held(params):
        anatomy = BreathingAnatomy(ct, params, Materials())
        cover = np.zeros(anatomy.shape, bool)
        for rib in anatomy.ribs:
            cover[rib.box] |= rib.alpha > 0
        return anatomy, cover

    assert Respiration().rib_plate_widen_mm == 3.0
    anatomy, cover = held(Respiration())
    assert len(anatomy.ribs) == len(sc.RIBS)
    assert not cover[plate].any() and anatomy.still[plate].all()
    # The control: unwidened, the leaning plate is as low as a rib and turns with it.
    _, unwidened = held(Respiration(rib_plate_widen_mm=0.0))
    assert unwidened[plate].all()
