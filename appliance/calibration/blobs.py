"""Find the balls' shadows as blobs, with their diameters, by scale-space blob detection.

The scale-normalised Laplacian of Gaussian, -sigma^2 LoG, peaks at the centre of a disc of
diameter D at sigma = D / (2 sqrt 2) (Lindeberg). Local maxima over position and scale
above a noise-relative threshold are the candidate balls; an edge (a plate rim) is refused
because its Hessian is elongated. The centre is then refined to a fraction of a pixel by
the background-subtracted centroid of the shadow.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..config.calibration_phantom import Detection
from .crowding import crowded
from .field_of_view import FieldOfView

SQRT8 = 2.0 * np.sqrt(2.0)


@dataclass(frozen=True)
class Blobs:
    """Detected shadows: centres (n, 2) as (u, v) pixels, diameters (n,) pixels, strengths (n,)."""

    uv: np.ndarray
    diameter_px: np.ndarray
    strength: np.ndarray
    #: Shadows found but dropped because another lay too near to measure either (crowding.py).
    crowded: int = 0

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, keep) -> Blobs:
        return Blobs(self.uv[keep], self.diameter_px[keep], self.strength[keep], self.crowded)

    @staticmethod
    def concat(*parts: Blobs) -> Blobs:
        return Blobs(np.concatenate([p.uv for p in parts]).reshape(-1, 2),
                     np.concatenate([p.diameter_px for p in parts]),
                     np.concatenate([p.strength for p in parts]), sum(p.crowded for p in parts))


def attenuation_image(image: np.ndarray, fov: FieldOfView, dark_balls: bool) -> np.ndarray:
    """The image turned so balls are bright, zero at the field's median, zero outside it (float32)."""
    img = np.asarray(image, dtype=np.float32)
    inside = fov.mask(img.shape, margin_px=2.0)
    med = float(np.median(img[inside]))
    out = med - img if dark_balls else img - med
    out[~inside] = 0.0
    return out


def _response_stack(a: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    stack = np.empty((len(sigmas),) + a.shape, np.float32)
    smooth, done = a, 0.0
    for i, s in enumerate(sigmas):
        # Blur the previous level by the difference, not the original by the whole sigma: same
        # result (Gaussians compose in quadrature), shorter kernels.
        smooth = cv2.GaussianBlur(smooth, (0, 0), float(np.sqrt(s * s - done * done)))
        done = s
        stack[i] = -(s * s) * cv2.Laplacian(smooth, cv2.CV_32F, ksize=1)
    return stack


def _refine_centre(image: np.ndarray, u: float, v: float, radius: float, dark_balls: bool) -> tuple[float, float]:
    """Centroid of the shadow's attenuation against its own local background, in a disc of
    1.5 radii, re-centred three times.

    The background is a plane fitted to a ring around the shadow (it follows vignetting,
    glare and a plate's edge). In an intensity frame the weight is -ln(I / background):
    the ball's attenuation, whatever the brightness there. Weighing the darkness instead
    (background - I) scales each side of a shadow by the local brightness, and the
    intensifier's fall-off toward the edge then pulls every centre toward the middle of
    the field, by up to a tenth of a pixel, which is enough to bias fx and the principal
    point. A log-attenuation display (balls bright) is already additive: there the weight
    is the value above the plane.
    """
    a = np.asarray(image)
    rows, cols = a.shape
    for _ in range(3):
        half = int(np.ceil(2.4 * radius)) + 2
        u0, v0 = int(round(u)), int(round(v))
        ulo, uhi, vlo, vhi = max(u0 - half, 0), min(u0 + half + 1, cols), max(v0 - half, 0), min(v0 + half + 1, rows)
        patch = a[vlo:vhi, ulo:uhi].astype(np.float64)
        vv, uu = np.mgrid[vlo:vhi, ulo:uhi]
        r = np.hypot(uu - u, vv - v)
        ring = (r >= 1.7 * radius) & (r <= 2.3 * radius)
        disc = r <= 1.5 * radius
        if ring.sum() < 8 or disc.sum() < 4:
            break
        A = np.stack([uu[ring] - u, vv[ring] - v, np.ones(ring.sum())], axis=1)
        coef, *_ = np.linalg.lstsq(A, patch[ring], rcond=None)
        background = coef[0] * (uu - u) + coef[1] * (vv - v) + coef[2]
        if dark_balls:
            if not coef[2] > 0:
                break
            w = -np.log(np.clip(patch / np.maximum(background, 1e-12), 1e-6, None))
        else:
            w = patch - background
        w = np.clip(w, 0.0, None) * disc
        total = w.sum()
        if not total > 0:
            break
        u, v = float((w * uu).sum() / total), float((w * vv).sum() / total)
    return u, v


def detect_blobs(image: np.ndarray, fov: FieldOfView, detection: Detection) -> Blobs:
    """Ball shadows inside `fov`, strongest first.

    Whether the balls are dark (an intensity frame) or bright (a log display) is decided by
    the balls: blobs are sought both ways on the same scale-space stack, and the polarity
    whose round blobs of the phantom's sizes respond more strongly in all wins. An image's histogram tails
    cannot tell it: faint balls lose against noise, glare or a bright rim.
    """
    a = attenuation_image(image, fov, dark_balls=False)
    n_scales = int(np.ceil(np.log2(detection.max_diameter_px / detection.min_diameter_px) * detection.scales_per_octave)) + 1
    # One scale beyond each end, so a peak at the first or last wanted scale is a true maximum.
    step = 2.0 ** (1.0 / detection.scales_per_octave)
    sigmas = detection.min_diameter_px / SQRT8 * step ** np.arange(-1, n_scales + 1)
    stack = _response_stack(a, sigmas)
    inside = fov.mask(a.shape, margin_px=3.0)
    # A quarter of the pixels estimate the noise as well as all of them, four times faster.
    sample = inside[::2, ::2]
    noise = np.array([1.4826 * np.median(np.abs(s[::2, ::2][sample] - np.median(s[::2, ::2][sample]))) for s in stack])
    noise = np.maximum(noise, 1e-12)
    bright = _candidates(stack, sigmas, noise, inside, fov, detection, step)
    stack = np.negative(stack, out=stack)
    dark = _candidates(stack, sigmas, noise, inside, fov, detection, step)
    # The polarity with the stronger blobs in all wins, not the one with more: between the
    # balls of a dense grid the open field forms as many bright "blobs" as there are balls,
    # each far weaker than a ball's shadow.
    dark_balls = dark[2].sum() >= bright[2].sum()
    uv, d, strength = dark if dark_balls else bright
    # Two shadows close enough to share a centroid window or background ring (a steep tilt
    # lays one plate's ball beside the other's) would pull each other's centres: drop both.
    keep = ~crowded(uv, d)
    img = np.asarray(image, dtype=np.float32)
    refined = np.array([_refine_centre(img, u, v, r, dark_balls) for (u, v), r in zip(uv[keep], d[keep] / 2)]).reshape(-1, 2)
    return Blobs(refined, d[keep], strength[keep], int((~keep).sum()))


def _candidates(stack: np.ndarray, sigmas: np.ndarray, noise: np.ndarray, inside: np.ndarray, fov: FieldOfView,
                detection: Detection, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uv (n, 2), diameters (n,), strengths (n,)) of the round scale-space maxima of `stack`."""
    # 3x3x3 maxima of the scale-normalised response itself (Lindeberg), a 3x3 dilation per
    # scale compared with the scales either side; the noise only sets the threshold. Maxima
    # of the response over its noise would move to the finest scales where a dense grid of
    # balls fills the field, as the balls then lift every scale's noise estimate but the finest.
    kernel = np.ones((3, 3), np.uint8)
    dilated = np.stack([cv2.dilate(s, kernel) for s in stack])
    peaks = np.zeros(stack.shape, bool)
    for i in range(1, len(sigmas) - 1):
        s = stack[i]
        peaks[i] = ((s > detection.threshold_noise_sigmas * noise[i]) & (s >= dilated[i]) & (s >= dilated[i - 1])
                    & (s >= dilated[i + 1]) & inside)
    k, v, u = np.nonzero(peaks)
    strength = stack[k, v, u]
    order = np.argsort(-strength)
    k, v, u, strength = k[order], v[order], u[order], strength[order]

    kept_uv: list[tuple[float, float]] = []
    kept_d: list[float] = []
    kept_s: list[float] = []
    # Kept centres and diameters also as arrays, filled as they come: a grid phantom has
    # hundreds of balls, and a Python loop over the kept ones per candidate costs seconds.
    taken_uv, taken_d = np.empty((len(k), 2)), np.empty(len(k))
    for ki, vi, ui, si in zip(k, v, u, strength):
        # Parabolic peak in log(sigma) gives the size between scale samples.
        r0, r1, r2 = stack[ki - 1, vi, ui], stack[ki, vi, ui], stack[ki + 1, vi, ui]
        denom = r0 - 2 * r1 + r2
        offset = 0.5 * (r0 - r2) / denom if denom < 0 else 0.0
        sigma = sigmas[ki] * step ** float(np.clip(offset, -0.5, 0.5))
        diameter = SQRT8 * sigma
        if not detection.min_diameter_px <= diameter <= detection.max_diameter_px:
            continue
        n = len(kept_uv)
        if n and np.any(np.hypot(taken_uv[:n, 0] - ui, taken_uv[:n, 1] - vi) < 0.5 * (diameter + taken_d[:n])):
            continue
        if not _round_enough(stack[ki], int(ui), int(vi), detection.max_axis_ratio):
            continue
        radius = diameter / 2
        if fov.distance_inside(np.array([(ui, vi)], float))[0] < 1.5 * radius + detection.fov_margin_px:
            continue
        taken_uv[len(kept_uv)] = (ui, vi)
        taken_d[len(kept_uv)] = diameter
        kept_uv.append((float(ui), float(vi)))
        kept_d.append(diameter)
        kept_s.append(float(si))
    return (np.array(kept_uv, dtype=np.float64).reshape(-1, 2), np.array(kept_d, dtype=np.float64),
            np.array(kept_s, dtype=np.float64))


def _round_enough(response: np.ndarray, u: int, v: int, max_axis_ratio: float) -> bool:
    """Hessian of the response at the peak: a blob curves alike both ways, an edge does not."""
    rows, cols = response.shape
    if not (1 <= u < cols - 1 and 1 <= v < rows - 1):
        return False
    c = response[v, u]
    duu = response[v, u + 1] - 2 * c + response[v, u - 1]
    dvv = response[v + 1, u] - 2 * c + response[v - 1, u]
    duv = 0.25 * (response[v + 1, u + 1] - response[v + 1, u - 1] - response[v - 1, u + 1] + response[v - 1, u - 1])
    eig = np.linalg.eigvalsh(np.array([[duu, duv], [duv, dvv]]))
    if eig[1] >= 0:  # not a maximum in both directions
        return False
    return abs(eig[0]) <= max_axis_ratio * abs(eig[1])
