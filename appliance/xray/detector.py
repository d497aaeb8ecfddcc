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
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..config.fluoroscope import FluoroscopeProfile
from ..console.dose import reference_distance_mm
from ..patient.materials import ANODE_ANGLE_DEG, Spectrum, tube_spectrum, water_mu_per_mm
from ..patient.spekpy_beam import beam
from .casting import DetectorTables
from .pixel_geometry import field_edge, field_radius_px, penumbra_px, pixel_pitch_at_zoom_mm

#: A Gaussian blur narrower than this (sigma, pixels) changes a pixel by under a per cent of
#: its neighbours' difference and is left out.
BLUR_MIN_SIGMA_PX = 0.3

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


def _fluence_per_kerma(spectrum: Spectrum, water_mm: float) -> float:
    """Photon fluence over air kerma (arbitrary units) of a binned spectrum behind `water_mm` of
    water: the ratio between two kV values is what `open_photons_per_pixel` needs."""
    key = (spectrum.kvp, spectrum.filtration_mm_al, len(spectrum.energies_kev), float(spectrum.energies_kev[0]),
           round(water_mm, 3))
    if key not in _FPK:
        import xraylib

        e = spectrum.energies_kev
        through = spectrum.photons_per_mm2_per_mas * np.exp(-water_mm * np.array([water_mu_per_mm(x) for x in e]))
        mu_en = np.array([xraylib.CS_Energy_CP("Air, Dry (near sea level)", float(x)) for x in e])
        _FPK[key] = float(through.sum() / (through * e * mu_en).sum())
    return _FPK[key]


_FPK: dict[tuple, float] = {}

#: Along a kV-mA curve the control is satisfied within this fraction of the reference signal
#: (the kV steps of 1 kV move the signal by a few per cent; the mA between them is continuous).
CURVE_MATCH = 0.01


def _rising_root(f: Callable[[float], float], lo: float, hi: float, steps: int = 40) -> tuple[float, float]:
    """(a, b), b - a < 1e-11 of [lo, hi], about where the non-decreasing f crosses 0: f(a) < 0 <=
    f(b) (bisection; f(lo) < 0 <= f(hi)). f may jump (the kV steps): a stays below, b above."""
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if f(mid) < 0:
            lo = mid
        else:
            hi = mid
    return lo, hi


@dataclass(frozen=True)
class Exposure:
    """What the exposure control set for one frame."""

    factor: float           # air-kerma rate relative to the profile's reference technique (the dose follows it)
    attenuation: float      # median log-attenuation -ln(I/I0) over the measuring field, at the reference kV
    limited: bool           # True where the control ran into its lowest or highest output
    kvp: float | None = None    # the tube voltage it set (kV); None: the reference technique's
    ma: float | None = None     # the tube current it set (mA); None: the reference technique's times factor


class Detector:
    """The detector model of one fluoroscope profile (units in each method's docstring)."""

    def __init__(self, fluoroscope: FluoroscopeProfile, mu_water_per_mm: float):
        self.fl = fluoroscope
        self.chain = fluoroscope.image
        self.mu_water_per_mm = mu_water_per_mm
        self._gains: dict = {}
        self._fields: dict = {}      # (id(mask), sigma, zoom) -> (mask, field, 1 / blurred field, vignetting x field)

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

    def open_photons_per_pixel(self, zoom: int, mode: str | None = None, spectrum: Spectrum | None = None) -> float:
        """Photons one pixel would count in one frame with nothing in the beam, at the reference
        air-kerma rate (made at the reference technique, or with `spectrum`: another kV's).

        The air kerma per frame at the reference point (the profile's rate over the frame
        rate) carried to the detector by the inverse-square law, times spekpy's fluence per
        air kerma of the beam as it leaves the reference patient (reference_attenuation of
        water), times the pixel's area at the input plane at this zoom. At another kV the
        fluence per air kerma is spekpy's at the reference kV times the ratio of the two
        binned spectra's (see `_fluence_per_kerma`): spekpy per kV is too slow for a control loop.
        """
        f = self.fl
        kerma_ugy = (self.reference_rate_mgy_per_min(zoom, mode) * 1000.0 / 60.0 / self.frame_rate_per_s(mode)
                     * (reference_distance_mm(f) / f.geometry.source_to_image_mm) ** 2)
        water_mm = f.abc.reference_attenuation / self.mu_water_per_mm
        pitch = pixel_pitch_at_zoom_mm(f, zoom)
        per_kerma = fluence_per_air_kerma(float(f.tube.kvp), float(f.tube.filtration_mm_al), water_mm)
        if spectrum is not None and spectrum.kvp != float(f.tube.kvp):
            reference = tube_spectrum(f.tube, len(spectrum.energies_kev) or 24)
            per_kerma *= _fluence_per_kerma(spectrum, water_mm) / _fluence_per_kerma(reference, water_mm)
        return kerma_ugy * per_kerma * pitch * pitch

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

    def exposure_on_curve(self, lines: np.ndarray, gain: np.ndarray | None, zoom: int, mode: str | None,
                          tables: Callable[[float], DetectorTables]) -> Exposure:
        """The exposure control with a kV-mA curve (abc.curve): the lowest point of the curve at
        which the detector signal over the measuring field reaches the reference patient's at
        the reference technique, within the dose-rate limit.

        `lines`: (n, 4) material integrals sampled over the measuring field; `gain`: the
        vignetting there (None: none); `tables(kvp)`: the detector tables at a tube voltage.
        The signal at (kV, mA) is mA x the open-field signal per mAs at that kV (spekpy) x
        the median transmission of the sampled rays at that kV's spectrum; the air-kerma rate
        relative to the reference technique, `factor`, is mA x air kerma per mAs at that kV
        over the same at the reference technique."""
        tube, abc = self.fl.tube, self.fl.abc
        curve = abc.curve
        ref = tables(float(tube.kvp))
        g = 1.0 if gain is None else gain

        @functools.cache
        def transmission(kv: float) -> float:
            return float(np.median(tables(kv).transmission(lines) * g))

        def at(x: float) -> tuple[float, float]:
            i = min(int(x), len(curve) - 2)
            w = x - i
            a, b = curve[i], curve[i + 1]
            return round(a.kvp + w * (b.kvp - a.kvp)), a.ma + w * (b.ma - a.ma)

        @functools.cache
        def per_mas(kv: float) -> float:       # the bisection asks each kV dozens of times
            return tables(kv).spectrum.detector_signal_per_mas() * transmission(kv)

        def signal(x: float) -> float:
            kv, ma = at(x)
            return ma * per_mas(kv)

        @functools.cache
        def kerma_per_mas(kv: float) -> float:
            return tables(kv).spectrum.air_kerma_ugy_per_mas

        def factor(x: float) -> float:
            kv, ma = at(x)
            return ma * kerma_per_mas(kv) / (tube.ma * ref.spectrum.air_kerma_ugy_per_mas)

        top = float(len(curve) - 1)
        ceiling = self.chain.dose_rate_limit_mgy_per_min / self.reference_rate_mgy_per_min(zoom, mode)
        # Never above the limit: the last point below it.
        x_max = top if factor(top) <= ceiling else _rising_root(lambda x: factor(x) - ceiling, 0.0, top)[0]
        target = tube.ma * ref.spectrum.detector_signal_per_mas() * math.exp(-abc.reference_attenuation)
        if signal(0.0) >= target:
            x, limited = 0.0, signal(0.0) > target * (1.0 + CURVE_MATCH)
        elif signal(x_max) <= target:
            x, limited = x_max, signal(x_max) < target * (1.0 - CURVE_MATCH)
        else:
            x, limited = _rising_root(lambda x: signal(x) - target, 0.0, x_max)[1], False
        kv, ma = at(x)
        # The generator sets kV in 1 kV steps and trims the mA within a step: to the reference
        # signal where the curve reaches it, else to the dose-rate limit where that stopped it.
        t = tables(kv).spectrum
        exact = target / (t.detector_signal_per_mas() * max(transmission(kv), 1e-300))
        capped = ceiling * tube.ma * ref.spectrum.air_kerma_ugy_per_mas / t.air_kerma_ugy_per_mas
        if not limited:
            ma = min(exact, capped)
        elif x == x_max < top:
            ma = capped
        rate = ma * t.air_kerma_ugy_per_mas / (tube.ma * ref.spectrum.air_kerma_ugy_per_mas)
        attenuation = -math.log(max(transmission(float(tube.kvp)), 1e-12))
        return Exposure(rate, attenuation, limited or ma == capped < exact, float(kv), float(ma))

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

        Blurs see the field as it is: outside the beam is no signal, before and after. Glare keeps the mean
        signal and moves `veiling_glare` of it into a broad halo (computed on a coarse grid:
        the halo has no fine detail).
        """
        import cv2

        sigma, field, inv_weight, gain = self.field_weights(mask, zoom)
        out = cv2.multiply(np.asarray(image, dtype=np.float32), field)
        if sigma > BLUR_MIN_SIGMA_PX:
            # Normalised by the blurred field, so the blur mixes no darkness into the field's
            # edge: the edge's fall-off is the aperture's own (see `edge`).
            out = cv2.multiply(cv2.GaussianBlur(out, (0, 0), sigma), inv_weight)
        glare = self.glare(zoom, out.shape)
        if glare is not None:
            g, (small_rows, small_cols), small_sigma = glare
            rows, cols = out.shape
            small = cv2.resize(out, (small_cols, small_rows), interpolation=cv2.INTER_AREA)
            small = cv2.GaussianBlur(small, (0, 0), small_sigma)
            halo = cv2.resize(small, (cols, rows), interpolation=cv2.INTER_LINEAR)
            out = cv2.addWeighted(out, 1.0 - g, halo, g, 0.0)
        return cv2.multiply(out, gain)

    def glare(self, zoom: int, shape: tuple[int, int]) -> tuple[float, tuple[int, int], float] | None:
        """The veiling glare of `spread` on a (rows, cols) image: its fraction, the coarse grid
        (rows, cols) the halo is blurred on and the blur's sigma there; None for no glare."""
        g = self.chain.veiling_glare
        if g <= 0:
            return None
        halo_px = self.chain.glare_sigma_mm / pixel_pitch_at_zoom_mm(self.fl, zoom)
        step = max(1, int(halo_px // 4))
        rows, cols = shape
        return g, (max(1, rows // step), max(1, cols // step)), max(halo_px / step, 0.5)

    def field_weights(self, mask: np.ndarray, zoom: int) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """`spread`'s point-spread sigma (pixels) and its field weights for `mask` (see `_field_weights`)."""
        sigma = self.psf_sigma_px(zoom)
        return (sigma, *self._field_weights(mask, sigma, zoom))

    def _field_weights(self, mask: np.ndarray, sigma: float, zoom: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The field as float32 1/0, the reciprocal of its blur at `sigma` (floored at 1e-3) and
        the vignetting times the field (no signal outside it): the same for every frame of one
        field, so made once per mask."""
        import cv2

        key = (id(mask), round(sigma, 6), zoom)
        held = self._fields.get(key)
        if held is None or held[0] is not mask:
            if len(self._fields) > 16:
                self._fields.clear()
            field = mask.astype(np.float32)
            inv = field
            if sigma > BLUR_MIN_SIGMA_PX:
                inv = (1.0 / np.maximum(cv2.GaussianBlur(field, (0, 0), sigma), np.float32(1e-3))).astype(np.float32)
            gain = self.gain(zoom)
            held = self._fields[key] = (mask, field, inv, field if gain is None else (field * gain).astype(np.float32))
        return held[1], held[2], held[3]

    def edge(self, mask: np.ndarray, zoom: int) -> np.ndarray:
        """(rows, cols) float32 weight in [0, 1] of the field's edge at `zoom` (casting.field_edge
        over image.field_edge_mm): the blurred shadow of the aperture and blades, one half at
        the geometric edge of `mask`, 0 beyond the penumbra."""
        return field_edge(mask, penumbra_px(self.fl, zoom))


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
        # Where a GPU's frames run through it (device_chain.py): (chain, buffer, shape) of the
        # state on the device instead of _state; one of the two holds it.
        self._on_device: tuple | None = None
        self._key = None

    def reset(self) -> None:
        self._state = None
        self._on_device = None

    def _host_state(self) -> np.ndarray | None:
        if self._on_device is not None:
            chain, buf, shape = self._on_device
            self._state, self._on_device = chain.download(buf, shape), None
        return self._state

    def carry_over(self, other: RecursiveFilter, shape: tuple[int, int]) -> None:
        """Go on from `other`'s state resampled to `shape` (rows, cols): the same field read out
        at another matrix (progressive.py), so the change of matrix runs through the filter
        like any other new frame instead of restarting it."""
        import cv2

        state = other._host_state()
        if state is None or other._key is None:
            self.reset()
            return
        rows, cols = shape
        self._state = cv2.resize(state, (cols, rows), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        self._on_device = None
        self._key = (*other._key[:-1], (rows, cols))

    def step(self, frame: np.ndarray, key) -> np.ndarray:
        state = self._host_state()
        if self.weight == 0 or state is None or key != self._key or state.shape != frame.shape:
            self._state, self._key = frame.astype(np.float32, copy=True), key
            return self._state.copy()
        state *= np.float32(self.weight)
        state += np.float32(1.0 - self.weight) * frame
        return state.copy()

    def step_on_device(self, chain, frame, shape: tuple[int, int], key):
        """`step` on a device buffer of `shape` (device_chain.DeviceChain `chain`): the state
        stays on the device; returns the buffer of the filtered frame, valid until the next step."""
        n = shape[0] * shape[1]
        if self._on_device is None and self._state is not None and self._state.shape == shape and key == self._key:
            self._on_device, self._state = (chain, chain.upload(self._state), shape), None     # carried over
        held = self._on_device
        if self.weight == 0 or held is None or key != self._key or held[2] != shape or held[0] is not chain:
            self._on_device, self._state, self._key = (chain, chain.copy(frame, n), shape), None, key
            return frame
        chain.recursive(held[1], frame, n, self.weight)
        return held[1]
