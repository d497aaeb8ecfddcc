"""Analytic X-ray images of the sphere phantom: exact ball shadows through K and OpenCV distortion.

This is the independent ground truth of the calibration pipeline. It shares no code with
detection or fitting: each detector pixel (supersampled) is turned into its ray with
`cv2.undistortPointsIter`, the chord that ray cuts through each steel ball is computed in
closed form, and Beer-Lambert gives the intensity. The image then gets focal-spot blur,
quantum-like noise, the intensifier's circular field and burned-in text outside it, as a
clinical frame grab has.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...config.calibration_phantom import CalibrationPhantomProfile
from ...geometry import apply

#: Linear attenuation of steel near 60 keV (1/mm): mu/rho ~0.2 cm^2/g times 7.8 g/cm^3.
STEEL_MU_PER_MM = 0.15


@dataclass(frozen=True)
class Exposure:
    """How the synthetic frame looks; every number in image units."""

    rows: int = 1024
    cols: int = 1024
    fov_centre_px: tuple[float, float] = (511.5, 511.5)
    fov_radius_px: float = 500.0
    blur_sigma_px: float = 0.8
    noise_sigma: float = 0.01
    supersample: int = 3
    text: bool = True
    #: Brightness lost at the field's edge, falling off as radius squared (fraction), as
    #: the fluoroscope profile's detector.vignetting declares it.
    vignetting: float = 0.0
    #: Veiling glare: this fraction of the light is spread over a Gaussian of glare_sigma_px,
    #: the intensifier's long-range scatter that lifts a shadow's floor (fraction, pixels).
    glare_fraction: float = 0.0
    glare_sigma_px: float = 40.0
    #: Mean brightness of the open field at the centre (image units); a frame grab's scale.
    brightness: float = 1.0


def ball_line_integrals(phantom: CalibrationPhantomProfile, K: np.ndarray, dist: np.ndarray,
                        T_xray_from_phantom: np.ndarray, exposure: Exposure) -> np.ndarray:
    """(rows, cols) sum over balls of mu * chord length seen by each pixel (dimensionless)."""
    centres = apply(T_xray_from_phantom, phantom.centres())
    radii = phantom.diameters() / 2.0
    out = np.zeros((exposure.rows, exposure.cols), np.float64)
    s = exposure.supersample
    sub = (np.arange(s) + 0.5) / s - 0.5
    fx = K[0, 0]
    for c, r in zip(centres, radii):
        uv, _ = cv2.projectPoints(c.reshape(1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
        u0, v0 = uv.reshape(2)
        # Generous box: the shadow radius plus distortion's local stretch.
        half = int(np.ceil(1.3 * fx * r / c[2])) + 4
        us = np.arange(int(np.floor(u0)) - half, int(np.ceil(u0)) + half + 1)
        vs = np.arange(int(np.floor(v0)) - half, int(np.ceil(v0)) + half + 1)
        us = us[(us >= 0) & (us < exposure.cols)]
        vs = vs[(vs >= 0) & (vs < exposure.rows)]
        if len(us) == 0 or len(vs) == 0:
            continue
        su = (us[:, None] + sub[None, :]).reshape(-1)
        sv = (vs[:, None] + sub[None, :]).reshape(-1)
        gu, gv = np.meshgrid(su, sv)
        pts = np.stack([gu.ravel(), gv.ravel()], axis=1).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        xy = cv2.undistortPoints(pts, K, dist, None, None, None, criteria).reshape(-1, 2)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        along = d @ c
        perp2 = c @ c - along ** 2
        chord = 2.0 * np.sqrt(np.clip(r * r - perp2, 0.0, None))
        chord = chord.reshape(len(vs), s, len(us), s).mean(axis=(1, 3))
        out[np.ix_(vs, us)] += STEEL_MU_PER_MM * chord
    return out


def render(phantom: CalibrationPhantomProfile, K: np.ndarray, dist: np.ndarray, T_xray_from_phantom: np.ndarray,
           exposure: Exposure = Exposure(), rng: np.random.Generator | None = None) -> np.ndarray:
    """A float32 intensity image in [0, brightness]: air bright, balls dark, black outside the field."""
    rng = rng or np.random.default_rng(0)
    image = np.exp(-ball_line_integrals(phantom, K, dist, T_xray_from_phantom, exposure))
    vv, uu = np.mgrid[0:exposure.rows, 0:exposure.cols]
    r2 = ((uu - exposure.fov_centre_px[0]) ** 2 + (vv - exposure.fov_centre_px[1]) ** 2) / exposure.fov_radius_px ** 2
    inside = r2 <= 1.0
    if exposure.blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), exposure.blur_sigma_px)
    # The output phosphor's fall-off multiplies the light; glare then spreads part of it.
    image = image * (1.0 - exposure.vignetting * np.minimum(r2, 1.0)) * inside
    if exposure.glare_fraction > 0:
        spread = cv2.GaussianBlur(image, (0, 0), exposure.glare_sigma_px)
        image = (1.0 - exposure.glare_fraction) * image + exposure.glare_fraction * spread
    image = image + rng.normal(0.0, exposure.noise_sigma, image.shape) * np.sqrt(np.clip(image, 0.0, None))
    image = np.where(inside, image * exposure.brightness, 0.0).astype(np.float32)
    if exposure.text:
        burn_in_text(image, exposure.brightness)
    return np.clip(image, 0.0, exposure.brightness)


def burn_in_text(image: np.ndarray, white: float = 1.0) -> None:
    """Write the corner annotations a clinical video grab carries, in full white, in place."""
    rows, cols = image.shape
    text = np.zeros((rows, cols), np.uint8)  # OpenCV draws text on 8-bit images only
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(text, "FLUORO 75kV 2.0mA", (8, 28), font, 0.8, 255, 2)
    cv2.putText(text, "23-NOV-2026 11:42", (cols - 290, 28), font, 0.8, 255, 2)
    cv2.putText(text, "FT 00:01:12  o", (8, rows - 12), font, 0.8, 255, 2)
    cv2.putText(text, "ZOOM 1  L", (cols - 170, rows - 12), font, 0.8, 255, 2)
    image[text > 0] = white
