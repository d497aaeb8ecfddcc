"""The anatomy of the built-in child: a procedurally drawn torso and pelvis of a 5-8 year old.

The parts are drawn separately so that a 4D series costs little more than one volume:

- `static_soft`: skin, subcutaneous fat, muscle, the body cavities, paraspinal and psoas
  muscles, bowel — everything that does not move with the breath;
- the bones, `skeleton` (still) and `rib_cage` (one breathing state), are in `child_skeleton.py`;
- `paint_breathing`: lungs, diaphragm, heart, great vessels, airways, liver, spleen,
  stomach and kidneys for one breathing state (0 = end-expiration, 1 = end-inspiration);
- `paint_bladder`: bladder, urethra and filling catheter for one stage of the voiding
  cystourethrogram, returning the fraction of each voxel that the lumen fills.

Coordinates are the `ct` frame (LPS, mm): x toward the patient's left, y posterior, z
superior, the patient centred at the origin. Sizes are those of a 5-8 year old child
(Hounsfield units and the main dimensions are module constants below; smaller placements
sit where they are drawn); the random bowel gas and pulmonary vessels come from a fixed seed.
"""

from __future__ import annotations

import numpy as np

from .shapes import (
    Grid,
    Layer,
    bounds,
    ellipsoid,
    elliptic_prism,
    intersect,
    paint_tube,
    rotation,
    segment,
    smooth_min,
    union,
)

# --- Hounsfield units of the tissues (typical unenhanced CT values) ---
HU_AIR = -1000.0
HU_LUNG = -850.0
HU_FAT = -100.0
HU_VISCERAL_FAT = -90.0
HU_MEDIASTINUM = -40.0          # mediastinal fat with thymus and small vessels
HU_SKIN = 40.0
HU_MUSCLE = 40.0
HU_SOFT = 40.0
HU_BLOOD = 45.0
HU_LIVER = 60.0
HU_SPLEEN = 50.0
HU_KIDNEY = 35.0
HU_BOWEL = 25.0
HU_STOOL = -30.0
HU_FLUID = 10.0
HU_URINE = 0.0
HU_DISC = 80.0
HU_CARTILAGE = 120.0            # a child's costal cartilage is not yet calcified
HU_CORTICAL = 1500.0
HU_TRABECULAR = 350.0
HU_MARROW_SHAFT = 150.0         # red marrow in a child's long-bone shaft

# --- sizes (mm) ---
BODY_TOP_Z = 200.0
#: Torso cross-section by height: semi-axes a (left-right) and b (antero-posterior) and the
#: y of its centre. Widest 216 mm across the chest, at most 144 mm antero-posterior.
BODY_Z = np.array([-200, -170, -140, -110, -80, -40, 0, 40, 80, 120, 150, 165, 180, 190, 200], np.float32)
BODY_A = np.array([96, 104, 107, 104, 96, 92, 94, 100, 106, 108, 106, 100, 75, 48, 40], np.float32)
BODY_B = np.array([56, 62, 66, 67, 68, 69, 69, 69, 68, 66, 62, 58, 50, 40, 36], np.float32)
BODY_YC = np.array([4, 3, 2, 1, 0, -1, -2, -2, -1, 0, 2, 3, 6, 8, 10], np.float32)
SKIN_MM = 2.0
SUBCUT_FAT_MM = 7.0
#: Thickness of the body wall muscle under the fat, by height (thicker over the chest and
#: where the glutei and iliacus fill the pelvis).
_WALL_Z = np.array([-200, -150, -110, -60, 0, 40, 200], np.float32)
_WALL_MM = np.array([35, 30, 18, 9, 9, 14, 14], np.float32)
CAVITY_BOTTOM_Z = -178.0        # pelvic floor
CAVITY_TOP_Z = 182.0            # lung apices, above the clavicles as in a child

#: Diaphragm domes at end-expiration: right dome higher (the liver under it).
RIGHT_DOME = (-50.0, 5.0, 45.0)     # apex x, y, z (mm)
LEFT_DOME = (55.0, 5.0, 33.0)
DOME_DROP_MM = 45.0                 # how far the dome falls over DOME_RADIUS_MM from its apex
DOME_RADIUS_MM = 55.0
DIAPHRAGM_MM = 4.0
#: Craniocaudal excursion of the domes from end-expiration to end-inspiration in quiet
#: breathing of a school-age child (about 1-1.5 cm); the liver and spleen follow fully,
#: the kidneys and heart partly.
BREATH_AMPLITUDE_MM = 12.0
KIDNEY_MOTION = 0.6
#: Elevation of the sternum and the front of the ribs at end-inspiration (pump handle),
#: the second, independent breathing motion of the seed simulators.
RIB_LIFT_MM = 4.0
HEART_MOTION = 0.8

#: Bladder: the full bladder of a 7 year old holds about (age + 2) x 30 = 270 mL; the
#: neck sits behind the pubic symphysis and the bladder grows upward into the abdomen.
BLADDER_NECK = (0.0, -15.0, -150.0)
BLADDER_FULL_RADII = (45.0, 35.0, 38.0)     # 250.7 mL
BLADDER_WALL_MM = 3.0
#: Male urethra from the bladder neck: prostatic, membranous, bulbar, penile (mm), with the
#: lumen radius while voiding (the membranous part narrowest).
URETHRA_PATH = ((0, -15, -150), (0, -17, -162), (0, -20, -172), (0, -26, -180),
                (0, -36, -187), (0, -48, -192), (0, -58, -199.5))
URETHRA_RADII = (3.5, 4.0, 3.5, 2.5, 3.5, 3.0, 3.0)

#: The feeding tube a VCUG fills the bladder through: 8 French (2.7 mm), with a barium
#: stripe that makes it faintly radiopaque.
CATHETER_RADIUS_MM = 1.35
HU_CATHETER = 600.0

SEED = 20120504


def bladder_radii(volume_ml: float) -> np.ndarray:
    """Semi-axes (mm) of the bladder lumen holding `volume_ml`, the full shape scaled."""
    full = np.array(BLADDER_FULL_RADII)
    full_ml = 4.0 / 3.0 * np.pi * full.prod() / 1000.0
    return full * (volume_ml / full_ml) ** (1.0 / 3.0)


def _at(Z, knots, values):
    return np.interp(Z, knots, values).astype(np.float32)


#: Exponent of the superellipse of the trunk's cross-section: a child's back and flanks are
#: flatter than an ellipse.
BODY_POWER = 2.5


def _ellipse_xsec(X, Y, a, b, yc, p=BODY_POWER):
    """Distance (mm, approximate) to the superellipse of semi-axes a, b centred (0, yc) in each axial slice."""
    u, w = np.abs(X) / a, np.abs(Y - yc) / b
    rho = (u ** p + w ** p) ** (1.0 / p)
    # Scale by the local radius so the distance is in mm near the surface.
    return (rho - 1.0) * np.sqrt((a * u) ** 2 + (b * w) ** 2) / (rho + 1e-6)


def torso(X, Y, Z, inset=0.0):
    """The skin surface of the trunk and upper thighs, moved inward by `inset` (mm)."""
    a, b, yc = _at(Z, BODY_Z, BODY_A), _at(Z, BODY_Z, BODY_B), _at(Z, BODY_Z, BODY_YC)
    trunk = np.maximum(_ellipse_xsec(X, Y, a, b, yc), (-185.0 - Z) * np.float32(0.7))
    thighs = np.minimum(np.sqrt((X + 52) ** 2 + (Y - 2) ** 2), np.sqrt((X - 52) ** 2 + (Y - 2) ** 2)) - 50.0
    thighs = np.maximum(thighs, Z + 120.0)
    return smooth_min(trunk, thighs, 20.0) + np.float32(inset)


def cavity(X, Y, Z, inset=0.0):
    """The body cavity (thorax, abdomen, pelvis) inside the muscular wall."""
    a, b, yc = _at(Z, BODY_Z, BODY_A), _at(Z, BODY_Z, BODY_B), _at(Z, BODY_Z, BODY_YC)
    wall = SKIN_MM + SUBCUT_FAT_MM + _at(Z, _WALL_Z, _WALL_MM) + np.float32(inset)
    d = _ellipse_xsec(X, Y, a - wall, b - wall, yc)
    # Domed lung apices rather than a flat roof.
    top = CAVITY_TOP_Z - 45.0 * (X / 85.0) ** 2 - 20.0 * ((Y - 10.0) / 60.0) ** 2
    return intersect(d, CAVITY_BOTTOM_Z - Z, Z - top)


# --- soft tissue that does not move with the breath ---

def static_soft(grid: Grid, rng: np.random.Generator) -> Layer:
    layer = Layer(grid, HU_AIR)
    everywhere = ((-1e4, -1e4, -1e4), (1e4, 1e4, 1e4))
    skin = torso(*grid.box(*everywhere)[1:])     # once: fat and muscle are the same surface moved in
    layer.paint(lambda *box: skin, HU_SKIN, *everywhere)
    layer.paint(lambda *box: skin + np.float32(SKIN_MM), HU_FAT, *everywhere)
    layer.paint(lambda *box: skin + np.float32(SKIN_MM + SUBCUT_FAT_MM), HU_MUSCLE, *everywhere)
    layer.paint(cavity, HU_VISCERAL_FAT, *everywhere)
    # Paraspinal muscles behind the spine, psoas muscles beside the lumbar spine.
    for s in (-1, 1):
        c = (s * 22.0, 52.0, 30.0)
        layer.paint(lambda X, Y, Z, c=c: elliptic_prism(X, Y, Z, c, 22.0, 15.0, 150.0), HU_MUSCLE,
                    *bounds([c], 160))
        paint_tube(layer, [(s * 16, 24, 5), (s * 28, 20, -40), (s * 40, 8, -100), (s * 48, -8, -150)],
                   (5.0, 12.0, 17.0, 13.0), HU_MUSCLE)
    # Penis (the male urethra runs through it); the rest of the perineum is the torso.
    paint_tube(layer, [(0, -42, -182), (0, -52, -192), (0, -60, -202)], (10.0, 9.0, 9.0), HU_SOFT)
    _paint_bowel(layer, rng)
    return layer


#: Colon centreline (mm): caecum, ascending, hepatic flexure, transverse (anterior, sagging),
#: splenic flexure, descending, sigmoid, rectum.
COLON = ((-58, -5, -100), (-62, 5, -60), (-60, 0, -25), (-50, -25, -12), (-20, -45, -35),
         (20, -45, -32), (58, -25, -5), (72, 10, -20), (74, 12, -65), (60, 0, -105),
         (30, -5, -118), (8, 20, -122), (0, 42, -135), (0, 44, -160), (0, 38, -185))
GASSY_COLON_SEGMENTS = (3, 4, 5)        # transverse colon: gas rises anteriorly in a supine child


def _paint_bowel(layer: Layer, rng: np.random.Generator) -> None:
    # Small bowel: a mass of loops filling the mid-abdomen with scattered gas.
    c = (0.0, -18.0, -60.0)
    layer.paint(lambda X, Y, Z: np.maximum(ellipsoid(X, Y, Z, c, (55.0, 30.0, 42.0)), cavity(X, Y, Z, 3.0)),
                HU_BOWEL, *bounds([c], 60))
    for _ in range(40):
        p = np.array(c) + rng.uniform(-1, 1, 3) * [48, 24, 36]
        r = rng.uniform(2.5, 6.0, 3)
        R = rotation("z", rng.uniform(0, 180)) @ rotation("x", rng.uniform(0, 180))
        layer.paint(lambda X, Y, Z, p=p, r=r, R=R: np.maximum(ellipsoid(X, Y, Z, p, r, R), cavity(X, Y, Z, 4.0)),
                    HU_AIR, *bounds([p], r.max() + 3))
    colon = np.array(COLON, float)
    inside = lambda X, Y, Z: cavity(X, Y, Z, 1.0)
    paint_tube(layer, colon, 14.0, HU_BOWEL, clip=inside)
    paint_tube(layer, colon, 11.0, HU_STOOL, clip=inside)
    for k in GASSY_COLON_SEGMENTS:
        paint_tube(layer, colon[k:k + 2], 11.0, HU_AIR, clip=inside)
    # Gas bubbles mottling the stool.
    for k in range(len(colon) - 1):
        for _ in range(3):
            along = rng.uniform(0, 1)
            p = colon[k] + along * (colon[k + 1] - colon[k]) + rng.uniform(-5, 5, 3)
            bubble_r = float(rng.uniform(3.0, 7.0))
            layer.paint(lambda X, Y, Z, p=p, r=bubble_r: np.maximum(ellipsoid(X, Y, Z, p, (r, r, r)), inside(X, Y, Z)),
                        HU_AIR, *bounds([p], bubble_r + 3))


# --- breathing ---

def dome_z(X, Y, shift):
    """Height (mm) of the diaphragm surface above (x, y), moved down by `shift` mm."""
    def one(apex):
        q = ((X - apex[0]) ** 2 + (Y - apex[1]) ** 2) / np.float32(DOME_RADIUS_MM ** 2)
        return apex[2] - DOME_DROP_MM * q
    right, left = one(RIGHT_DOME), one(LEFT_DOME)
    return -smooth_min(-right, -left, 10.0) - np.float32(shift)


def heart_centre(shift):
    return (18.0, -14.0, 50.0 - HEART_MOTION * shift)


def _heart(X, Y, Z, shift):
    return ellipsoid(X, Y, Z, heart_centre(shift), (44.0, 32.0, 36.0), rotation("y", 35) @ rotation("z", -25))


def _mediastinum(X, Y, Z, shift):
    """Heart, the superior mediastinum and the spine with its muscles: what the lungs wrap round."""
    superior = elliptic_prism(X, Y, Z, (0.0, -8.0, 150.0), 17.0, 42.0, 60.0)
    spine = elliptic_prism(X, Y, Z, (0.0, 32.0, 40.0), 24.0, 22.0, 180.0)
    fat_pad = ellipsoid(X, Y, Z, (8.0, -12.0, 20.0 - shift), (38.0, 30.0, 22.0))
    return union(_heart(X, Y, Z, shift) - 4.0, superior, spine, fat_pad)


def lungs(X, Y, Z, shift):
    return intersect(*[cavity(X, Y, Z), dome_z(X, Y, shift) - Z, -_mediastinum(X, Y, Z, shift)])


def paint_breathing(layer: Layer, breath: float, rng_seed: int = SEED) -> None:
    """Draw the organs that move with the breath; `breath` 0 = end-expiration, 1 = end-inspiration."""
    shift = BREATH_AMPLITUDE_MM * breath
    thorax_lo, thorax_hi = (-120, -90, -40), (120, 90, 190)
    layer.paint(lambda X, Y, Z: np.maximum(cavity(X, Y, Z), dome_z(X, Y, shift) - Z), HU_MEDIASTINUM, thorax_lo, thorax_hi)
    layer.paint(lambda X, Y, Z: lungs(X, Y, Z, shift), HU_LUNG, thorax_lo, thorax_hi)
    _paint_lung_vessels(layer, shift, np.random.default_rng(rng_seed + 1))
    c = heart_centre(shift)
    layer.paint(lambda X, Y, Z: _heart(X, Y, Z, shift), HU_BLOOD, *bounds([c], 50))
    # Aorta: ascending, arch, descending beside the spine down to its bifurcation; IVC.
    paint_tube(layer, [(6, -20, c[2] + 20), (4, -14, 128), (10, 5, 134), (14, 14, 118), (12, 8, 40),
                       (6, 2, -20), (3, 0, -75)], 6.5, HU_BLOOD)
    paint_tube(layer, [(-18, 0, -80), (-20, 5, -20), (-22, 0, 30 - shift), (-14, -10, c[2] - 15)], 8.0, HU_BLOOD)
    # Airway: trachea to the carina, main bronchi.
    carina = (0.0, 8.0, 122.0)
    paint_tube(layer, [(0, -5, 205), (0, 2, 160), carina], 6.0, HU_AIR)
    paint_tube(layer, [carina, (-25, 12, 106)], 4.5, HU_AIR)
    paint_tube(layer, [carina, (24, 12, 100)], 4.0, HU_AIR)
    # Diaphragm: a muscular sheet under the lungs.
    layer.paint(lambda X, Y, Z: np.maximum(cavity(X, Y, Z), np.abs(Z - dome_z(X, Y, shift) + DIAPHRAGM_MM / 2) - DIAPHRAGM_MM / 2),
                HU_MUSCLE, (-120, -90, -40), (120, 90, 60))
    below = lambda X, Y, Z: Z - dome_z(X, Y, shift) + DIAPHRAGM_MM

    def organ(centre, radii, R=None):
        return lambda X, Y, Z: intersect(*[ellipsoid(X, Y, Z, centre, radii, R), below(X, Y, Z), cavity(X, Y, Z, 1.0)])
    liver_c = (-32.0, 0.0, 0.0 - shift)
    layer.paint(organ(liver_c, (84.0, 70.0, 70.0), rotation("y", 18)), HU_LIVER, *bounds([liver_c], 90))
    stomach_c = (40.0, -14.0, 6.0 - shift)
    stomach_R = rotation("y", -20)
    layer.paint(organ(stomach_c, (32.0, 26.0, 38.0), stomach_R), HU_SOFT, *bounds([stomach_c], 45))
    layer.paint(organ(stomach_c, (28.0, 22.0, 34.0), stomach_R), HU_FLUID, *bounds([stomach_c], 45))
    # Supine: the gastric gas bubble lies anteriorly, above an air-fluid level.
    layer.paint(lambda X, Y, Z: np.maximum(organ(stomach_c, (28.0, 22.0, 34.0), stomach_R)(X, Y, Z), Y - (stomach_c[1] - 8.0)),
                HU_AIR, *bounds([stomach_c], 45))
    for s, z0 in ((-1, -35.0), (1, -24.0)):
        kc = (s * 42.0, 30.0, z0 - KIDNEY_MOTION * shift)
        R = rotation("z", -s * 30) @ rotation("y", s * 12)
        layer.paint(lambda X, Y, Z, kc=kc, R=R: ellipsoid(X, Y, Z, kc, (26.0, 22.0, 49.0), R), HU_FAT, *bounds([kc], 55))
        layer.paint(lambda X, Y, Z, kc=kc, R=R: ellipsoid(X, Y, Z, kc, (20.0, 16.0, 43.0), R), HU_KIDNEY, *bounds([kc], 50))
        sinus = (kc[0] - s * 8.0, kc[1] - 2.0, kc[2])
        layer.paint(lambda X, Y, Z, c=sinus, R=R: ellipsoid(X, Y, Z, c, (7.0, 7.0, 22.0), R), HU_VISCERAL_FAT, *bounds([sinus], 25))
        paint_tube(layer, [(kc[0] - s * 18, kc[1] - 4, kc[2]), (s * 30, 15, -70), (s * 28, 10, -120), (s * 14, 8, -150)],
                   2.0, HU_SOFT)
    # Spleen: posterolateral under the left dome, along the 9th-11th ribs.
    spleen_c = (64.0, 18.0, 10.0 - shift)
    layer.paint(organ(spleen_c, (16.0, 34.0, 42.0), rotation("z", -45)), HU_SPLEEN, *bounds([spleen_c], 50))


def _paint_lung_vessels(layer: Layer, shift: float, rng: np.random.Generator) -> None:
    """Branching pulmonary vessels from each hilum, clipped to the lungs: the lung markings."""
    inside = lambda X, Y, Z: lungs(X, Y, Z, shift) + 1.0
    for s in (-1, 1):
        hilum = np.array([s * 30.0, 5.0, 105.0])
        stack = [(hilum, np.array([s, 0.0, 0.0]), 5.0, 0)]
        while stack:
            p, direction, radius, depth = stack.pop()
            for _ in range(2 if depth else 4):
                d = direction + rng.normal(0, 0.6, 3) * [0.5, 0.8, 1.4] + (0 if depth else [0, 0, rng.choice([-1.2, 1.0])])
                d = d / np.linalg.norm(d)
                length = rng.uniform(25, 40) * (0.75 ** depth)
                q = p + d * length
                paint_tube(layer, [p, q], (radius, radius * 0.7), HU_BLOOD, clip=inside)
                if depth < 3:
                    stack.append((q, d, radius * 0.7, depth + 1))


# --- the voiding cystourethrogram ---

def paint_bladder(layer: Layer, volume_ml: float, urethra_open: bool,
                  catheter: bool = False) -> tuple[tuple[slice, slice, slice], np.ndarray]:
    """Draw the bladder holding `volume_ml`, while voiding the distended urethra, and the
    filling catheter (8 Fr, radiopaque) up the urethra into the bladder when `catheter`.

    Returns the slices of a box of the grid and the fraction (0-1) of each voxel of it that
    the lumen (urine or contrast) fills, for the caller to mark contrast.
    """
    grid = layer.grid
    radii = bladder_radii(volume_ml)
    centre = np.array(BLADDER_NECK) + [0.0, 0.0, radii[2]]
    reach = radii + BLADDER_WALL_MM + 2 * grid.spacing_mm
    # One box round the bladder and the urethra below it; the tubes only in their own part.
    path = np.array(URETHRA_PATH, float)
    tube_lo, tube_hi = bounds(path, 6.0)
    # The catheter runs up the urethra and 18 mm into the bladder.
    tip = np.array([*URETHRA_PATH[::-1], (0.0, -15.0, -132.0)], float)
    cath_lo, cath_hi = bounds(tip, 4.0)
    lo = np.minimum.reduce([centre - reach, tube_lo, cath_lo])
    hi = np.maximum.reduce([centre + reach, tube_hi, cath_hi])
    sl, X, Y, Z = grid.box(lo, hi)
    wall = ellipsoid(X, Y, Z, centre, radii + BLADDER_WALL_MM)
    lumen = ellipsoid(X, Y, Z, centre, radii)
    sub = grid.box(tube_lo, tube_hi)[0]
    inner = tuple(slice(t.start - b.start, t.stop - b.start) for t, b in zip(sub, sl))
    Xt, Yt, Zt = X[..., inner[2]], Y[:, inner[1], :], Z[inner[0]]
    if urethra_open:
        rads = np.array(URETHRA_RADII, float)
        tube = union(*[segment(Xt, Yt, Zt, p, q, r0, r1) for p, q, r0, r1 in zip(path[:-1], path[1:], rads[:-1], rads[1:])])
        wall[inner] = np.minimum(wall[inner], tube - 1.5)
        lumen[inner] = np.minimum(lumen[inner], tube)
    v = layer.value[sl]
    a = layer.coverage(wall)
    v += a * (np.float32(HU_SOFT) - v)
    fill = layer.coverage(lumen)
    v += fill * (np.float32(HU_URINE) - v)
    if catheter:
        region = grid.box(cath_lo, cath_hi)[0]
        inner = tuple(slice(t.start - b.start, t.stop - b.start) for t, b in zip(region, sl))
        Xc, Yc, Zc = X[..., inner[2]], Y[:, inner[1], :], Z[inner[0]]
        tube = union(*[segment(Xc, Yc, Zc, p, q, CATHETER_RADIUS_MM, CATHETER_RADIUS_MM) for p, q in zip(tip[:-1], tip[1:])])
        a = layer.coverage(tube)
        vc = v[inner]
        vc += a * (np.float32(HU_CATHETER) - vc)
        fill[inner] *= 1.0 - a
    return sl, fill
