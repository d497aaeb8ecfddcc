"""The synthetic adult chest's bones: the spine T1-L3 (cortex, cancellous bone, discs,
posterior elements, canal), 12 pairs of ribs with costal cartilage, the sternum, clavicles
and scapulae, drawn into the body of `adult_body.py`."""

from __future__ import annotations

import numpy as np

from .adult_body import (
    BODY_A,
    BODY_B,
    BODY_POWER,
    BODY_YC,
    HU_CARTILAGE,
    HU_CORTICAL,
    HU_CSF,
    HU_DISC,
    HU_TRABECULAR,
    SKIN_MM,
    SUBCUT_FAT_MM,
    body_at,
)
from .shapes import Layer, bounds, ellipsoid, elliptic_prism, paint_bone, paint_tube, rotation

SPINE_Y = 62.0                  # y of the vertebral body centres at mid-thorax (mm)
T1_TOP_Z = 190.0


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


def paint_spine(layer: Layer) -> None:
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
    a = float(body_at(zr, BODY_A)) - SKIN_MM - SUBCUT_FAT_MM - 8.0
    b = float(body_at(zr, BODY_B)) - SKIN_MM - SUBCUT_FAT_MM - 8.0
    yc = float(body_at(zr, BODY_YC))
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


def paint_ribs_and_sternum(layer: Layer) -> None:
    verts = _vertebrae()
    sternum_y = float(body_at(80.0, BODY_YC) - body_at(80.0, BODY_B)) + SKIN_MM + SUBCUT_FAT_MM + 12.0
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
