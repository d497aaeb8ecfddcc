"""The anatomy of the built-in child: a procedurally drawn torso and pelvis of a 5-8 year old.

The parts are drawn separately so that a 4D series costs little more than one volume:

- `static_soft`: skin, subcutaneous fat, muscle, the body cavities, paraspinal and psoas
  muscles, bowel — everything that does not move with the breath;
- `skeleton`: a transparent layer of the bones that stay still (vertebrae with discs and
  posterior elements, clavicles, scapulae, pelvis, femora), laid over every phase;
- `rib_cage`: ribs with costal cartilage and the sternum for one breathing state, their
  front raised by the pump-handle motion of inspiration;
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

from dataclasses import dataclass

import numpy as np

from .shapes import (
    Grid,
    Layer,
    bounds,
    ellipsoid,
    elliptic_prism,
    intersect,
    paint_bone,
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
_BODY_Z = np.array([-200, -170, -140, -110, -80, -40, 0, 40, 80, 120, 150, 165, 180, 190, 200], np.float32)
_BODY_A = np.array([96, 104, 107, 104, 96, 92, 94, 100, 106, 108, 106, 100, 75, 48, 40], np.float32)
_BODY_B = np.array([56, 62, 66, 67, 68, 69, 69, 69, 68, 66, 62, 58, 50, 40, 36], np.float32)
_BODY_YC = np.array([4, 3, 2, 1, 0, -1, -2, -2, -1, 0, 2, 3, 6, 8, 10], np.float32)
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
    a, b, yc = _at(Z, _BODY_Z, _BODY_A), _at(Z, _BODY_Z, _BODY_B), _at(Z, _BODY_Z, _BODY_YC)
    trunk = np.maximum(_ellipse_xsec(X, Y, a, b, yc), (-185.0 - Z) * np.float32(0.7))
    thighs = np.minimum(np.sqrt((X + 52) ** 2 + (Y - 2) ** 2), np.sqrt((X - 52) ** 2 + (Y - 2) ** 2)) - 50.0
    thighs = np.maximum(thighs, Z + 120.0)
    return smooth_min(trunk, thighs, 20.0) + np.float32(inset)


def cavity(X, Y, Z, inset=0.0):
    """The body cavity (thorax, abdomen, pelvis) inside the muscular wall."""
    a, b, yc = _at(Z, _BODY_Z, _BODY_A), _at(Z, _BODY_Z, _BODY_B), _at(Z, _BODY_Z, _BODY_YC)
    wall = SKIN_MM + SUBCUT_FAT_MM + _at(Z, _WALL_Z, _WALL_MM) + np.float32(inset)
    d = _ellipse_xsec(X, Y, a - wall, b - wall, yc)
    # Domed lung apices rather than a flat roof.
    top = CAVITY_TOP_Z - 45.0 * (X / 85.0) ** 2 - 20.0 * ((Y - 10.0) / 60.0) ** 2
    return intersect(d, CAVITY_BOTTOM_Z - Z, Z - top)


# --- the spine ---

@dataclass(frozen=True)
class Vertebra:
    name: str
    z: float            # centre of the body (mm)
    height: float       # of the body (mm)
    disc: float         # disc below it (mm)
    a: float            # half-width of the body (mm)
    b: float            # half-depth of the body (mm)
    y: float            # y of the body centre (mm)


def spine_y(z):
    """y of the vertebral body centres (mm): cervical lordosis, thoracic kyphosis, lumbar lordosis."""
    z = np.asarray(z, float)
    thoracic = 20.0 + 4.0 * np.sin(np.pi * np.clip(z, 0, 174) / 174.0) - 0.6 * np.clip(z - 174, 0, None)
    lumbar = 20.0 - 6.0 * np.sin(np.pi * np.clip(-z, 0, 96) / 96.0)
    return np.where(z >= 0, thoracic, lumbar)


def vertebrae() -> list[Vertebra]:
    """C6-L5: cervical bodies 9 mm high, thoracic 10-12 mm with 3-4 mm discs, lumbar 13.5-15 mm
    with 4.5 mm discs; T1 starts 172 mm above the centre of the volume."""
    out = []
    for name, zc in (("C6", 191.5), ("C7", 179.5)):
        out.append(Vertebra(name, zc, 9.0, 3.0, 9.0, 7.0, float(spine_y(zc))))
    top = 172.0
    specs = [(f"T{i + 1}", h, d, a, b) for i, (h, d, a, b) in enumerate(zip(
        np.linspace(10, 12, 12), np.linspace(3, 4, 12), np.linspace(10, 14, 12), np.linspace(8, 11.5, 12)))]
    specs += [(f"L{i + 1}", h, 4.5, a, b) for i, (h, a, b) in enumerate(zip(
        np.linspace(13.5, 15, 5), np.linspace(15, 18, 5), np.linspace(12, 13, 5)))]
    for name, h, d, a, b in specs:
        zc = top - h / 2
        out.append(Vertebra(name, zc, h, d, a, b, float(spine_y(zc))))
        top -= h + d
    return out


def _paint_vertebra(bones: Layer, v: Vertebra) -> None:
    lumbar = v.name.startswith("L")
    cervical = v.name.startswith("C")
    back = v.y + v.b
    r = 3.5 if lumbar else 3.0
    for s in (-1, 1):
        root = (s * 0.55 * v.a, v.y + 0.6 * v.b, v.z + 1)
        ped = (s * 0.6 * v.a, back + 8, v.z + 1)
        lamina = (0.0, back + 15, v.z - 2)
        tp = (s * (v.a + (20 if lumbar else 8 if cervical else 15)), back + (3 if lumbar else 0 if cervical else 13), v.z + 2)
        for path, radius in (([root, ped], r), ([ped, lamina], r - 0.4), ([ped, tp], r)):
            paint_tube(bones, path, radius, HU_CORTICAL * 0.8)
    spinous_end = (0.0, back + (16 if cervical else 25), v.z - (3 if lumbar else 8))
    paint_tube(bones, [(0.0, back + 15, v.z - 2), spinous_end], (4.5 if lumbar else 3.2, 2.5), HU_CORTICAL * 0.8)
    # The body last, so the roots of the pedicles lie under its cortex.
    c = (0.0, v.y, v.z)
    body = lambda X, Y, Z: elliptic_prism(X, Y, Z, c, v.a, v.b, v.height / 2, power=2.2)
    lo, hi = bounds([c], max(v.a, v.b, v.height) + 3)
    paint_bone(bones, body, lo, hi, 2.0, HU_CORTICAL, HU_TRABECULAR)
    dc = (0.0, v.y, v.z - v.height / 2 - v.disc / 2)
    bones.paint(lambda X, Y, Z: elliptic_prism(X, Y, Z, dc, v.a - 0.5, v.b - 0.5, v.disc / 2 + 0.3, power=2.2),
                HU_DISC, *bounds([dc], max(v.a, v.b) + 3))


def _paint_sacrum(bones: Layer) -> None:
    """S1 at the lumbosacral disc, tapering and curving posteriorly down to the coccyx."""
    zk = np.array([-160.0, -140.0, -120.0, -100.0], np.float32)
    yk = np.array([48.0, 40.0, 29.0, 20.0], np.float32)
    wk = np.array([9.0, 22.0, 36.0, 42.0], np.float32)
    tk = np.array([5.0, 8.0, 11.0, 13.0], np.float32)

    def sacrum(X, Y, Z):
        y, w, t = np.interp(Z, zk, yk), np.interp(Z, zk, wk), np.interp(Z, zk, tk)
        # The base (S1 endplate) is level in the middle; the alae slope down laterally.
        base = -98.5 - 0.5 * np.maximum(np.abs(X) - 16.0, 0.0)
        return intersect((np.sqrt((X / w) ** 2 + ((Y - y) / t) ** 2) - 1.0) * np.minimum(w, t), Z - base, -160.0 - Z)
    paint_bone(bones, sacrum, (-46, 0, -165), (46, 65, -95), 2.0, HU_CORTICAL, HU_TRABECULAR)


def _paint_pelvis(bones: Layer) -> None:
    for s in (-1, 1):
        # Iliac wing: a plate from the sacroiliac joint (posteromedial) to the anterior
        # superior iliac spine (anterolateral), bowed into the iliac fossa, its crest arched
        # over L4-L5 and its lower border narrowing into the body of the ilium above the hip.
        si, asis = np.array([s * 36.0, 40.0]), np.array([s * 92.0, -22.0])
        along = asis - si
        length = float(np.linalg.norm(along))
        along /= length
        normal = np.array([along[1], -along[0]]) * s     # toward posterolateral

        def wing(X, Y, Z, si=si, along=along, normal=normal, length=length):
            dx, dy = X - np.float32(si[0]), Y - np.float32(si[1])
            u = (dx * along[0] + dy * along[1]) / length
            n = dx * normal[0] + dy * normal[1] - 14.0 * np.sin(np.pi * np.clip(u, 0, 1))
            crest = -100.0 + 34.0 * np.sin(np.pi * np.clip(u, 0, 1) ** 0.8) ** 0.6
            low = -112.0 - 26.0 * np.exp(-((u - 0.32) / 0.16) ** 2)
            return intersect(np.abs(n) - 3.5, Z - crest, low - Z, -u * length, (u - 1.0) * length)
        paint_bone(bones, wing, (min(si[0], asis[0]) - 20, -35, -142), (max(si[0], asis[0]) + 20, 55, -60),
                   1.5, HU_CORTICAL, HU_TRABECULAR)
        # Acetabulum and femur: head (with its growth plate), neck, greater trochanter, shaft.
        head = np.array([s * 55.0, -5.0, -152.0])
        # The acetabulum: a block of bone medial to and above the head, where ilium, ischium
        # and pubis meet, with the socket (head plus 2 mm of joint cartilage) carved out and
        # open laterally and downward.
        block_c = head + [-s * 6.0, 0.0, 5.0]

        def acetabulum(X, Y, Z, h=head, c=block_c, s=s):
            block = np.sqrt((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) - 24.0
            socket = np.sqrt((X - h[0]) ** 2 + (Y - h[1]) ** 2 + (Z - h[2]) ** 2) - 17.0
            return intersect(block, -socket, 0.7 * s * (X - h[0]) - 0.7 * (Z - h[2]) - 6.0)
        paint_bone(bones, acetabulum, *bounds([block_c], 28), 1.5, HU_CORTICAL, HU_TRABECULAR)
        neck_end = head + [s * 22, 4, -16]
        shaft_end = np.array([s * 68.0, 8.0, -215.0])
        troch = head + [s * 30, 8, -8]
        for path, radius in (([head, neck_end], 9.0), ([neck_end, troch], 10.0), ([neck_end + [0, 0, 4], shaft_end], 9.0)):
            paint_tube(bones, path, radius, HU_CORTICAL)
        for path, radius in (([head, neck_end], 7.0), ([neck_end, troch], 8.5)):
            paint_tube(bones, path, radius, HU_TRABECULAR)
        paint_tube(bones, [neck_end + [0, 0, 4], shaft_end], 6.0, HU_MARROW_SHAFT)
        # The head last: its cortex across the top of the neck stands for the growth plate.
        paint_bone(bones, lambda X, Y, Z, h=head: np.sqrt((X - h[0]) ** 2 + (Y - h[1]) ** 2 + (Z - h[2]) ** 2) - 15.0,
                   *bounds([head], 18), 1.2, HU_CORTICAL, HU_TRABECULAR)
        # Pubis and ischium around the obturator foramen, meeting at the symphysis.
        sup_ramus = [(s * 45, -12, -146), (s * 20, -32, -155), (s * 4.5, -40, -162)]
        inf_ramus = [(s * 4.5, -38, -170), (s * 22, -24, -182), (s * 40, -2, -184)]
        ischium = [(s * 48, 4, -150), (s * 44, 4, -172), (s * 40, -2, -184)]
        for ramus, radius in ((sup_ramus, 6.0), (inf_ramus, 5.5), (ischium, 8.0)):
            paint_tube(bones, ramus, radius, HU_CORTICAL)
            paint_tube(bones, ramus, radius - 1.5, HU_TRABECULAR)


def _paint_ribs(bones: Layer, lift: float) -> None:
    """Twelve pairs, each following the chest wall from its vertebra round to the front.

    A rib is drawn in the angular coordinate of its own ellipse: for each voxel, its angle
    from the back toward the front picks the point of the rib, and the distance in that
    radial/vertical plane gives the rib's flattened oval cross-section.
    """
    verts = {v.name: v for v in vertebrae()}
    sternum_top, sternum_bottom = 150.0, 78.0
    sternal_z = np.linspace(sternum_top - 6, sternum_bottom + 6, 7)
    theta0 = 0.2 * np.pi
    for i in range(12):
        v = verts[f"T{i + 1}"]
        zr = v.z + 2.0
        a = float(np.interp(zr, _BODY_Z, _BODY_A)) - 18.0
        b = float(np.interp(zr, _BODY_Z, _BODY_B)) - 18.0
        yc = float(np.interp(zr, _BODY_Z, _BODY_YC))
        if i == 0:
            a, b = a - 14.0, b - 6.0
        drop = 28.0 + 2.5 * min(i, 8)
        end = (0.78 * np.pi if i < 7 else 0.72 * np.pi if i < 10 else 0.55 * np.pi if i == 10 else 0.42 * np.pi)
        if i < 7:
            cart_end, cart_z = np.pi, sternal_z[i]
        elif i < 10:
            cart_end, cart_z = (0.93 - 0.03 * (i - 7)) * np.pi, sternal_z[6] - 6.0 * (i - 6)
        else:
            cart_end, cart_z = end, None
        half_t, half_h = (2.5, 3.2) if i in (0, 10, 11) else (2.8, 3.8)

        def z_bone(th, zr=zr, drop=drop - lift):
            # A rib lies roughly in a plane tilted down toward the front: its height falls
            # with the antero-posterior position, (1 - cos) of the angle from the back.
            f = (np.cos(theta0) - np.cos(np.maximum(th, theta0))) / (np.cos(theta0) + 1.0)
            return zr - drop * f

        z_end = float(z_bone(end))

        zlo = min(z_end, cart_z if cart_z is not None else z_end) - 10
        lo, hi = (-a - 8, yc - b - 8, zlo), (a + 8, yc + b + 8, zr + 10)
        # The rib's angular coordinates of every voxel of its box, shared by bone and cartilage.
        _, X, Y, Z = bones.grid.box(lo, hi)
        u, w = np.abs(X) / a, (Y - yc) / b
        th = np.arctan2(u, w)
        rho = (u ** BODY_POWER + np.abs(w) ** BODY_POWER) ** (1.0 / BODY_POWER)
        R = np.sqrt((a * np.sin(th)) ** 2 + (b * np.cos(th)) ** 2)

        def rib_sdf(t0, t1, zfun, ht, hh, th=th, rho=rho, R=R, Z=Z):
            dr = (rho - 1.0) * R
            dz = Z - zfun(th)
            k0 = np.sqrt((dr / ht) ** 2 + (dz / hh) ** 2)
            k1 = np.sqrt((dr / ht ** 2) ** 2 + (dz / hh ** 2) ** 2)
            d = k0 * (k0 - 1.0) / (k1 + 1e-6)
            return np.maximum(d, np.maximum(t0 - th, th - t1) * R)

        bone = rib_sdf(theta0, end, z_bone, half_t, half_h)
        paint_bone(bones, lambda *box, bone=bone: bone, lo, hi, 1.5, HU_CORTICAL, HU_TRABECULAR)
        if cart_z is not None:
            def z_cart(th, end=end, cart_end=cart_end, z_end=z_end, cart_z=cart_z + lift):
                f = np.clip((th - end) / (cart_end - end), 0, 1)
                return z_end + (cart_z - z_end) * f
            cartilage = rib_sdf(end - 0.02, cart_end, z_cart, half_t, half_h - 0.5)
            bones.paint(lambda *box, cartilage=cartilage: cartilage, HU_CARTILAGE, lo, hi)
        # Neck and head of the rib: from the rib's angle to the transverse process and the body.
        for s in (-1, 1):
            n = (np.sin(theta0) ** BODY_POWER + np.cos(theta0) ** BODY_POWER) ** (1.0 / BODY_POWER)
            start = (s * a * np.sin(theta0) / n, yc + b * np.cos(theta0) / n, zr)
            tp = (s * (v.a + 14), v.y + v.b + 12, zr)
            head = (s * (v.a + 1), v.y + 2, v.z + v.height / 2)
            paint_tube(bones, [start, tp, head], (half_t + 0.8, half_t + 0.5, half_t + 0.3), HU_CORTICAL)
            paint_tube(bones, [start, tp, head], (half_t - 0.4, half_t - 0.7, half_t - 0.9), HU_TRABECULAR)


def _sternum_y() -> float:
    return float(np.interp(110, _BODY_Z, _BODY_YC) - np.interp(110, _BODY_Z, _BODY_B)) + 14.0


def _paint_sternum(bones: Layer, lift: float) -> None:
    """Manubrium and three sternebrae of a child, separated by cartilage; raised by `lift` mm
    and carried forward a little by the ribs' pump-handle motion."""
    yst = _sternum_y() - 0.3 * lift
    for zc, half_w, half_h in ((143.0, 16.0, 8.0), (124.0, 11.0, 8.0), (105.0, 11.0, 8.0), (86.0, 10.0, 7.0)):
        c = (0.0, yst, zc + lift)
        paint_bone(bones, lambda X, Y, Z, c=c, w=half_w, h=half_h: elliptic_prism(X, Y, Z, c, w, 5.0, h),
                   *bounds([c], 20), 1.0, HU_CORTICAL, HU_TRABECULAR)


def _paint_shoulder_girdle(bones: Layer) -> None:
    yst = _sternum_y()
    for s in (-1, 1):
        clav = [(s * 14, yst - 2, 156), (s * 45, yst + 4, 163), (s * 75, yst + 20, 167), (s * 92, yst + 40, 170)]
        paint_tube(bones, clav, 5.0, HU_CORTICAL)
        paint_tube(bones, clav, 3.5, HU_TRABECULAR)
        # Scapula: a thin plate over the upper posterior ribs with its spine.
        # It follows the back, turning forward laterally (about 22 degrees).
        c = (s * 60.0, 46.0, 128.0)
        R = rotation("y", -s * 12) @ rotation("z", -s * 22)
        plate = lambda X, Y, Z, c=c, R=R: ellipsoid(X, Y, Z, c, (24.0, 3.5, 40.0), R)
        paint_bone(bones, plate, *bounds([c], 42), 1.0, HU_CORTICAL, HU_TRABECULAR)
        paint_tube(bones, [(s * 40, 54, 150), (s * 78, 40, 156)], 3.5, HU_CORTICAL)


def skeleton(grid: Grid) -> Layer:
    """The skeleton that stays still while breathing, as a transparent layer to lay over every phase."""
    layer = Layer(grid, opaque=False)
    for v in vertebrae():
        _paint_vertebra(layer, v)
    _paint_sacrum(layer)
    _paint_pelvis(layer)
    _paint_shoulder_girdle(layer)
    return layer


def rib_cage(grid: Grid, breath: float) -> Layer:
    """Ribs, costal cartilage and sternum at breathing state `breath` (0 end-expiration, 1
    end-inspiration): the pump-handle motion raises the front of the cage by up to
    RIB_LIFT_MM while the rib heads stay at the spine."""
    layer = Layer(grid, opaque=False)
    _paint_ribs(layer, RIB_LIFT_MM * breath)
    _paint_sternum(layer, RIB_LIFT_MM * breath)
    return layer


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
