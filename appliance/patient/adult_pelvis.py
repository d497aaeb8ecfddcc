"""A synthetic adult abdomen and pelvis CT, in Hounsfield units, as a clinical scanner writes it.

A real abdomen-pelvis CT holds what the synthetic chest lacks, each of which can break the
display chain: the lumbar spine, sacrum, iliac wings and femoral heads (dense bone over
much of an AP field); bowel gas in loops of many sizes (large dark areas inside soft
tissue); thick fat (-100 HU) round the muscles; a fluid-filled bladder; the CT table under
the patient (a curved carbon-fibre shell over a foam core, in the beam of an AP view);
and the reconstruction circle: voxels outside the scan's field of view hold the padding
value (PixelPaddingValue, -3024 HU here), and the arms beside a large patient's body are
cut off at the circle's edge.

This draws an 85 kg man from L1 down to the lesser trochanters, on the tissue values of
`adult_body.py` and the painting helpers of `shapes.py`. Coordinates are the `ct` frame
(LPS, mm): x toward the patient's left, y posterior, z superior; the grid is centred on
the origin, which is the centre of the reconstruction circle.
"""

from __future__ import annotations

import numpy as np

from .adult_body import (
    HU_AIR,
    HU_BLOOD,
    HU_BOWEL,
    HU_CORTICAL,
    HU_CSF,
    HU_DISC,
    HU_FAT,
    HU_FLUID,
    HU_KIDNEY,
    HU_LIVER,
    HU_MUSCLE,
    HU_NOISE,
    HU_SKIN,
    HU_TRABECULAR,
    AnisotropicGrid,
    superellipse,
)
from .shapes import Layer, bounds, ellipsoid, elliptic_prism, intersect, paint_bone, paint_tube, rotation

#: Voxels outside the reconstruction circle: the padding value GE and Siemens scanners
#: write (PixelPaddingValue -3024 HU, i.e. stored 0 with rescale intercept -3024).
HU_PADDING = -3024
#: The CT couch: a carbon-fibre shell (about 1.5 g/cm^3; carbon attenuates like soft tissue
#: per gram, so kept under the bone threshold) over a foam core (about 0.1 g/cm^3).
HU_TABLE_SHELL = 250.0
HU_TABLE_CORE = -900.0
TABLE_SHELL_MM = 3.0
TABLE_CORE_MM = 40.0
TABLE_HALF_WIDTH_MM = 225.0     # a 450 mm couch: wider than the 410 mm circle, so the circle cuts it
TABLE_CURVE_MM = 700.0          # radius of the couch's cross-section (a shallow cradle)

# --- the trunk (mm) by height z: semi-axes a (left-right), b (antero-posterior) ---
#: A large adult: 360 mm across the upper abdomen, 390 mm over the hips, 250-260 mm deep.
TRUNK_Z = np.array([-170, -120, -80, -30, 20, 80, 170], np.float32)
TRUNK_A = np.array([182, 195, 192, 180, 176, 178, 180], np.float32)
TRUNK_B = np.array([118, 122, 124, 126, 128, 128, 126], np.float32)
SKIN_MM = 2.0
SUBCUT_FAT_MM = 28.0
WALL_MM = 12.0                  # abdominal wall muscle
BACK_Y = 126.0                  # the patient's back rests on the couch here
#: Arms beside the body, cut by the reconstruction circle: centre x (mm), semi-axes (mm).
ARM_X, ARM_A, ARM_B = 238.0, 42.0, 48.0

#: Lumbar vertebrae L1-L5 from L1's top down: height, disc below, half-width, half-depth (mm).
L1_TOP_Z = 165.0
LUMBAR = ((27.0, 10.0, 25.0, 18.0), (28.0, 10.0, 26.0, 18.5), (29.0, 11.0, 27.0, 19.0),
          (29.0, 11.0, 28.0, 19.0), (28.0, 10.0, 28.0, 18.0))
SPINE_Y = 40.0                  # y of the vertebral body centres (mm), lordosis added by height


def _trunk(X, Y, Z, inset=0.0):
    a = np.interp(Z, TRUNK_Z, TRUNK_A).astype(np.float32) - inset
    b = np.interp(Z, TRUNK_Z, TRUNK_B).astype(np.float32) - inset
    return superellipse(X, Y, a, b, np.float32(BACK_Y) - b - np.float32(inset))


def _spine_y(z):
    """Vertebral body centres: lumbar lordosis, most anterior at L4 (z about 20)."""
    return SPINE_Y - 12.0 * np.exp(-((z - 20.0) / 90.0) ** 2)


def _lumbar_levels():
    """(centre z, height, disc below, half-width, half-depth) of L1-L5, mm."""
    out, top = [], L1_TOP_Z
    for h, disc, a, b in LUMBAR:
        out.append((top - h / 2, h, disc, a, b))
        top -= h + disc
    return out


def _paint_lumbar_spine(layer: Layer) -> None:
    """L1-L5: cortex, cancellous body, disc, pedicles, laminae, transverse and spinous
    processes, canal."""
    for zc, h, disc, a, b in _lumbar_levels():
        y = float(_spine_y(zc))
        c = (0.0, y, zc)
        paint_bone(layer, lambda X, Y, Z, c=c, a=a, b=b, h=h: elliptic_prism(X, Y, Z, c, a, b, h / 2, power=2.2),
                   *bounds([c], max(a, b, h) + 3), 1.2, HU_CORTICAL, HU_TRABECULAR)
        dc = (0.0, y, zc - h / 2 - disc / 2)
        layer.paint(lambda X, Y, Z, c=dc, a=a, b=b, d=disc: elliptic_prism(X, Y, Z, c, a - 0.5, b - 0.5, d / 2 + 0.3, power=2.2),
                    HU_DISC, *bounds([dc], max(a, b) + 3))
        back = y + b
        for s in (-1, 1):
            ped = (s * 0.6 * a, back + 9, zc + 1)
            for path, r in (([(s * 0.5 * a, y + 0.6 * b, zc + 1), ped], 5.0), ([ped, (0.0, back + 22, zc - 3)], 4.5),
                            ([ped, (s * (a + 32), back + 6, zc + 2)], 4.5)):
                paint_tube(layer, path, r, HU_CORTICAL * 0.7)
        paint_tube(layer, [(0.0, back + 22, zc - 3), (0.0, back + 48, zc - 14)], (6.0, 4.0), HU_CORTICAL * 0.7)
        canal = (0.0, back + 9, zc)
        layer.paint(lambda X, Y, Z, c=canal, hh=(h + disc) / 2: elliptic_prism(X, Y, Z, c, 11.0, 8.0, hh),
                    HU_CSF, *bounds([canal], 12 + h))


def _paint_pelvis(layer: Layer, s1_top_z: float) -> None:
    """Sacrum, iliac wings, acetabula, femoral heads and necks, pubic and ischial rami."""
    # The sacrum: a wedge tilted back, S1 under L5 down to the coccyx.
    sacrum = [(0.0, float(_spine_y(s1_top_z)) + 8, s1_top_z - 15), (0.0, 75.0, -60.0), (0.0, 95.0, -110.0), (0.0, 100.0, -140.0)]
    for hu, inset in ((HU_CORTICAL, 0.0), (HU_TRABECULAR, 1.5)):
        paint_tube(layer, sacrum, np.array([22.0, 18.0, 11.0, 6.0]) - inset, hu)
        for s in (-1, 1):       # the alae, reaching out to the sacro-iliac joints
            paint_tube(layer, [(0.0, 60.0, s1_top_z - 22), (s * 48.0, 70.0, s1_top_z - 30), (s * 62.0, 80.0, -70.0)],
                       np.array([16.0, 14.0, 10.0]) - inset, hu)
    for s in (-1, 1):
        # Iliac wing: a thin curved plate from the crest (L4-L5) down to the acetabulum,
        # flaring forward and outward; a thin shell of cortex over cancellous bone.
        wing = (s * 100.0, 40.0, -40.0)
        R = rotation("z", -s * 50) @ rotation("x", -10)
        paint_bone(layer, lambda X, Y, Z, c=wing, R=R: ellipsoid(X, Y, Z, c, (72.0, 9.0, 60.0), R),
                   *bounds([wing], 80), 1.5, HU_CORTICAL, HU_TRABECULAR)
        acetabulum = (s * 92.0, 15.0, -120.0)     # the femoral head's centre, in its socket
        femur = [(s * 120.0, 20.0, -140.0), (s * 140.0, 25.0, -150.0), (s * 135.0, 20.0, -200.0)]
        for hu, inset in ((HU_CORTICAL, 0.0), (HU_TRABECULAR, 3.0)):
            paint_tube(layer, [acetabulum] + femur, np.array([12.0, 17.0, 20.0, 15.0]) - inset, hu)
            # Superior pubic ramus to the symphysis, inferior ramus and ischium behind it.
            paint_tube(layer, [acetabulum, (s * 45.0, -45.0, -125.0), (s * 8.0, -62.0, -135.0)], np.array([13.0, 10.0, 9.0]) - inset, hu)
            paint_tube(layer, [(s * 8.0, -62.0, -140.0), (s * 40.0, -30.0, -165.0), (s * 70.0, 25.0, -160.0), acetabulum],
                       np.array([8.0, 8.0, 12.0, 14.0]) - inset * 0.7, hu)
        # The acetabular roof over the head, then the head itself.
        roof = (s * 88.0, 18.0, -108.0)
        paint_bone(layer, lambda X, Y, Z, c=roof: ellipsoid(X, Y, Z, c, (32.0, 30.0, 22.0)),
                   *bounds([roof], 36), 2.5, HU_CORTICAL, HU_TRABECULAR)
        paint_bone(layer, lambda X, Y, Z, c=acetabulum: ellipsoid(X, Y, Z, c, (24.0, 24.0, 24.0)),
                   *bounds([acetabulum], 30), 1.5, HU_CORTICAL, HU_TRABECULAR)


def _paint_soft_tissue(layer: Layer, rng) -> None:
    every = (-1e4, -1e4, -1e4), (1e4, 1e4, 1e4)
    cavity = lambda X, Y, Z: _trunk(X, Y, Z, SKIN_MM + SUBCUT_FAT_MM + WALL_MM)
    layer.paint(cavity, HU_FAT, *every)           # retroperitoneal and mesenteric fat
    for s in (-1, 1):
        # Psoas from L1 to the groin, growing downward; iliacus inside each iliac wing;
        # paraspinal and gluteal muscle behind.
        paint_tube(layer, [(s * 30.0, 40.0, 160.0), (s * 45.0, 30.0, 40.0), (s * 65.0, 20.0, -60.0), (s * 85.0, -15.0, -150.0)],
                   (10.0, 22.0, 26.0, 20.0), HU_MUSCLE)
        paint_tube(layer, [(s * 95.0, 30.0, -30.0), (s * 95.0, 10.0, -100.0)], (22.0, 18.0), HU_MUSCLE)
        paint_tube(layer, [(s * 42.0, 95.0, 170.0), (s * 40.0, 100.0, -40.0)], (30.0, 24.0), HU_MUSCLE)
        paint_tube(layer, [(s * 100.0, 85.0, -40.0), (s * 120.0, 70.0, -150.0)], (35.0, 40.0), HU_MUSCLE)
        # Lower poles of the kidneys and, on the right, the tip of the liver.
        kc = (s * 78.0, 55.0, 150.0 + (8.0 if s > 0 else 0.0))
        layer.paint(lambda X, Y, Z, c=kc, s=s: ellipsoid(X, Y, Z, c, (27.0, 24.0, 50.0), rotation("y", s * 12)), HU_KIDNEY,
                    *bounds([kc], 55))
    layer.paint(lambda X, Y, Z: intersect(ellipsoid(X, Y, Z, (-95.0, -10.0, 175.0), (70.0, 80.0, 45.0)), cavity(X, Y, Z) + 3),
                HU_LIVER, *bounds([(-95.0, -10.0, 175.0)], 90))
    # Aorta and IVC to their bifurcation at L4, then the common and external iliac vessels.
    l4 = _lumbar_levels()[3][0]
    for x0, r in ((12.0, 11.0), (-20.0, 12.0)):
        paint_tube(layer, [(x0, 10.0, 170.0), (x0 * 0.5, 5.0, l4)], r, HU_BLOOD)
        for s in (-1, 1):
            paint_tube(layer, [(x0 * 0.5, 5.0, l4), (s * 45.0, 20.0, -40.0), (s * 80.0, -10.0, -110.0), (s * 85.0, -25.0, -170.0)],
                       r * 0.7, HU_BLOOD)
    # The bladder, fluid-filled, behind the symphysis.
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, (0.0, -35.0, -100.0), (50.0, 38.0, 40.0)), HU_MUSCLE, *bounds([(0, -35, -100)], 55))
    layer.paint(lambda X, Y, Z: ellipsoid(X, Y, Z, (0.0, -35.0, -100.0), (46.0, 34.0, 36.0)), HU_FLUID, *bounds([(0, -35, -100)], 50))
    _paint_bowel(layer, rng, cavity)


def _paint_bowel(layer: Layer, rng, cavity) -> None:
    """Colon round the frame of the abdomen, sigmoid and rectum; small-bowel loops in the
    middle; gas in pockets from a few mm to large distended segments."""
    clip = lambda X, Y, Z: cavity(X, Y, Z) + 3.0
    colon = [(-115.0, -10.0, 175.0), (-120.0, 0.0, 40.0), (-115.0, -5.0, -40.0), (-105.0, -30.0, -60.0)]  # ascending, caecum
    descending = [(120.0, 10.0, 175.0), (125.0, 15.0, 40.0), (110.0, 10.0, -40.0), (50.0, -20.0, -70.0),
                  (15.0, 40.0, -95.0), (0.0, 75.0, -130.0), (0.0, 70.0, -165.0)]        # sigmoid and rectum
    loops = [np.array([0.0, -40.0, 120.0])]
    for _ in range(22):            # small bowel: a random walk kept in the middle abdomen
        step = rng.normal(0, 1, 3) * [30.0, 12.0, 30.0]
        p = np.clip(loops[-1] + step, [-80, -80, -50], [80, 10, 140])
        loops.append(p)
    for path, r in ((colon, 26.0), (descending, 22.0), (loops, 14.0)):
        paint_tube(layer, path, r, HU_BOWEL, clip=clip)
        paint_tube(layer, path, r - 3.0, HU_FLUID, clip=clip)
        pts = np.array(path)
        for _ in range(len(path) * 3):
            k = rng.integers(0, len(pts) - 1)
            c = pts[k] + rng.uniform(0, 1) * (pts[k + 1] - pts[k])
            radii = rng.uniform(0.25, 1.0, 3) * (r - 3.0) * [1.0, 1.0, 2.0]
            layer.paint(lambda X, Y, Z, c=c, r=radii: intersect(ellipsoid(X, Y, Z, c, r), clip(X, Y, Z)), HU_AIR,
                        *bounds([c], float(radii.max()) + 3))


def _paint_table(layer: Layer) -> None:
    """The couch under the patient: shell, core, shell, curving up at its edges."""
    every = (-TABLE_HALF_WIDTH_MM, BACK_Y - 5, -1e4), (TABLE_HALF_WIDTH_MM, BACK_Y + 120, 1e4)
    depth = lambda X, Y: Y - (BACK_Y + 1.0) + X * X / (2 * TABLE_CURVE_MM)       # mm below the couch's top
    width = lambda X: np.abs(X) - TABLE_HALF_WIDTH_MM
    thick = 2 * TABLE_SHELL_MM + TABLE_CORE_MM
    # The couch is the same at every z: `0 * Z` spreads its (y, x) distance over the box's slices.
    layer.paint(lambda X, Y, Z: intersect(-depth(X, Y), depth(X, Y) - thick, width(X)) + 0 * Z, HU_TABLE_SHELL, *every)
    layer.paint(lambda X, Y, Z: intersect(TABLE_SHELL_MM - depth(X, Y), depth(X, Y) - thick + TABLE_SHELL_MM,
                                          width(X) + TABLE_SHELL_MM) + 0 * Z, HU_TABLE_CORE, *every)


def build_adult_pelvis(shape_zyx=(130, 512, 512), spacing_mm=(2.5, 0.8, 0.8), seed=0, ct_noise=True):
    """The abdomen-pelvis CT on a grid of `shape_zyx` voxels of `spacing_mm` (z, y, x; mm),
    centred on the reconstruction circle, which is the in-plane grid's inscribed circle.

    Returns (hu, spacing_mm, origin_mm) as `adult_chest.build_adult_chest` does: int16 HU
    [z, y, x], HU_PADDING outside the circle; `seed` draws the bowel and the CT noise.
    """
    rng = np.random.default_rng(seed)
    grid = AnisotropicGrid(shape_zyx, spacing_mm, "adult pelvis")
    layer = Layer(grid, HU_AIR)
    every = (-1e4, -1e4, -1e4), (1e4, 1e4, 1e4)
    for s in (-1, 1):       # the arms first, so the trunk's skin covers where they touch
        layer.paint(lambda X, Y, Z, s=s: elliptic_prism(X, Y, Z, (s * ARM_X, 20.0, 0.0), ARM_A, ARM_B, 1e4), HU_MUSCLE, *every)
        paint_tube(layer, [(s * ARM_X, 25.0, -1e3), (s * ARM_X, 25.0, 1e3)], 11.0, HU_CORTICAL)
    _, X, Y, Z = grid.box(*every)
    outer = _trunk(X, Y, Z)
    layer.paint(lambda *box: outer, HU_SKIN, *every)
    layer.paint(lambda *box: outer + np.float32(SKIN_MM), HU_FAT, *every)
    layer.paint(lambda *box: outer + np.float32(SKIN_MM + SUBCUT_FAT_MM), HU_MUSCLE, *every)
    _paint_soft_tissue(layer, rng)
    _paint_lumbar_spine(layer)        # over the psoas and vessels it lies among
    zc, h, disc, _, _ = _lumbar_levels()[-1]
    s1_top = zc - h / 2 - disc
    _paint_pelvis(layer, s1_top)
    _paint_table(layer)
    hu = layer.value
    if ct_noise:
        hu += rng.normal(0.0, HU_NOISE, hu.shape).astype(np.float32)
    out = np.clip(np.rint(hu), -1024, 3071).astype(np.int16)
    radius = min(grid.shape[1] * grid.spacing_xyz[1], grid.shape[2] * grid.spacing_xyz[0]) / 2
    out[:, (Y[0] ** 2 + X[0] ** 2) > radius ** 2] = HU_PADDING
    return out, tuple(float(s) for s in spacing_mm), tuple(float(o) for o in grid.origin_mm)


#: Grids: the clinical one (512 x 512, 0.8 mm pixels, 2.5 mm slices) and a quick one.
SIZES = {"full": ((130, 512, 512), (2.5, 0.8, 0.8)), "small": ((65, 128, 128), (5.0, 3.2, 3.2))}
