"""Find the image intensifier's circular field of view, so nothing outside it is read.

Outside the circle a frame grab carries only black and burned-in text (patient name,
kV, time), which would otherwise turn into spurious blobs. The exposed disc is the largest
bright connected region after Otsu's threshold; its outer contour is fitted with a circle,
dropping contour points that dip inward where a dark object touches the edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import FluorosimError


@dataclass(frozen=True)
class FieldOfView:
    """The exposed disc of the detector (pixels; centre as u = column, v = row)."""

    centre_u: float
    centre_v: float
    radius_px: float

    def mask(self, shape: tuple[int, int], margin_px: float = 0.0) -> np.ndarray:
        """Boolean (rows, cols) mask of pixels at least `margin_px` inside the circle."""
        vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
        r = self.radius_px - margin_px
        return (uu - self.centre_u) ** 2 + (vv - self.centre_v) ** 2 <= r * r

    def distance_inside(self, uv: np.ndarray) -> np.ndarray:
        """How far each (u, v) point lies inside the circle edge (pixels; negative outside)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        return self.radius_px - np.hypot(uv[:, 0] - self.centre_u, uv[:, 1] - self.centre_v)


def whole_image(shape: tuple[int, int]) -> FieldOfView:
    """A flat panel has no circle: a disc that covers every pixel."""
    rows, cols = shape
    return FieldOfView((cols - 1) / 2, (rows - 1) / 2, float(np.hypot(rows, cols)))


def _fit_circle(points: np.ndarray) -> tuple[float, float, float]:
    """Algebraic (Kasa) least-squares circle through (n, 2) points."""
    x, y = points[:, 0], points[:, 1]
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    b = -(x * x + y * y)
    (D, E, F), *_ = np.linalg.lstsq(A, b, rcond=None)
    cu, cv = -D / 2, -E / 2
    return cu, cv, float(np.sqrt(max(cu * cu + cv * cv - F, 0.0)))


def find_field_of_view(image: np.ndarray, source: str = "image") -> FieldOfView:
    """The intensifier's circle in `image` (any dtype, one channel), or FluorosimError naming `source`."""
    img = np.asarray(image, dtype=np.float32)
    lo, hi = np.percentile(img, [0.5, 99.5])
    if not hi > lo:
        raise FluorosimError(f"{source}: the image is blank; check that it is an X-ray frame of the phantom")
    scaled = np.clip((img - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8)
    _, binary = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        raise FluorosimError(f"{source}: no exposed field of view found; check that it is an X-ray frame of the phantom")
    contour = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    area = cv2.contourArea(contour.astype(np.float32))
    if area < 0.1 * img.shape[0] * img.shape[1]:
        raise FluorosimError(f"{source}: the exposed area covers only {100 * area / img.size:.0f} % of the image; "
                             "an intensifier frame shows a large bright circle (check exposure and polarity)")
    # Points on the image border belong to a field cut by the frame, not to the circle.
    rows, cols = img.shape
    on_border = (contour[:, 0] <= 0) | (contour[:, 1] <= 0) | (contour[:, 0] >= cols - 1) | (contour[:, 1] >= rows - 1)
    points = contour[~on_border]
    if len(points) < 20:
        raise FluorosimError(f"{source}: the exposed area has no circular edge inside the image")
    cu, cv, r = _fit_circle(points)
    for _ in range(5):
        dist = np.hypot(points[:, 0] - cu, points[:, 1] - cv) - r
        keep = np.abs(dist) < max(2.0, 3.0 * np.median(np.abs(dist)))
        if keep.sum() < 20:
            break
        cu, cv, r = _fit_circle(points[keep])
    on_circle = np.abs(np.hypot(points[:, 0] - cu, points[:, 1] - cv) - r) < 2.0
    if on_circle.mean() < 0.5:
        raise FluorosimError(f"{source}: the exposed area is not a circle (only {100 * on_circle.mean():.0f} % of its edge "
                             "lies on one); an intensifier frame grab shows the field as a bright disc on black, so "
                             "export it with air bright, or calibrate a flat panel with its profile's detector.kind")
    # Contour pixels lie half a pixel inside the true edge on average.
    return FieldOfView(cu, cv, r + 0.5)
