"""The fluoroscope's pixels and its field, from the profile alone: the matrix it is read out
at, the camera matrix per zoom, each pixel's ray (through the intensifier's distortion), the
beam's field (blades, the intensifier's circle, the soft edge) and the exposure control's
measuring field.

Pure geometry on NumPy and OpenCV, apart from the device: the caster uploads what these give,
and the tests hold them against a camera matrix built by hand.
"""

from __future__ import annotations

import numpy as np

from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError


def at_resolution(fluoroscope: FluoroscopeProfile, columns: int, rows: int) -> FluoroscopeProfile:
    """The same machine read out at another matrix: pixel pitch and intrinsics scaled."""
    sx, sy = columns / fluoroscope.detector.columns, rows / fluoroscope.detector.rows
    det = fluoroscope.detector.model_copy(update=dict(columns=columns, rows=rows,
                                                      pixel_pitch_mm=fluoroscope.detector.pixel_pitch_mm / sx))
    i = fluoroscope.intrinsics
    intr = i.model_copy(update=dict(fx=i.fx * sx, fy=i.fy * sy,
                                    cx=(i.cx + 0.5) * sx - 0.5, cy=(i.cy + 0.5) * sy - 0.5))
    return fluoroscope.model_copy(update=dict(detector=det, intrinsics=intr))


def zoomed_K(fluoroscope: FluoroscopeProfile, zoom: int) -> np.ndarray:
    """Camera matrix at zoom level `zoom` (1..4): focal lengths scaled by fov[0]/fov[zoom-1]
    about the principal point, so the narrower field fills the full pixel matrix."""
    fovs = [z.fov_mm for z in fluoroscope.zoom_levels]
    if not 1 <= zoom <= len(fovs):
        raise FluorosimError(f"zoom {zoom} is not one of the fluoroscope's levels 1..{len(fovs)}")
    K = fluoroscope.intrinsics.K().copy()
    s = fovs[0] / fovs[zoom - 1]
    K[0, 0] *= s
    K[1, 1] *= s
    return K


def pixel_pitch_at_zoom_mm(fluoroscope: FluoroscopeProfile, zoom: int) -> float:
    """Size of one pixel at the detector's input plane at zoom level `zoom` (mm)."""
    fovs = [z.fov_mm for z in fluoroscope.zoom_levels]
    return fluoroscope.detector.pixel_pitch_mm * fovs[zoom - 1] / fovs[0]


def ray_directions(fluoroscope: FluoroscopeProfile, zoom: int, distorted: bool) -> np.ndarray:
    """(rows, cols, 2) float32 normalised ray directions (x/z, y/z) in the xray frame of each
    pixel centre: through OpenCV's distortion model when `distorted`, the plain pinhole otherwise."""
    import cv2

    rows, cols = fluoroscope.detector.rows, fluoroscope.detector.columns
    K = zoomed_K(fluoroscope, zoom)
    u, v = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    pix = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    dist = fluoroscope.intrinsics.distortion.coefficients()
    if distorted and np.any(dist != 0):
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
        n = cv2.undistortPoints(pix, K, dist, None, None, None, criteria)
    else:
        n = np.empty_like(pix)
        n[..., 0] = (pix[..., 0] - K[0, 2]) / K[0, 0]
        n[..., 1] = (pix[..., 1] - K[1, 2]) / K[1, 1]
    return n.reshape(rows, cols, 2).astype(np.float32)


def field_radius_px(fluoroscope: FluoroscopeProfile) -> float:
    """Radius of the intensifier's circular field in pixels: the same circle at every zoom."""
    return fluoroscope.zoom_levels[0].fov_mm / fluoroscope.detector.pixel_pitch_mm / 2.0


def field_mask(fluoroscope: FluoroscopeProfile, zoom: int, collimation_mm, circle: bool) -> np.ndarray:
    """(rows, cols) bool: pixels the beam reaches (inside the blades, and inside the
    intensifier's circular field when `circle`)."""
    det = fluoroscope.detector
    rows, cols = det.rows, det.columns
    pitch = pixel_pitch_at_zoom_mm(fluoroscope, zoom)
    u = np.arange(cols) - (cols - 1) / 2.0
    v = np.arange(rows) - (rows - 1) / 2.0
    m = np.ones((rows, cols), dtype=bool)
    if collimation_mm is not None:
        half_u, half_v = collimation_mm[0] / 2.0 / pitch, collimation_mm[1] / 2.0 / pitch
        m &= (np.abs(v)[:, None] <= half_v) & (np.abs(u)[None, :] <= half_u)
    if circle:
        r = field_radius_px(fluoroscope)
        m &= (v[:, None] ** 2 + u[None, :] ** 2) <= r * r
    return m


def penumbra_px(fluoroscope: FluoroscopeProfile, zoom: int) -> float:
    """Half the width (pixels) of the field edge's fall-off at `zoom`: half of image.field_edge_mm
    on each side of the geometric edge."""
    return 0.5 * fluoroscope.image.field_edge_mm / pixel_pitch_at_zoom_mm(fluoroscope, zoom)


def field_edge(mask: np.ndarray, half_px: float) -> np.ndarray:
    """(rows, cols) float32 weight in [0, 1] of the blurred shadow of the aperture and blades
    around the geometric field `mask`: a smoothstep of the signed distance from the edge over
    [-half_px, +half_px], so one half at the geometric edge (where calibration finds it), 1 a
    half-width inside and 0 a half-width outside. The frame's border counts as outside the
    field: where the circle meets it, it fades as elsewhere."""
    import cv2

    if half_px < 0.25:
        return mask.astype(np.float32)
    # Distances (px) of pixel centres from the edge: a boundary pixel's is 0.5 on either side.
    padded = np.pad(mask.astype(np.uint8), 1)
    inside = cv2.distanceTransform(padded, cv2.DIST_L2, 5)[1:-1, 1:-1] - np.float32(0.5)
    outside = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5) - np.float32(0.5)
    signed = np.where(mask, inside, -outside)
    t = np.clip((signed + np.float32(half_px)) / np.float32(2.0 * half_px), 0.0, 1.0)
    return (t * t * (3.0 - 2.0 * t)).astype(np.float32)


def measuring_field(beam: np.ndarray) -> np.ndarray:
    """The automatic brightness control's measuring field: a disc half the diameter of the beam
    (the intensifier's circle or the collimated field), about its centre, as an ABC sensor
    weights the middle of the image."""
    rows, cols = beam.shape
    area = int(beam.sum())
    if area == 0:
        return beam
    r = 0.5 * np.sqrt(area / np.pi)
    ys, xs = np.nonzero(beam)
    cy, cx = ys.mean(), xs.mean()
    central = beam & (((np.arange(rows) - cy) ** 2)[:, None] + ((np.arange(cols) - cx) ** 2)[None, :] <= r * r)
    return central if central.any() else beam
