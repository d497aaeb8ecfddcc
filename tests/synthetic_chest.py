"""A simple chest CT drawn in closed form, for the breathing tests: not the built-in patient.

Body: an elliptic cylinder of soft tissue (40 HU) in air. Lungs: two ellipsoids (-850 HU)
whose bases are paraboloid domes with apices at DOME_APEX_Z. Spine: a bone block (700 HU)
behind the centre. Ribs: bone rods (900 HU) from the spine out and down to the side.
LPS mm, 2.5 mm voxels, axial slices.
"""

from __future__ import annotations

import numpy as np

from appliance.patient.volume import Volume

SPACING = 2.5
SHAPE_XYZ = (96, 64, 112)
DOME_APEX_Z = 10.0
LUNG_X = 50.0
DOME_DROP_MM = 40.0
DOME_RADIUS_MM = 45.0
#: Rib rods: (z of the head end, side) from (side*14, 40, z) to (side*95, -5, z - 15), radius 4 mm.
RIBS = [(z, s) for z in (100.0, 70.0, 40.0) for s in (-1, 1)]
RIB_RADIUS = 4.0


def rib_ends(z: float, side: int):
    return np.array([side * 14.0, 40.0, z]), np.array([side * 95.0, -5.0, z - 15.0])


def grid():
    nx, ny, nz = SHAPE_XYZ
    T = np.diag([SPACING, SPACING, SPACING, 1.0])
    T[:3, 3] = -(np.array(SHAPE_XYZ) - 1) / 2.0 * SPACING
    z, y, x = np.meshgrid(*[T[a, 3] + SPACING * np.arange(n) for a, n in ((2, nz), (1, ny), (0, nx))], indexing="ij")
    return T, x, y, z


def dome_z(x, y):
    return DOME_APEX_Z - DOME_DROP_MM * np.minimum(((np.abs(x) - LUNG_X) ** 2 + y ** 2) / DOME_RADIUS_MM ** 2, 1.5)


#: Label ids of chest_labels(): the two lungs and the spine.
LUNG_LABELS, SPINE_LABEL = (10, 11), 30


def _lungs(x, y, z):
    return (((np.abs(x) - LUNG_X) / 40.0) ** 2 + (y / 45.0) ** 2 + ((z - 60.0) / 90.0) ** 2 <= 1.0) & (z > dome_z(x, y))


def _spine(x, y, z):
    return (np.abs(x) < 12) & (y > 30) & (y < 55) & (np.abs(z) < 135)


def chest_labels() -> np.ndarray:
    """A label map of chest(): right lung 10, left lung 11, spine 30, else 0."""
    T, x, y, z = grid()
    lab = np.zeros(x.shape, np.int16)
    lungs = _lungs(x, y, z)
    lab[lungs & (x < 0)], lab[lungs & (x > 0)] = LUNG_LABELS
    lab[_spine(x, y, z)] = SPINE_LABEL
    return lab


def chest(ribs: bool = True, lung_hu: float = -850.0) -> Volume:
    T, x, y, z = grid()
    hu = np.full(x.shape, -1000.0, np.float32)
    hu[(x / 110.0) ** 2 + (y / 70.0) ** 2 <= 1.0] = 40.0
    hu[_lungs(x, y, z)] = lung_hu
    hu[_spine(x, y, z)] = 700.0
    if ribs:
        for zr, s in RIBS:
            p, q = rib_ends(zr, s)
            d = q - p
            pts = np.stack([x, y, z], axis=-1) - p
            t = np.clip(pts @ d / (d @ d), 0, 1)
            dist = np.linalg.norm(pts - t[..., None] * d, axis=-1)
            hu[dist <= RIB_RADIUS] = 900.0
    return Volume(np.rint(hu).astype(np.int16), T, source="synthetic chest")
