"""The synthetic adult chest on the grids `bench image` needs to tell the chain from its reference.

The detail figure compares the display with the exact (Siddon) line integral of the CT it
was rendered from. Siddon integrates the CT's voxels as constant blocks, so at zoom 4 (a
0.24 mm pixel at the isocentre on a 256 matrix) a clinical CT's 2.5 mm slices stand in the
reference as 10-pixel stairs that are no anatomy. Two more grids of the same patient (the
same seed draws the same vessels, ribs and gas on any grid) separate the two:

- a thin-slice CT, 0.8 mm voxels in all three directions, as a chest CT reconstructed at
  thin slices is: the CT an acceptance test would render and integrate;
- the anatomy itself, sampled finely across the beam (0.2 mm in x and z) and without the
  CT's noise, around one view: its exact line integral is the patient's, not a CT's. Along
  the beam (y) 1 mm is enough: a ray running along y sums a voxel column's HU times its
  length, and a partial-volume voxel's HU is (nearly) the mean along it, so the column's
  sum hardly depends on how finely y is cut.
"""

from __future__ import annotations

import math

import numpy as np

from ..patient.volume import Volume

#: A thin-slice chest CT's voxels (z, y, x; mm).
THIN_SPACING_MM = (0.8, 0.8, 0.8)
#: The thin-slice CT covers the bench's three adult views at zoom 1 with their beams'
#: divergence: x and z (mm, LPS) of its corners, the body's whole depth in y.
THIN_BOX_MM = ((-185.0, -130.0, -170.0), (95.0, 130.0, 155.0))
#: The anatomy's sampling (z, y, x; mm): four times finer than the thin CT across the beam.
ANATOMY_SPACING_MM = (0.2, 1.0, 0.2)
#: Half-width (mm) in x and z of the anatomy around a view's centre: the zoom-4 beam
#: (100 mm at the 1000 mm SID) is 78 mm across at the patient's back (780 mm from the source).
ANATOMY_HALF_MM = 46.0
#: Depth of the body (y, mm, LPS) every grid here covers: the trunk is at most 122 mm from y = 0.
BODY_Y_MM = (-130.0, 130.0)


def adult_chest_box(lo_mm, hi_mm, spacing_zyx, ct_noise: bool = True, seed: int = 0) -> Volume:
    """The adult chest (appliance.patient.adult_chest, `seed`) on voxels of `spacing_zyx` (mm)
    whose centres span the box from `lo_mm` to `hi_mm` (x, y, z; LPS mm), the first at `lo_mm`."""
    from ..patient.adult_chest import build_adult_chest

    sz, sy, sx = spacing_zyx
    # The last centre at or just past hi_mm (a float's rounding of a whole count is no extra voxel).
    counts = [int(math.ceil((hi_mm[i] - lo_mm[i]) / s - 1e-6)) + 1 for i, s in ((2, sz), (1, sy), (0, sx))]
    hu, spacing, origin = build_adult_chest(tuple(counts), spacing_zyx, seed, origin_mm=tuple(lo_mm), ct_noise=ct_noise)
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    T[:3, 3] = origin
    where = "x".join(str(n) for n in hu.shape)
    return Volume(hu=hu, T_ct_from_voxel=T, source=f"adult chest, {where} voxels of {'/'.join(map(str, spacing))} mm")


def thin_slice_chest() -> Volume:
    """The adult chest as a thin-slice CT (THIN_SPACING_MM) over THIN_BOX_MM."""
    return adult_chest_box(*THIN_BOX_MM, THIN_SPACING_MM)


def anatomy_around(centre_ct) -> Volume:
    """The adult chest's anatomy without CT noise on ANATOMY_SPACING_MM, ANATOMY_HALF_MM about
    `centre_ct` (LPS mm) in x and z, the body's whole depth in y."""
    cx, _, cz = (float(c) for c in centre_ct)
    lo = (cx - ANATOMY_HALF_MM, BODY_Y_MM[0], cz - ANATOMY_HALF_MM)
    hi = (cx + ANATOMY_HALF_MM, BODY_Y_MM[1], cz + ANATOMY_HALF_MM)
    return adult_chest_box(lo, hi, ANATOMY_SPACING_MM, ct_noise=False)
