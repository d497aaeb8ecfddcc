"""A chest whose ribs line the lungs and whose scapulae lie on the upper ribs, drawn in closed
form for the rib-finding tests (synthetic_chest.py's rods run through its lungs and it has no
scapulae).

On synthetic_chest's body, lungs and spine: each rib is a tube (radius RIB_RADIUS) whose axis runs
from the spine's side (the neck) to the lung's posteromedial surface and round the lung's outline,
RIB_AXIS_MM outside it, to the front; the scapula is a curved plate SCAPULA_MM from the lung on the
back of each side, over the two upper ribs, with a small bony contact patch at each, so that on
the CT the scapula and the upper ribs of a side are one piece of bone. LPS mm, 2.5 mm voxels.
"""

from __future__ import annotations

import numpy as np
import synthetic_chest as sc
from scipy import ndimage
from scipy.spatial import cKDTree

from appliance.patient.volume import Volume

RIB_Z = (100.0, 70.0, 40.0)
RIB_RADIUS = 3.5
RIB_AXIS_MM = 4.5                        # the axis outside the lung's outline (its tube spans 1-8 mm)
RIB_ARC_DEG = (135.0, -45.0)             # posteromedial to anterolateral (0 = lateral, 90 = posterior)
NECK_START = (13.0, 38.0)                # |x|, y of the neck's medial end, beside the spine
SCAPULA_MM = (11.0, 16.0)                # its inner and outer faces from the lungs
SCAPULA_ARC_DEG = (40.0, 110.0)
SCAPULA_Z = (55.0, 115.0)
CONTACT_DEG = 75.0                       # where each upper rib touches the scapula
HU_RIB, HU_SCAPULA = 900.0, 700.0


def lung_radii(z: float) -> tuple[float, float]:
    """The lung's half-widths (x, y) at height z (synthetic_chest's ellipsoid)."""
    f = np.sqrt(max(1.0 - ((z - 60.0) / 90.0) ** 2, 0.0))
    return 40.0 * f, 45.0 * f


def rib_axis(z: float, side: int, theta_deg) -> np.ndarray:
    """Points (n, 3) of a rib's axis on its arc at angles theta (deg)."""
    a, b = lung_radii(z)
    t = np.radians(np.atleast_1d(np.asarray(theta_deg, float)))
    x = side * (sc.LUNG_X + (a + RIB_AXIS_MM) * np.cos(t))
    y = (b + RIB_AXIS_MM) * np.sin(t)
    return np.stack([x, y, np.full_like(x, z)], axis=-1)


def rib_points(z: float, side: int) -> np.ndarray:
    """The whole axis, neck and arc, sampled every half millimetre or so."""
    arc = rib_axis(z, side, np.linspace(*RIB_ARC_DEG, 400))
    neck_from = np.array([side * NECK_START[0], NECK_START[1], z])
    neck = neck_from + np.linspace(0.0, 1.0, 40)[:, None] * (arc[0] - neck_from)
    return np.vstack([neck, arc])


def rib_cage() -> tuple[Volume, dict[str, np.ndarray]]:
    """The CT and masks of its parts ("ribs", "scapulae", "contacts", "spine"), on the CT's grid."""
    T, x, y, z = sc.grid()
    hu = np.full(x.shape, -1000.0, np.float32)
    hu[(x / 110.0) ** 2 + (y / 70.0) ** 2 <= 1.0] = 40.0
    lungs = sc._lungs(x, y, z)
    hu[lungs] = -850.0
    spine = sc._spine(x, y, z)
    hu[spine] = 700.0
    from_lungs = ndimage.distance_transform_edt(~lungs, sampling=sc.SPACING)
    ribs = np.zeros(x.shape, bool)
    pts = np.stack([x, y, z], axis=-1)
    for zr in RIB_Z:
        slab = np.abs(z - zr) <= RIB_RADIUS + sc.SPACING
        for side in (-1, 1):
            d, _ = cKDTree(rib_points(zr, side)).query(pts[slab])
            ribs[slab] |= d <= RIB_RADIUS
    ribs &= ~spine
    # Angle round each lung's axis, its outline's ellipse made round (0 lateral, 90 posterior).
    theta = np.degrees(np.arctan2(y, (np.abs(x) - sc.LUNG_X) * 45.0 / 40.0))
    back = (theta >= SCAPULA_ARC_DEG[0]) & (theta <= SCAPULA_ARC_DEG[1]) & (z >= SCAPULA_Z[0]) & (z <= SCAPULA_Z[1])
    scapulae = back & (from_lungs >= SCAPULA_MM[0]) & (from_lungs <= SCAPULA_MM[1]) & (np.abs(x) > sc.LUNG_X - 20)
    contacts = np.zeros(x.shape, bool)
    for zr in RIB_Z:
        if SCAPULA_Z[0] <= zr <= SCAPULA_Z[1]:
            contacts |= ((np.abs(theta - CONTACT_DEG) <= 5.0) & (np.abs(z - zr) <= 2.5)
                         & (from_lungs >= RIB_AXIS_MM) & (from_lungs <= SCAPULA_MM[0] + 1.0))
    contacts &= ~ribs & ~scapulae
    hu[ribs] = HU_RIB
    hu[scapulae | contacts] = HU_SCAPULA
    ct = Volume(np.rint(hu).astype(np.int16), T, source="synthetic rib cage")
    return ct, {"ribs": ribs, "scapulae": scapulae, "contacts": contacts, "spine": spine, "from_lungs": from_lungs}
