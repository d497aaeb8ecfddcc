"""The detector and its exposure control: photons, quantum noise, point-spread, veiling glare,
vignetting, the automatic exposure (brightness) control and the recursive temporal filter.

Works on the relative detector signal of `casting.Caster.intensity` (1 = open beam) in
NumPy and OpenCV; only the Poisson sampling runs on the OpenCL device (kernel
quantum_noise of drr.cl). Order, as in a real chain: focal-spot blur of the radiation
image -> photons counted (noise) -> the detector's own point-spread -> veiling glare ->
vignetting -> recursive filter.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..config.fluoroscope import FluoroscopeProfile
from ..console.dose import reference_distance_mm
from ..patient.materials import ANODE_ANGLE_DEG
from ..patient.spekpy_beam import beam
from .casting import field_radius_px, pixel_pitch_at_zoom_mm

#: MTF of the detector at its stated limiting resolution: the contrast at which the bars of
#: a resolution pattern can no longer be told apart.
MTF_AT_LIMIT = 0.04
#: Gaussian sigma (mm) times the limiting frequency (lp/mm) for that MTF: exp(-2 pi^2 s^2 f^2) = MTF.
_SIGMA_TIMES_F = math.sqrt(math.log(1.0 / MTF_AT_LIMIT) / (2.0 * math.pi ** 2))


@functools.lru_cache(maxsize=32)
def fluence_per_air_kerma(kvp: float, filtration_mm_al: float, water_mm: float) -> float:
    """Photons per mm^2 per uGy of air kerma of the tube's beam after `water_mm` of water
    (spekpy: fluence over air kerma of the same spectrum)."""
    b = beam(kvp, ANODE_ANGLE_DEG, 0.5, (("Al", filtration_mm_al), ("Water, Liquid", water_mm)))
    return b.fluence_per_cm2_per_mas / b.air_kerma_ugy_per_mas / 100.0   # /cm^2 per uGy -> /mm^2 per uGy


@dataclass(frozen=True)
class Exposure:
    """What the exposure control set for one frame."""

    factor: float           # tube output (mA x pulse width) relative to the profile's reference technique
    attenuation: float      # median log-attenuation -ln(I/I0) over the measuring field
    limited: bool           # True where the control ran into its lowest or highest output


class Detector:
    """The detector model of one fluoroscope profile (units in each method's docstring)."""

    def __init__(self, fluoroscope: FluoroscopeProfile, mu_water_per_mm: float):
        self.fl = fluoroscope
        self.chain = fluoroscope.image
        self.mu_water_per_mm = mu_water_per_mm
        self._gains: dict = {}

    # -- photons ---------------------------------------------------------------------
    def frame_rate_per_s(self, mode: str | None) -> float:
        m = self._mode(mode)
        return float(m.pulse_rate_per_s) if getattr(m, "pulse_rate_per_s", None) else self.chain.frame_rate_per_s

    def _mode(self, mode: str | None):
        modes = {m.name: m for m in self.fl.tube.modes}
        return modes.get(mode or "", self.fl.tube.modes[0])

    def reference_rate_mgy_per_min(self, zoom: int, mode: str | None) -> float:
        """The profile's air-kerma rate at the reference point for the reference patient (mGy/min)."""
        return float(self.fl.zoom_levels[zoom - 1].air_kerma_rate_mgy_per_min[self._mode(mode).name])

    def open_photons_per_pixel(self, zoom: int, mode: str | None = None) -> float:
        """Photons one pixel would count in one frame with nothing in the beam, at the reference technique.

        The air kerma per frame at the reference point (the profile's rate over the frame
        rate) carried to the detector by the inverse-square law, times spekpy's fluence per
        air kerma of the beam as it leaves the reference patient (reference_attenuation of
        water), times the pixel's area at the input plane at this zoom.
        """
        f = self.fl
        kerma_ugy = (self.reference_rate_mgy_per_min(zoom, mode) * 1000.0 / 60.0 / self.frame_rate_per_s(mode)
                     * (reference_distance_mm(f) / f.geometry.source_to_image_mm) ** 2)
        water_mm = f.abc.reference_attenuation / self.mu_water_per_mm
        pitch = pixel_pitch_at_zoom_mm(f, zoom)
        return kerma_ugy * fluence_per_air_kerma(float(f.tube.kvp), float(f.tube.filtration_mm_al), water_mm) * pitch * pitch

    # -- exposure control --------------------------------------------------------------
    def exposure(self, measured_intensity: float, zoom: int, mode: str | None = None) -> Exposure:
        """The automatic exposure control's answer to the median relative intensity over its
        measuring field: the tube output that brings the detector signal there back to the
        reference patient's, exp(attenuation - reference), within the tube's range and the
        dose-rate limit."""
        abc = self.fl.abc
        attenuation = -math.log(max(measured_intensity, 1e-12))
        wanted = math.exp(min(attenuation - abc.reference_attenuation, 50.0))
        ceiling = min(abc.max_factor, self.chain.dose_rate_limit_mgy_per_min / self.reference_rate_mgy_per_min(zoom, mode))
        factor = min(max(wanted, abc.min_factor), ceiling)
        return Exposure(factor, attenuation, limited=factor != wanted)

    # -- blur, glare, vignetting --------------------------------------------------------
    def psf_sigma_px(self, zoom: int) -> float:
        """Gaussian sigma (pixels) of the detector's point-spread at `zoom`, from its limiting resolution."""
        f_lim = self.chain.limiting_resolution_lp_per_mm[zoom - 1]
        return _SIGMA_TIMES_F / f_lim / pixel_pitch_at_zoom_mm(self.fl, zoom)

    def focal_blur_px(self, zoom: int, depth_mm: float | None = None) -> float:
        """Gaussian sigma (pixels) of the focal spot's penumbra for an object `depth_mm` from the
        source (default: the isocentre): spot size x (SID - depth) / depth, taken as the FWHM."""
        f = self.fl
        sid = f.geometry.source_to_image_mm
        depth = f.geometry.source_to_isocentre_mm if depth_mm is None else min(max(depth_mm, 1.0), sid)
        return f.tube.focal_spot_mm * (sid - depth) / depth / pixel_pitch_at_zoom_mm(f, zoom) / 2.3548

    def gain(self, zoom: int) -> np.ndarray | None:
        """Intensifier vignetting as a multiplicative gain, 1 at the centre (None for none)."""
        det = self.fl.detector
        if det.kind != "image_intensifier" or det.vignetting == 0:
            return None
        if zoom not in self._gains:
            rows, cols = det.rows, det.columns
            r = field_radius_px(self.fl)
            v = np.arange(rows) - (rows - 1) / 2.0
            u = np.arange(cols) - (cols - 1) / 2.0
            rr = (v[:, None] ** 2 + u[None, :] ** 2) / (r * r)
            self._gains[zoom] = (1.0 - det.vignetting * np.minimum(rr, 1.0)).astype(np.float32)
        return self._gains[zoom]

    def spread(self, image: np.ndarray, mask: np.ndarray, zoom: int) -> np.ndarray:
        """The detector's own point-spread and veiling glare on a (noisy) signal, and its vignetting.

        Blurs see the field as it is: outside the beam is no signal. Glare keeps the mean
        signal and moves `veiling_glare` of it into a broad halo (computed on a coarse grid:
        the halo has no fine detail).
        """
        import cv2

        out = np.where(mask, image, np.float32(0)).astype(np.float32)
        sigma = self.psf_sigma_px(zoom)
        if sigma > 0.3:
            # Normalised by the blurred field, so the blur mixes no darkness into the field's
            # edge: the edge's fall-off is the aperture's own (see `edge`).
            weight = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), sigma)
            out = cv2.GaussianBlur(out, (0, 0), sigma) / np.maximum(weight, np.float32(1e-3))
        g = self.chain.veiling_glare
        if g > 0:
            halo_px = self.chain.glare_sigma_mm / pixel_pitch_at_zoom_mm(self.fl, zoom)
            step = max(1, int(halo_px // 4))
            rows, cols = out.shape
            small = cv2.resize(out, (max(1, cols // step), max(1, rows // step)), interpolation=cv2.INTER_AREA)
            small = cv2.GaussianBlur(small, (0, 0), max(halo_px / step, 0.5))
            halo = cv2.resize(small, (cols, rows), interpolation=cv2.INTER_LINEAR)
            out = (1.0 - g) * out + g * halo
        gain = self.gain(zoom)
        if gain is not None:
            out = out * gain
        return out.astype(np.float32)

    def edge(self, mask: np.ndarray, zoom: int) -> np.ndarray:
        """(rows, cols) float32 weight in [0, 1]: 1 well inside the field, falling smoothly
        toward the edge of the beam (the blurred shadow of the aperture and blades) to one half
        at the geometric edge, so the edge is where calibration finds it; 0 outside the beam.
        The fall spans half of field_edge_mm inside the field (the half outside the beam has
        no rays cast)."""
        import cv2

        half_px = 0.5 * self.chain.field_edge_mm / pixel_pitch_at_zoom_mm(self.fl, zoom)
        if half_px < 0.25:
            return mask.astype(np.float32)
        # Distance (px) of each in-beam pixel centre from the edge: the boundary pixel's is 0.5.
        # The frame's border counts as outside: where the circle meets it, it fades as elsewhere.
        padded = np.pad(mask.astype(np.uint8), 1)
        inside = cv2.distanceTransform(padded, cv2.DIST_L2, 5)[1:-1, 1:-1] - np.float32(0.5)
        t = np.clip(inside / np.float32(half_px), 0.0, 1.0)
        w = 0.5 + 0.5 * t * t * (3.0 - 2.0 * t)
        return np.where(mask, w, np.float32(0)).astype(np.float32)


def settled_noise_gain(weight: float) -> float:
    """Photons that give one unfiltered frame the noise of the recursive filter's output once
    the scene has been still for many frames: its variance is (1 - w) / (1 + w) of one frame's."""
    return (1.0 + weight) / (1.0 - weight)


class RecursiveFilter:
    """y_n = w y_(n-1) + (1 - w) x_n on the detector signal, as a clinical unit's frame
    integrator does: it averages out quantum mottle while the C-arm is still and leaves a
    fading trail when it moves. A change of field (zoom, collimation, matrix) restarts it."""

    def __init__(self, weight: float):
        self.weight = float(weight)
        self._state: np.ndarray | None = None
        self._key = None

    def reset(self) -> None:
        self._state = None

    def carry_over(self, other: RecursiveFilter, shape: tuple[int, int]) -> None:
        """Go on from `other`'s state resampled to `shape` (rows, cols): the same field read out
        at another matrix (progressive.py), so the change of matrix runs through the filter
        like any other new frame instead of restarting it."""
        import cv2

        if other._state is None or other._key is None:
            self.reset()
            return
        rows, cols = shape
        self._state = cv2.resize(other._state, (cols, rows), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        self._key = (*other._key[:-1], (rows, cols))

    def step(self, frame: np.ndarray, key) -> np.ndarray:
        if self.weight == 0 or self._state is None or key != self._key or self._state.shape != frame.shape:
            self._state, self._key = frame.astype(np.float32, copy=True), key
            return self._state.copy()
        self._state *= np.float32(self.weight)
        self._state += np.float32(1.0 - self.weight) * frame
        return self._state.copy()
