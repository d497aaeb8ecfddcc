"""The bones of the built-in child (see `anatomy.py` for the body they sit in).

- `skeleton`: a transparent layer of the bones that stay still (vertebrae with discs and
  posterior elements, clavicles, scapulae, pelvis, femora), laid over every phase;
- `rib_cage`: ribs with costal cartilage and the sternum for one breathing state, their
  front raised by the pump-handle motion of inspiration.

Coordinates are the `ct` frame (LPS, mm), as in `anatomy.py`, whose tissue values and
breathing motion these use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .anatomy import (
    BODY_A,
    BODY_B,
    BODY_POWER,
    BODY_YC,
    BODY_Z,
    HU_CARTILAGE,
    HU_CORTICAL,
    HU_DISC,
    HU_MARROW_SHAFT,
    HU_TRABECULAR,
    RIB_LIFT_MM,
)
from .shapes import Grid, Layer, bounds, ellipsoid, elliptic_prism, intersect, paint_bone, paint_tube, rotation

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
        a = float(np.interp(zr, BODY_Z, BODY_A)) - 18.0
        b = float(np.interp(zr, BODY_Z, BODY_B)) - 18.0
        yc = float(np.interp(zr, BODY_Z, BODY_YC))
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
    return float(np.interp(110, BODY_Z, BODY_YC) - np.interp(110, BODY_Z, BODY_B)) + 14.0


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
