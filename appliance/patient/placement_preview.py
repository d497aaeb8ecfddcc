"""The picture `fluorosim case place` draws: the placed CT seen from the beam (AP) and from
the side (lateral), with the box phantom's outline, the X-ray field and the target.

Each view is a sum projection of a rough attenuation (1 + HU/1000, water-relative) along
the viewing direction on a 1 mm grid, drawn in the phantom frame, so what is inside the
field here is what the appliance will render at the home pose. It is for checking a
placement by eye, not the renderer's physics.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..atomic_file import write_atomic
from ..errors import FluorosimError
from ..geometry import apply
from .placement import HEAD_AXIS_PHANTOM, BeamGeometry
from .volume import Volume

#: Voxels sampled for a view; more only slows the picture down.
MAX_SAMPLES = 6_000_000
#: Half-size of each view around the isocentre (mm): along the box, and across it.
HALF_ALONG_MM = 380
HALF_ACROSS_MM = 220

FIELD_COLOUR = (0, 200, 255)     # BGR: amber, the colour of a light-beam localiser
BOX_COLOUR = (80, 220, 80)
CT_COLOUR = (255, 160, 60)       # the CT's voxel box
TARGET_COLOUR = (60, 60, 255)


def _axes(geometry: BeamGeometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = geometry.direction / np.linalg.norm(geometry.direction)
    head = HEAD_AXIS_PHANTOM - (HEAD_AXIS_PHANTOM @ d) * d
    head /= np.linalg.norm(head)
    return head, np.cross(d, head), d


def _projection(points: np.ndarray, weights: np.ndarray, horizontal: np.ndarray, vertical: np.ndarray,
                origin: np.ndarray, half_h: int, half_v: int, sample_mm: float) -> np.ndarray:
    """Sum projection at 1 mm per pixel, blurred over the sample spacing `sample_mm` so voxels
    coarser than a pixel leave no empty stripes between them."""
    rel = points - origin
    col = np.floor(rel @ horizontal + half_h).astype(np.int64)
    row = np.floor(half_v - rel @ vertical).astype(np.int64)    # vertical axis points up on screen
    w, h = 2 * half_h, 2 * half_v
    ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    image = np.bincount(row[ok] * w + col[ok], weights=weights[ok], minlength=w * h).reshape(h, w)
    blurred = cv2.GaussianBlur(image.astype(np.float32), (0, 0), max(sample_mm, 0.5))
    body = blurred[blurred > 0]
    top = np.percentile(body, 99.5) if body.size else 1.0
    grey = (255 * np.clip(blurred / (top + 1e-9), 0, 1)).astype(np.uint8)
    return cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)


def _to_px(p, origin, horizontal, vertical, half_h, half_v) -> tuple[int, int]:
    rel = np.asarray(p, float) - origin
    return int(round(rel @ horizontal + half_h)), int(round(half_v - rel @ vertical))


def draw_preview(volume: Volume, T_phantom_from_ct: np.ndarray, geometry: BeamGeometry,
                 box_mm: tuple[float, float, float], target_lps) -> np.ndarray:
    """(rows, cols, 3) BGR picture: beam's-eye view on the left, lateral view on the right."""
    nz, ny, nx = volume.hu.shape
    step = max(1, int(np.ceil((volume.hu.size / MAX_SAMPLES) ** (1 / 3))))
    k, j, i = np.mgrid[0:nz:step, 0:ny:step, 0:nx:step]
    hu = volume.hu[::step, ::step, ::step].astype(np.float32).reshape(-1)
    ijk = np.stack([i.reshape(-1), j.reshape(-1), k.reshape(-1)], axis=1).astype(np.float64)
    pts = apply(T_phantom_from_ct @ volume.T_ct_from_voxel, ijk)
    voxel_mm3 = float(np.prod(volume.spacing_mm)) * step ** 3
    weights = np.clip(1.0 + hu / 1000.0, 0.0, 3.0) * voxel_mm3
    cell = float(volume.spacing_mm.max()) * step
    head, across, d = _axes(geometry)
    iso = geometry.isocentre
    # Centre the views between the isocentre and the box's centre along the box, so both show.
    middle = iso - 0.5 * (iso @ head) * head
    views = []
    # Beam's eye: looking along the beam, head to the right, `across` up.
    ap = _projection(pts, weights, head, across, middle, HALF_ALONG_MM, HALF_ACROSS_MM, cell)
    px = lambda p: _to_px(p, middle, head, across, HALF_ALONG_MM, HALF_ACROSS_MM)  # noqa: E731
    L, W, H = box_mm
    box = [np.array([sx * L / 2, sy * W / 2, 0.0]) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    cv2.polylines(ap, [np.array([px(c) for c in box], np.int32)], True, BOX_COLOUR, 2)
    cv2.circle(ap, px(iso), int(round(geometry.field_radius_mm)), FIELD_COLOUR, 2)
    views.append((ap, "AP: beam's eye at the isocentre (head ->)", px))
    # Lateral: looking across the beam, head to the right, detector up, source below.
    lat = _projection(pts, weights, head, -d, middle, HALF_ALONG_MM, HALF_ACROSS_MM, cell)
    pl = lambda p: _to_px(p, middle, head, -d, HALF_ALONG_MM, HALF_ACROSS_MM)  # noqa: E731
    box = [np.array([sx * L / 2, 0.0, sz * H / 2]) for sx, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    cv2.polylines(lat, [np.array([pl(c) for c in box], np.int32)], True, BOX_COLOUR, 2)
    # The field as a cone from the focal spot through the field's edge at the isocentre plane.
    r = geometry.field_radius_mm
    far = geometry.source_to_image_mm / geometry.source_to_isocentre_mm
    for side in (-1.0, 1.0):
        edge = iso + side * r * head
        end = geometry.source + far * (edge - geometry.source)
        cv2.line(lat, pl(geometry.source), pl(end), FIELD_COLOUR, 2)
    views.append((lat, "LATERAL: detector up, source down (head ->)", pl))
    panels = []
    centre = apply(T_phantom_from_ct, np.asarray(target_lps, float))
    ct_box = apply(T_phantom_from_ct @ volume.T_ct_from_voxel,
                   np.array([[a, b, c] for a in (0, nx - 1) for b in (0, ny - 1) for c in (0, nz - 1)], float))
    for image, title, to_px in views:
        hull = cv2.convexHull(np.array([to_px(c) for c in ct_box], np.int32))
        cv2.polylines(image, [hull], True, CT_COLOUR, 1)
        u, v = to_px(centre)
        cv2.drawMarker(image, (u, v), TARGET_COLOUR, cv2.MARKER_CROSS, 24, 2)
        cv2.putText(image, title, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
        panels.append(image)
    legend = "green: box phantom   blue: CT volume   amber: X-ray field (widest zoom)   red: target at the isocentre   1 px = 1 mm"
    out = np.concatenate([panels[0], np.full((panels[0].shape[0], 8, 3), 40, np.uint8), panels[1]], axis=1)
    strip = np.full((28, out.shape[1], 3), 40, np.uint8)
    cv2.putText(strip, legend, (8, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([out, strip], axis=0)


def write_preview(path: Path, picture: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", picture)
    if not ok:
        raise FluorosimError(f"{path}: cannot encode the preview as PNG")
    try:
        write_atomic(path, data.tobytes())
    except OSError as e:
        raise FluorosimError(f"{path}: cannot write the preview ({e.strerror or e}); check the folder and free space") from None
