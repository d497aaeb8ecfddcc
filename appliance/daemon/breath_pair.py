"""The demo's breathing pair, measured: how far the diaphragm's dome moved on the detector
between the end-expiration and the end-inspiration images, against what the case's
`respiration.diaphragm_mm` predicts through the pose (the pinhole's SID/SOD magnification).

The prediction projects the dome's apex and the apex moved down by the tendon's descent
between the two breaths (diaphragm_mm times the change in `inspired`, the intercostal share
applied as the breathing model applies it) with the pose of the pair. The measurement reads
the two rendered images only, along the projected direction of that motion, in bands of
profiles across it through and beside the projected apex.

Why the difference of the two profiles and not each image's strongest step: the dome's
shadow is a ramp (a curved surface seen edge-on: the liver's chord grows over millimetres
below the apex), while the ribs' shadows have sharp edges and hardly move. On the
displayed image, where the beam's low energies make bone three times as dark per gram as
soft tissue, a rib's edge beside the dome is the strongest step; picking it read the
demo's pair 20 % long. In the difference the still ribs cancel and what remains is the band
the dome swept, its front the expiration apex and its back the inspiration apex, each with
the same ramp's shape (the dome moved as a whole), so the same edge finder places both
alike. The band is smoothed on its own scale first, so the thin slivers of the ribs' own few
pixels of motion do not place it. Pixels are turned into millimetres at the detector with
the rendered matrix's pitch at the zoom used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config.base import matrix
from ..patient.respiration import muscle_amplitudes
from ..teaching.views import Beam, view_detail
from .snapshots import KeptFrame

#: Half-width (px) of the band of profiles averaged across the motion, and how far beyond
#: the predicted motion the edge is looked for (px), so the search does not presume the answer.
BAND_PX = 6
SEARCH_MARGIN_PX = 12
#: Half-width (px) of the gradient's peak whose centroid places an edge: a few pixels, about a
#: blurred dome edge's width, narrower than the ribs' spacing.
EDGE_HALF_WIDTH_PX = 3.0
#: Bands beside the apex's (px across the motion): the dome's outline is measured along them
#: too and the median taken, so a rib crossing one band does not set the reading.
BAND_OFFSETS_PX = tuple(range(-24, 25, 6))
#: The swept band is smoothed by a Gaussian of its own width over this (sigma px = width /
#: this): wide enough to drown the ribs' slivers, narrow enough that the band's two edges stay
#: apart. Measured on the built-in child at three poses, full and half breaths, line-integral,
#: intensity and displayed images (tests/test_breath_pair.py).
SMOOTHING_PER_WIDTH = 7.0
#: The smoothing's width is taken from the reading itself, refined this many times from the
#: prediction's, so a band narrower or wider than predicted is read on its own scale.
REFINEMENTS = 2
#: Profiles are sampled this finely (px): an edge's centroid window of whole samples is off
#: its peak by up to half a sample, on each of the band's two edges.
STEP_PX = 0.05


@dataclass(frozen=True)
class PairCheck:
    predicted_px: float
    measured_px: float
    mm_per_px: float              # at the detector, this matrix and zoom
    descent_mm: float             # the tendon's descent between the two images (patient mm)
    magnification: float          # SID / distance of the apex from the focal spot

    @property
    def predicted_mm(self) -> float:
        return self.predicted_px * self.mm_per_px

    @property
    def measured_mm(self) -> float:
        return self.measured_px * self.mm_per_px

    def line(self) -> str:
        err = (self.measured_px / self.predicted_px - 1.0) * 100.0 if self.predicted_px else float("nan")
        return (f"dome moved {self.measured_mm:.1f} mm on the detector ({self.measured_px:.1f} px); predicted "
                f"{self.predicted_mm:.1f} mm = {self.descent_mm:.1f} mm descent x {self.magnification:.2f} "
                f"magnification ({err:+.0f} %)")


def _profile(image: np.ndarray, origin: np.ndarray, along: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Mean of the image along `along` at offsets `s` (px) from `origin`, over +-BAND_PX across it (bilinear)."""
    import cv2

    across = np.array([-along[1], along[0]])
    offsets = np.arange(-BAND_PX, BAND_PX + 1, dtype=float)
    pts = origin[None, None, :] + s[:, None, None] * along + offsets[None, :, None] * across
    xy = pts.astype(np.float32)
    sampled = cv2.remap(np.ascontiguousarray(image, dtype=np.float32), xy[..., 0], xy[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
    return sampled.mean(axis=1)


def _edge(profile: np.ndarray, s: np.ndarray, window: tuple[float, float], sign: float | None) -> tuple[float, float]:
    """(position px, signed step) of the strongest step of `profile` inside `window`: the centroid
    of the gradient over +-EDGE_HALF_WIDTH_PX about its peak (a bilinear profile's gradient is flat
    within each pixel, so its peak alone is good to half a pixel only)."""
    g = np.gradient(profile, s)
    inside = (s >= window[0]) & (s <= window[1])
    oriented = g * sign if sign is not None else np.abs(g)
    k = int(np.argmax(np.where(inside, oriented, -np.inf)))
    pos = float(s[k])
    for _ in range(4):          # recentred: a window off the peak pulls the centroid toward its middle
        near = inside & (np.abs(s - pos) <= EDGE_HALF_WIDTH_PX)
        w = np.clip(np.where(near, oriented, 0.0), 0.0, None)
        if w.sum() <= 0:
            break
        pos = float((w * s).sum() / w.sum())
    return pos, float(g[k])


def _swept_band(before: np.ndarray, after: np.ndarray, s: np.ndarray, width_px: float) -> tuple[float, float]:
    """(front, back) px of the band the dome swept: the difference `before - after` oriented
    so that the band is positive, smoothed by width_px / SMOOTHING_PER_WIDTH."""
    from scipy.ndimage import gaussian_filter1d

    _, step = _edge(before, s, (-SEARCH_MARGIN_PX, SEARCH_MARGIN_PX), None)
    band = (before - after) * np.sign(step)
    sigma_px = width_px / SMOOTHING_PER_WIDTH
    if sigma_px > 0.5:
        band = gaussian_filter1d(band, sigma_px / float(s[1] - s[0]), mode="nearest")
    front, _ = _edge(band, s, (-SEARCH_MARGIN_PX, SEARCH_MARGIN_PX), 1.0)
    back, _ = _edge(band, s, (front + 2.0, front + 2 * width_px + SEARCH_MARGIN_PX), -1.0)
    return front, back


def dome_shift(cfg, fluoroscope, expiration: KeptFrame, inspiration: KeptFrame, apex_ct) -> PairCheck | None:
    """The dome's motion between the pair (rendered with `fluoroscope`, the profile as read out),
    or None where the case has no breathing model or a frame lacks its breath."""
    r = cfg.case.respiration
    if r is None or expiration.inspired is None or inspiration.inspired is None:
        return None
    descent = muscle_amplitudes(r)[2] * (inspiration.inspired - expiration.inspired)
    T = fluoroscope.T_xray_from_webcam() @ expiration.T_webcam_from_phantom @ matrix(cfg.case.T_phantom_from_ct)
    beam = Beam.of(view_detail(fluoroscope, T, expiration.zoom, None, None))
    apex = np.asarray(apex_ct, dtype=float)
    moved = apex - [0.0, 0.0, descent]
    det = beam.detector_mm(np.vstack([apex, moved]))
    if not np.isfinite(det).all():
        return None
    cam = beam.camera
    rows, cols = expiration.image.shape
    mm_per_px = cam["pixel_pitch_mm"] * cam["columns"] / cols * beam.fov_mm / cam["fovs_mm"][0]
    centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
    a_px, m_px = centre + det[0] / mm_per_px, centre + det[1] / mm_per_px
    predicted = float(np.linalg.norm(m_px - a_px))
    if predicted < 1.0:
        return None
    along = (m_px - a_px) / predicted
    across = np.array([-along[1], along[0]])
    s = np.arange(-3 * SEARCH_MARGIN_PX, 2 * predicted + 3 * SEARCH_MARGIN_PX, STEP_PX)
    profiles = [(_profile(expiration.image, a_px + o * across, along, s),
                 _profile(inspiration.image, a_px + o * across, along, s)) for o in BAND_OFFSETS_PX]
    width = predicted
    for _ in range(REFINEMENTS + 1):
        shifts = [back - front for front, back in (_swept_band(b, a, s, width) for b, a in profiles)]
        width = max(float(np.median(shifts)), 1.0)
    z_apex = float((T[:3, :3] @ apex + T[:3, 3])[2])
    return PairCheck(predicted, float(np.median(shifts)), mm_per_px, descent, cam["sid_mm"] / z_apex)


def builtin_apex(case) -> tuple[float, float, float] | None:
    """The right dome's apex at end-expiration (CT mm) of the built-in child; None for another case,
    whose dome the demo does not know."""
    if case.builtin != "child-torso":
        return None
    from ..patient.anatomy import RIGHT_DOME
    return RIGHT_DOME


def pair_lines(cfg, fluoroscope, kept: dict[str, KeptFrame]) -> list[str]:
    """The demo summary's lines about the breathing pair (none when there is no pair to measure)."""
    e, i = kept.get("end-expiration"), kept.get("end-inspiration")
    apex = builtin_apex(cfg.case)
    if e is None or i is None or apex is None:
        return []
    check = dome_shift(cfg, fluoroscope, e, i, apex)
    if check is None:
        return []
    return [f"breathing pair:     inspired {e.inspired:.3f} -> {i.inspired:.3f}, one pose; " + check.line()]
