"""A synthetic adult chest and upper abdomen CT, in Hounsfield units, for tests and benchmarks.

The built-in patient is a child; an image chain tuned on a child alone fails on an adult,
whose mediastinum and spine let through a hundred times fewer photons and whose lungs let
through more. This draws a 45-year-old man of average build from the lung apices down to
the upper poles of the kidneys: skin, subcutaneous fat, chest-wall muscle, 12 pairs of ribs
with a cortical shell and costal cartilage, sternum, clavicles, scapulae, the spine T1-L2
(cortex, cancellous bone, discs, posterior elements, canal), lungs with branching
pulmonary vessels and bronchi, heart with pericardial fat, aorta, trachea, diaphragm domes
(the right higher), liver, spleen, stomach with its gas bubble, kidneys and colon with gas.

The grid may be anisotropic, as a clinical CT is (2.5 mm slices, 0.8 mm pixels); any
shape and spacing cover the same body, centred in the grid, so a small grid is the same
patient at coarse resolution. Coordinates are the `ct` frame of DESIGN.md (LPS, mm):
x toward the patient's left, y posterior, z superior.

    python -m appliance.patient.adult_chest --out DIR [--small]

writes `adult-chest.mha` and a case profile `adult-chest.yaml` beside it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..errors import FluorosimError
from .shapes import (
    Layer,
    bounds,
    ellipsoid,
    elliptic_prism,
    grid_axis,
    grid_box,
    intersect,
    paint_bone,
    paint_tube,
    rotation,
)

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
_BODY_Z = np.array([-200, -150, -100, -50, 0, 50, 100, 150, 200], np.float32)
_BODY_A = np.array([158, 160, 162, 165, 168, 170, 172, 168, 150], np.float32)
_BODY_B = np.array([112, 110, 108, 106, 108, 112, 114, 110, 100], np.float32)
_BODY_YC = np.array([-4, -4, -3, -2, 0, 2, 4, 6, 8], np.float32)
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
SPINE_Y = 62.0                  # y of the vertebral body centres at mid-thorax (mm)
T1_TOP_Z = 190.0
#: Pulmonary vessels: a branch splits while its radius is above this (mm); Murray's law
#: gives children of 2^(-1/3) of the parent's radius.
VESSEL_MIN_RADIUS_MM = 0.7


class AnisotropicGrid:
    """The voxel grid of a CT with its own spacing along z, y and x, for `shapes.Layer`.

    `spacing_mm`, the one number `Layer` blends partial-volume edges over, is the geometric
    mean of the three spacings: the width of a voxel on average over directions.
    """

    def __init__(self, shape_zyx, spacing_zyx):
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


def _at(Z, values):
    return np.interp(Z, _BODY_Z, values).astype(np.float32)


def _superellipse(X, Y, a, b, yc):
    """Approximate distance (mm) to the superellipse of semi-axes a, b centred at (0, yc)."""
    u, w = np.abs(X) / a, np.abs(Y - yc) / b
    rho = (u ** BODY_POWER + w ** BODY_POWER) ** (1.0 / BODY_POWER)
    return (rho - 1.0) * np.sqrt((a * u) ** 2 + (b * w) ** 2) / (rho + 1e-6)


def skin(X, Y, Z, inset=0.0):
    """The skin of the trunk moved inward by `inset` mm (the whole grid is trunk along z)."""
    return _superellipse(X, Y, _at(Z, _BODY_A) - inset, _at(Z, _BODY_B) - inset, _at(Z, _BODY_YC))


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


# --- the spine ---

def _vertebrae():
    """(name, centre z, height, disc below, half-width, half-depth) of T1-L3, from T1_TOP_Z down."""
    out, top = [], T1_TOP_Z
    for i in range(15):
        thoracic = i < 12
        h = float(np.interp(i, [0, 11, 12, 14], [17, 24, 26, 28]))
        disc = 4.5 if thoracic else 9.0
        a = float(np.interp(i, [0, 11, 14], [15, 22, 25]))
        b = float(np.interp(i, [0, 11, 14], [12, 17, 18]))
        name = f"T{i + 1}" if thoracic else f"L{i - 11}"
        out.append((name, top - h / 2, h, disc, a, b))
        top -= h + disc
    return out


def spine_y(z):
    """y of the vertebral body centres (mm): thoracic kyphosis, lumbar lordosis."""
    return SPINE_Y + 10.0 * np.sin(np.pi * np.clip((z + 60.0) / 250.0, 0, 1)) - 8.0


def _paint_spine(layer: Layer) -> None:
    for name, zc, h, disc, a, b in _vertebrae():
        y = float(spine_y(zc))
        back = y + b
        for s in (-1, 1):
            ped = (s * 0.6 * a, back + 9, zc + 1)
            lamina = (0.0, back + 20, zc - 3)
            tp = (s * (a + (30 if name.startswith("L") else 22)), back + (5 if name.startswith("L") else 16), zc + 2)
            for path, radius in (([(s * 0.5 * a, y + 0.6 * b, zc + 1), ped], 4.0), ([ped, lamina], 3.5), ([ped, tp], 4.0)):
                paint_tube(layer, path, radius, HU_CORTICAL * 0.7)
        paint_tube(layer, [(0.0, back + 20, zc - 3), (0.0, back + 42, zc - 22)], (5.0, 3.0), HU_CORTICAL * 0.7)
        c = (0.0, y, zc)
        paint_bone(layer, lambda X, Y, Z, c=c, a=a, b=b, h=h: elliptic_prism(X, Y, Z, c, a, b, h / 2, power=2.2),
                   *bounds([c], max(a, b, h) + 3), 1.2, HU_CORTICAL, HU_TRABECULAR)
        dc = (0.0, y, zc - h / 2 - disc / 2)
        layer.paint(lambda X, Y, Z, dc=dc, a=a, b=b, disc=disc: elliptic_prism(X, Y, Z, dc, a - 0.5, b - 0.5, disc / 2 + 0.3, power=2.2),
                    HU_DISC, *bounds([dc], max(a, b) + 3))
        canal = (0.0, back + 9, zc)
        layer.paint(lambda X, Y, Z, c=canal, h=h + disc: elliptic_prism(X, Y, Z, c, 9.0, 7.5, h / 2 + 0.5),
                    HU_CSF, *bounds([canal], 12 + h))


# --- ribs, sternum, shoulder girdle ---

def _rib_path(level: int, zc: float, y_spine: float):
    """Points (mm) of rib `level` (0 = first) of the right side: from the head at the spine
    round the chest wall to its anterior end, falling toward the front as ribs do."""
    zr = zc + 4.0
    a = float(_at(zr, _BODY_A)) - SKIN_MM - SUBCUT_FAT_MM - 8.0
    b = float(_at(zr, _BODY_B)) - SKIN_MM - SUBCUT_FAT_MM - 8.0
    yc = float(_at(zr, _BODY_YC))
    if level == 0:
        a, b = a - 45.0, b - 25.0            # the first rib is short and tight
    elif level == 1:
        a, b = a - 18.0, b - 10.0
    end = (0.80 if level < 7 else 0.70 if level < 10 else 0.52 if level == 10 else 0.40) * np.pi
    drop = 45.0 + 6.0 * min(level, 7)
    theta = np.linspace(0.12 * np.pi, end, 14)
    points = [(-12.0 - 14.0, y_spine + 4.0, zc + 2.0)]        # the head, beside the vertebral body
    for th in theta:
        n = (np.sin(th) ** BODY_POWER + abs(np.cos(th)) ** BODY_POWER) ** (1.0 / BODY_POWER)
        f = (1.0 - np.cos(th)) / 2.0
        points.append((-a * np.sin(th) / n, yc + b * np.cos(th) / n, zr - drop * f ** 1.3))
    return np.array(points), end


def _paint_ribs_and_sternum(layer: Layer) -> None:
    verts = _vertebrae()
    sternum_y = float(_at(80.0, _BODY_YC) - _at(80.0, _BODY_B)) + SKIN_MM + SUBCUT_FAT_MM + 12.0
    sternum_top, sternum_bottom = 120.0, -15.0
    for level in range(12):
        _, zc, h, _, _, _ = verts[level]
        pts, _ = _rib_path(level, zc, float(spine_y(zc)))
        r_out = 4.0 if level in (0, 10, 11) else 5.0
        for s in (-1, 1):
            side = pts * [-s, 1, 1]
            paint_tube(layer, side, r_out, HU_CORTICAL)
            paint_tube(layer, side, r_out - 1.4, HU_TRABECULAR)
            if level < 10:
                # Costal cartilage from the rib's end to the sternum (ribs 1-7) or to the
                # cartilage above (8-10), rising toward the front.
                z_st = sternum_top - 8 - (sternum_top - sternum_bottom - 16) * min(level, 6) / 6.0
                if level < 7:
                    target = (s * 14.0, sternum_y, z_st)
                else:
                    target = (s * (50.0 + 12 * (level - 7)), sternum_y + 12.0, z_st - 10 * (level - 6))
                mid = 0.5 * (side[-1] + np.array(target)) + [0, -6.0, 0]
                paint_tube(layer, [side[-1], mid, target], (r_out - 0.5, r_out - 1.0, r_out - 1.5), HU_CARTILAGE)
    for zc, half_w, half_h in ((108.0, 26.0, 14.0), (80.0, 16.0, 14.0), (50.0, 15.0, 15.0), (20.0, 14.0, 14.0), (-8.0, 10.0, 8.0)):
        c = (0.0, sternum_y, zc)
        paint_bone(layer, lambda X, Y, Z, c=c, w=half_w, h=half_h: elliptic_prism(X, Y, Z, c, w, 6.0, h),
                   *bounds([c], 30), 1.2, HU_CORTICAL, HU_TRABECULAR)
    for s in (-1, 1):
        clav = [(s * 20, sternum_y - 4, 128), (s * 70, sternum_y + 2, 140), (s * 120, sternum_y + 25, 150), (s * 150, sternum_y + 60, 155)]
        paint_tube(layer, clav, 7.0, HU_CORTICAL)
        paint_tube(layer, clav, 5.0, HU_TRABECULAR)
        c = (s * 100.0, 92.0, 95.0)
        R = rotation("y", -s * 10) @ rotation("z", -s * 28)
        paint_bone(layer, lambda X, Y, Z, c=c, R=R: ellipsoid(X, Y, Z, c, (45.0, 4.0, 70.0), R),
                   *bounds([c], 75), 1.2, HU_CORTICAL, HU_TRABECULAR)
        paint_tube(layer, [(s * 60, 108, 140), (s * 135, 88, 150)], 5.0, HU_CORTICAL)


# --- airways and pulmonary vessels ---

def _tree(rng, start, direction, radius, length, side, out, depth=0):
    """Grow a bifurcating tube tree from `start`, appending (p, q, r0, r1) segments to `out`."""
    direction = direction / np.linalg.norm(direction)
    end = start + direction * length
    if lung(*(np.float32(v) for v in end), side) > 0 or depth > 12:
        end = start + direction * length * 0.5
        out.append((start, end, radius, radius * 0.8))
        return
    out.append((start, end, radius, radius * 0.9))
    if radius < VESSEL_MIN_RADIUS_MM:
        return
    # Two children about 35 degrees apart in a random plane through the parent's axis.
    helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(direction, helper)
    u /= np.linalg.norm(u)
    w = np.cross(direction, u)
    phi = rng.uniform(0, 2 * np.pi)
    plane = np.cos(phi) * u + np.sin(phi) * w
    rng.uniform(0.45, 0.55)          # a draw kept so that each seed keeps the tree it always had
    for sign in (1, -1):
        angle = np.radians(rng.uniform(25, 42))
        child = np.cos(angle) * direction + sign * np.sin(angle) * plane
        r = radius * 2 ** (-1 / 3) * (1.0 + rng.uniform(-0.1, 0.1))
        _tree(rng, end, child, r, length * rng.uniform(0.72, 0.88), side, out, depth + 1)


def _lung_clip(side):
    return lambda X, Y, Z: lung(X, Y, Z, side) + 0.5


def _paint_lungs(layer: Layer, rng) -> None:
    for side in (-1, 1):
        layer.paint(lambda X, Y, Z, s=side: lung(X, Y, Z, s), 0.0, (-200, -150, -120), (200, 150, 200))
    # Aerated lung, denser toward the back; painted as an offset added in place.
    region = layer.grid.box((-200, -150, -120), (200, 150, 200))
    sl, X, Y, Z = region
    inside = np.clip(0.5 - np.minimum(lung(X, Y, Z, -1), lung(X, Y, Z, 1)) / layer.grid.spacing_mm, 0, 1)
    dependent = HU_LUNG + HU_LUNG_DEPENDENT_RISE * np.clip((Y + 100.0) / 200.0, 0, 1)
    v = layer.value[sl]
    v += inside * (dependent - v)
    # Pulmonary arteries and veins from each hilum toward the upper, middle and lower lung.
    for side in (-1, 1):
        hilum = np.array([side * 62.0, 10.0, 45.0])
        segments: list = []
        for target in ((side * 70, -40, 130), (side * 110, 20, 90), (side * 100, -60, 30), (side * 110, 40, 10),
                       (side * 80, 60, -20), (side * 120, -20, -10), (side * 60, 40, 120)):
            d = np.array(target, float) - hilum
            _tree(rng, hilum.copy(), d, 5.5, 0.32 * np.linalg.norm(d), side, segments)
        clip = _lung_clip(side)
        for p, q, r0, r1 in segments:
            paint_tube(layer, [p, q], [r0, r1], HU_BLOOD, clip=clip)
    # Trachea, carina and main bronchi: air with a soft-tissue wall.
    airway = [(0.0, 0.0, 200.0), (0.0, 8.0, 120.0), (0.0, 12.0, 75.0)]
    paint_tube(layer, airway, 11.0, HU_MUSCLE)
    paint_tube(layer, airway, 9.0, HU_AIR)
    for side in (-1, 1):
        bronchus = [(0.0, 12.0, 75.0), (side * 30.0, 14.0, 62.0), (side * 55.0, 16.0, 50.0 - 5 * (side > 0))]
        paint_tube(layer, bronchus, 7.5, HU_MUSCLE)
        paint_tube(layer, bronchus, 5.5, HU_AIR)
        lobar = [(side * 55.0, 16.0, 50.0), (side * 75.0, 22.0, 20.0)]
        paint_tube(layer, lobar, 5.0, HU_MUSCLE, clip=_lung_clip(side))
        paint_tube(layer, lobar, 3.5, HU_AIR, clip=_lung_clip(side))


# --- mediastinum and abdomen ---

def _paint_mediastinum(layer: Layer) -> None:
    heart_c = (22.0, -25.0, 5.0)
    R = rotation("y", -35) @ rotation("z", -20)
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, heart_c, (75.0, 58.0, 62.0), R), HU_FAT, *bounds([heart_c], 85))
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, heart_c, (70.0, 53.0, 57.0), R), HU_MYOCARDIUM, *bounds([heart_c], 80))
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, (heart_c[0] + 8, heart_c[1], heart_c[2] + 5), (50.0, 38.0, 42.0), R),
                HU_BLOOD, *bounds([heart_c], 70))
    # Aorta: ascending from the heart, the arch over the left bronchus, descending left of the spine.
    aorta = [(5.0, -20.0, 40.0), (2.0, -22.0, 85.0), (5.0, -5.0, 110.0), (22.0, 25.0, 105.0),
             (26.0, 40.0, 80.0), (22.0, 42.0, 0.0), (12.0, 32.0, -90.0), (5.0, 22.0, -200.0)]
    paint_tube(layer, aorta, (15.0, 15.0, 14.0, 13.0, 13.0, 12.0, 11.0, 10.0), HU_BLOOD)
    paint_tube(layer, [(-25.0, -15.0, 130.0), (-25.0, -12.0, 40.0)], 10.0, HU_BLOOD)      # superior vena cava
    paint_tube(layer, [(-5.0, -30.0, 35.0), (-12.0, 0.0, 60.0), (-55.0, 8.0, 47.0)], (14.0, 12.0, 9.0), HU_BLOOD)
    paint_tube(layer, [(-12.0, 0.0, 60.0), (12.0, 5.0, 65.0), (58.0, 10.0, 52.0)], (12.0, 11.0, 9.0), HU_BLOOD)
    paint_tube(layer, [(-20.0, 5.0, -200.0), (-22.0, 5.0, -30.0), (-18.0, 0.0, 0.0)], 13.0, HU_BLOOD)    # IVC
    paint_tube(layer, [(0.0, 20.0, 60.0), (12.0, 35.0, -50.0), (8.0, 30.0, -90.0)], 7.0, HU_MUSCLE)      # oesophagus


def _paint_abdomen(layer: Layer, rng) -> None:
    every = (-200, -150, -250), (200, 150, 100)
    below = lambda X, Y, Z, inset=0.0: intersect(cavity(X, Y, Z) + inset, Z - (diaphragm_z(X, Y) - inset))
    layer.paint(below, HU_BOWEL, *every)
    # The liver fills the right upper quadrant under the right dome, its lower edge rising to the left.
    layer.paint(lambda X, Y, Z: intersect(below(X, Y, Z, 4.0), X - 40.0 + 0.3 * (Y + 40), -140.0 - Z + 0.25 * (X + 100)),
                HU_LIVER, *every)
    spleen_c = (105.0, 45.0, -60.0)
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, spleen_c, (30.0, 55.0, 50.0), rotation("z", 35)), below(X, Y, Z, 3.0)),
                HU_SPLEEN, *bounds([spleen_c], 60))
    stomach_c = (60.0, -35.0, -60.0)
    Rs = rotation("y", 25)
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, stomach_c, (50.0, 40.0, 60.0), Rs), below(X, Y, Z, 3.0)),
                HU_MUSCLE, *bounds([stomach_c], 70))
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, stomach_c, (45.0, 35.0, 55.0), Rs), below(X, Y, Z, 7.0)),
                HU_FLUID, *bounds([stomach_c], 65))
    # The gas bubble of the fundus rises to the top (anterior, supine; superior on an erect film).
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, stomach_c, (45.0, 35.0, 55.0), Rs), below(X, Y, Z, 7.0),
                                          Y - (stomach_c[1] - 15.0)), HU_AIR, *bounds([stomach_c], 65))
    for s in (-1, 1):
        kc = (s * 75.0, 55.0, -165.0 + (10.0 if s > 0 else 0.0))
        layer.paint(lambda X, Y, Z, c=kc, s=s: ellipsoid(X, Y, Z, c, (28.0, 25.0, 55.0), rotation("y", s * 12)), HU_KIDNEY,
                    *bounds([kc], 60))
    # Colon: the hepatic and splenic flexures and transverse colon, with gas pockets.
    colon = [(-110.0, 10.0, -200.0), (-100.0, -20.0, -120.0), (-40.0, -60.0, -140.0),
             (40.0, -60.0, -130.0), (105.0, -10.0, -95.0), (115.0, 20.0, -200.0)]
    paint_tube(layer, colon, 24.0, HU_BOWEL, clip=lambda X, Y, Z: below(X, Y, Z, 2.0))
    pts = np.array(colon)
    for _ in range(18):
        k = rng.integers(0, len(pts) - 1)
        t = rng.uniform(0, 1)
        c = pts[k] + t * (pts[k + 1] - pts[k]) + rng.normal(0, 5, 3)
        radii = rng.uniform(8, 18, 3)
        layer.paint(lambda X, Y, Z, c=c, r=radii: intersect(ellipsoid(X, Y, Z, c, r), below(X, Y, Z, 4.0)),
                    HU_AIR, *bounds([c], 20))
    # Paraspinal muscles behind the spine, the whole height.
    for s in (-1, 1):
        c = (s * 35.0, 95.0, 0.0)
        layer.paint(lambda X, Y, Z, c=c: intersect(elliptic_prism(X, Y, Z, c, 32.0, 22.0, 300.0), skin(X, Y, Z, SKIN_MM + SUBCUT_FAT_MM)),
                    HU_MUSCLE, *bounds([c], 310))


def build_adult_chest(shape_zyx=(136, 512, 512), spacing_mm=(2.5, 0.8, 0.8), seed=0):
    """The adult chest CT on a grid of `shape_zyx` voxels of `spacing_mm` (z, y, x; mm).

    Returns (hu, spacing_mm, origin_mm): int16 HU indexed [z, y, x]; the spacing (z, y, x)
    as given; the LPS position (x, y, z; mm) of voxel [0, 0, 0]. The body is centred in the
    grid; `seed` picks the vessel branching, bowel gas and CT noise.
    """
    if len(shape_zyx) != 3 or min(shape_zyx) < 2:
        raise FluorosimError(f"adult chest: shape_zyx {tuple(shape_zyx)} must be three counts of at least 2 voxels")
    if len(spacing_mm) != 3 or min(spacing_mm) <= 0:
        raise FluorosimError(f"adult chest: spacing_mm {tuple(spacing_mm)} must be three positive sizes (mm)")
    rng = np.random.default_rng(seed)
    grid = AnisotropicGrid(shape_zyx, spacing_mm)
    layer = Layer(grid, HU_AIR)
    every = (-1e4, -1e4, -1e4), (1e4, 1e4, 1e4)
    _, X, Y, Z = grid.box(*every)
    outer = skin(X, Y, Z)
    layer.paint(lambda *box: outer, HU_SKIN, *every)
    layer.paint(lambda *box: outer + np.float32(SKIN_MM), HU_FAT, *every)
    layer.paint(lambda *box: outer + np.float32(SKIN_MM + SUBCUT_FAT_MM), HU_MUSCLE, *every)
    layer.paint(cavity, HU_MEDIASTINUM, *every)
    _paint_abdomen(layer, rng)
    _paint_lungs(layer, rng)
    _paint_mediastinum(layer)
    _paint_ribs_and_sternum(layer)
    _paint_spine(layer)
    hu = layer.value
    hu += rng.normal(0.0, HU_NOISE, hu.shape).astype(np.float32)
    out = np.clip(np.rint(hu), -1024, 3071).astype(np.int16)
    return out, tuple(float(s) for s in spacing_mm), tuple(float(o) for o in grid.origin_mm)


#: Demographics of the drawn patient, for the case profile's dose reports.
CASE_YAML = """\
# A synthetic adult chest and upper abdomen CT ({shape} voxels of {spacing} mm, z y x),
# drawn by appliance/patient/adult_chest.py with seed {seed}.
title: Adult chest - synthetic CT
description: Adult chest and upper abdomen; ribs, spine, lung vessels, heart, diaphragm.
phases:
  - volume: {volume}
    time_s: 0
at_end: hold
# The patient lies supine along the box: superior toward phantom +x, posterior toward the
# box floor (phantom -z), the patient's left toward phantom -y.
T_phantom_from_ct:
  - [0, 0, 1, 0]
  - [-1, 0, 0, 0]
  - [0, -1, 0, 0]
  - [0, 0, 0, 1]
materials:
  air_max_hu: -800
  bone_min_hu: 300
  bone_density_at_1000_hu_g_per_cm3: 1.6
patient:
  sex: M
  age_years: 45
  weight_kg: 80
  height_m: 1.78
"""

#: Grids the command writes: the clinical one, and a quick one for tests and benches.
SIZES = {"full": ((136, 512, 512), (2.5, 0.8, 0.8)), "small": ((68, 128, 128), (5.0, 3.2, 3.2))}


def write_adult_chest(out_dir: str | Path, size: str = "full", seed: int = 0, suffix: str = ".mha") -> Path:
    """Write the CT as `adult-chest<suffix>` (.mha, .nii or .nii.gz) and its case profile
    `adult-chest.yaml` into `out_dir`; returns the profile's path."""
    import SimpleITK as sitk

    shape, spacing = SIZES[size]
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FluorosimError(f"{out}: cannot create the folder ({e.strerror or e}); choose another --out") from None
    hu, spacing, origin = build_adult_chest(shape, spacing, seed)
    image = sitk.GetImageFromArray(hu)
    image.SetSpacing((spacing[2], spacing[1], spacing[0]))
    image.SetOrigin(origin)
    volume = out / f"adult-chest{suffix}"
    profile = out / "adult-chest.yaml"
    try:
        sitk.WriteImage(image, str(volume), True)
        profile.write_text(CASE_YAML.format(shape="x".join(map(str, shape)), spacing="/".join(map(str, spacing)),
                                            seed=seed, volume=volume.name))
    except (OSError, RuntimeError) as e:
        raise FluorosimError(f"{volume}: cannot write the CT ({str(e).strip().splitlines()[-1][:120]}); "
                             "check the folder and free space") from None
    return profile


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m appliance.patient.adult_chest", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, metavar="DIR", help="folder for adult-chest.mha and adult-chest.yaml")
    parser.add_argument("--size", choices=sorted(SIZES), default="full", help="full: 136x512x512 at 2.5/0.8/0.8 mm; small: 68x128x128")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--format", choices=(".mha", ".nii.gz", ".nii"), default=".mha")
    args = parser.parse_args(argv)
    try:
        print(write_adult_chest(args.out, args.size, args.seed, args.format))
    except FluorosimError as e:
        print(f"adult chest: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
