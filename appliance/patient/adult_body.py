"""The synthetic adult chest's body: its tissue values, its voxel grid, and the surfaces
everything else is drawn inside (skin, body cavity, diaphragm domes, lungs).

`adult_chest.py` draws the organs and writes the CT; `adult_skeleton.py` the bones.
Coordinates are the `ct` frame (LPS, mm): x toward the patient's left, y posterior, z superior.
"""

from __future__ import annotations

import numpy as np

from ..errors import FluorosimError
from .shapes import grid_axis, grid_box, intersect

# --- Hounsfield units (typical unenhanced adult CT values) ---
HU_AIR = -1000.0
HU_LUNG = -860.0                # aerated lung; the dependent (posterior) lung is denser
HU_LUNG_DEPENDENT_RISE = 60.0   # HU more at the back of the lung than at the front, supine
HU_FAT = -100.0
HU_MEDIASTINUM = -60.0          # mediastinal fat with lymph nodes and small vessels
HU_SKIN = 40.0
HU_MUSCLE = 45.0
HU_BLOOD = 40.0                 # unenhanced blood pool
HU_MYOCARDIUM = 45.0
HU_LIVER = 60.0
HU_SPLEEN = 50.0
HU_KIDNEY = 35.0
HU_BOWEL = 30.0
HU_FLUID = 10.0
HU_DISC = 80.0
HU_CSF = 10.0
HU_CARTILAGE = 180.0            # an adult's costal cartilage is partly calcified
HU_CORTICAL = 1300.0
HU_TRABECULAR = 220.0           # cancellous bone of a middle-aged adult
HU_NOISE = 6.0                  # standard deviation of the CT's own noise (HU)

# --- sizes (mm) ---
#: Trunk cross-section by height z: semi-axes a (left-right) and b (antero-posterior) and
#: the y of its centre: 330 x 220 mm across the chest, broader over the shoulders (arms up).
BODY_Z = np.array([-200, -150, -100, -50, 0, 50, 100, 150, 200], np.float32)
BODY_A = np.array([158, 160, 162, 165, 168, 170, 172, 168, 150], np.float32)
BODY_B = np.array([112, 110, 108, 106, 108, 112, 114, 110, 100], np.float32)
BODY_YC = np.array([-4, -4, -3, -2, 0, 2, 4, 6, 8], np.float32)
BODY_POWER = 2.4                # superellipse: an adult's back and flanks are flatter than an ellipse
SKIN_MM = 2.0
SUBCUT_FAT_MM = 16.0
WALL_MM = 14.0                  # intercostal and abdominal wall muscle
PECTORAL_MM = 18.0              # the pectoral muscles over the upper anterior chest
LUNG_APEX_Z = 165.0
#: Diaphragm domes at end-expiration: apex (x, y, z) mm; the surface falls by DOME_DROP_MM
#: over DOME_RADIUS_MM from the apex, into the costophrenic recesses.
RIGHT_DOME = (-75.0, 5.0, -5.0)
LEFT_DOME = (80.0, 5.0, -22.0)
DOME_DROP_MM = 70.0
DOME_RADIUS_MM = 95.0
DIAPHRAGM_MM = 4.0


class AnisotropicGrid:
    """The voxel grid of a CT with its own spacing along z, y and x, for `shapes.Layer`.

    `spacing_mm`, the one number `Layer` blends partial-volume edges over, is the geometric
    mean of the three spacings: the width of a voxel on average over directions.
    """

    def __init__(self, shape_zyx, spacing_zyx, what: str = "CT"):
        # `what` names the CT in the one-line refusal of a grid no CT can have.
        if len(shape_zyx) != 3 or min(shape_zyx) < 2:
            raise FluorosimError(f"{what}: shape_zyx {tuple(shape_zyx)} must be three counts of at least 2 voxels")
        if len(spacing_zyx) != 3 or min(spacing_zyx) <= 0:
            raise FluorosimError(f"{what}: spacing_mm {tuple(spacing_zyx)} must be three positive sizes (mm)")
        self.shape = tuple(int(n) for n in shape_zyx)
        self.spacing_zyx = tuple(float(s) for s in spacing_zyx)
        sz, sy, sx = self.spacing_zyx
        self.spacing_xyz = (sx, sy, sz)
        self.spacing_mm = float(np.prod(self.spacing_xyz) ** (1.0 / 3.0))
        nz, ny, nx = self.shape
        self.origin_mm = tuple(-(n - 1) / 2 * s for n, s in zip((nx, ny, nz), self.spacing_xyz))

    # The same voxel geometry as `shapes.Grid`, with a spacing of its own along each axis.
    axis = grid_axis
    box = grid_box


def body_at(Z, values):
    return np.interp(Z, BODY_Z, values).astype(np.float32)


def superellipse(X, Y, a, b, yc):
    """Approximate distance (mm) to the superellipse of semi-axes a, b centred at (0, yc)."""
    u, w = np.abs(X) / a, np.abs(Y - yc) / b
    rho = (u ** BODY_POWER + w ** BODY_POWER) ** (1.0 / BODY_POWER)
    return (rho - 1.0) * np.sqrt((a * u) ** 2 + (b * w) ** 2) / (rho + 1e-6)


def skin(X, Y, Z, inset=0.0):
    """The skin of the trunk moved inward by `inset` mm (the whole grid is trunk along z)."""
    return superellipse(X, Y, body_at(Z, BODY_A) - inset, body_at(Z, BODY_B) - inset, body_at(Z, BODY_YC))


def cavity(X, Y, Z):
    """Thorax and abdomen inside the wall; the pectorals thicken the wall in front above z = 40."""
    wall = SKIN_MM + SUBCUT_FAT_MM + WALL_MM
    front = PECTORAL_MM * np.clip((Z - 40.0) / 60.0, 0, 1) * np.clip((60.0 - Y) / 120.0, 0, 1)
    top = LUNG_APEX_Z + 15.0 - 60.0 * (X / 130.0) ** 2
    return intersect(skin(X, Y, Z, wall) + front, Z - top)


def dome_z(X, Y, apex):
    """Height (mm) of a diaphragm dome above (x, y)."""
    r2 = ((X - apex[0]) ** 2 + (Y - apex[1]) ** 2) / DOME_RADIUS_MM ** 2
    return apex[2] - DOME_DROP_MM * r2


def diaphragm_z(X, Y):
    """The diaphragm: the higher of the two domes, with a saddle under the heart."""
    return np.maximum(dome_z(X, Y, RIGHT_DOME), dome_z(X, Y, LEFT_DOME))


def lung(X, Y, Z, side: int):
    """Right (side -1) or left (+1) lung: the cavity above the diaphragm lateral to the mediastinum."""
    medial = 18.0 + 12.0 * np.clip((Y - 30.0) / 40.0, 0, 1)     # the spine widens the mediastinum at the back
    return intersect(cavity(X, Y, Z) + 3.0, medial - side * X, diaphragm_z(X, Y) + DIAPHRAGM_MM - Z)
