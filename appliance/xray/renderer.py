"""The DRR engine: one X-ray image of a CT phase, from the rays to the monitor's grey scale.

It strings together the three jobs, each in its own module:
  - `device`: the OpenCL device and the programs of drr.cl;
  - `casting`: the rays of the fluoroscope's pixels through the CT and the detector's
    signal relative to the open beam (Joseph or Siddon, mono- or polychromatic);
  - `detector` and `display_lut`: exposure control, photons and quantum noise, the
    detector's point-spread, veiling glare, vignetting, the recursive filter, the soft
    field edge, the log display with its window and the polarity (invert's one owner).

`render` returns a `Frame`: the image with what the exposure control set for it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..config.case import Contrast, Materials
from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError
from ..patient.volume import Volume, padding_as_air
from .casting import EMPTY_MAX_HU, ENERGY_BINS, PACKET, PAD, Caster, PreparedVolume
from .detector import BLUR_MIN_SIGMA_PX, Detector, Exposure, RecursiveFilter, settled_noise_gain
from .device import ClDevice, pick_device
from .device_chain import SOURCE, DeviceChain
from .display_lut import WINDOW_STEP, auto_window, to_display, unsharp, window_of
from .pixel_geometry import at_resolution, field_mask, measuring_field, pixel_pitch_at_zoom_mm, ray_directions, zoomed_K
from .slabs import LAYOUT_PHASES, SlabCache

__all__ = ["EMPTY_MAX_HU", "ENERGY_BINS", "PACKET", "PAD", "QUANTITIES", "Frame", "PreparedVolume", "Renderer", "View",
           "at_resolution", "field_mask", "measuring_field", "pick_device", "ray_directions", "zoomed_K"]

log = logging.getLogger(__name__)

QUANTITIES = ("display", "intensity", "line-integral")
#: How a display frame meets the recursive filter: "live" runs it over successive frames
#: (the trail when the C-arm moves), "settled" shows the still scene after the filter has
#: settled (its noise, one render), "off" leaves it out.
TEMPORAL = ("live", "settled", "off")


@dataclass
class View:
    """What the console asks of one frame."""

    zoom: int = 1                       # 1..4, index+1 into fluoroscope.zoom_levels
    collimation_mm: tuple[float, float] | None = None  # (horizontal, vertical) blade opening at the detector plane, mm; None = fully open
    invert: bool = False
    noise: bool = True
    quantity: str = "display"           # "display" | "intensity" | "line-integral"
    seed: int | None = None
    polychromatic: bool = True          # False: one bin at the spectrum's effective energy
    temporal: str = "settled"           # see TEMPORAL
    mode: str | None = None             # fluoroscopy mode (sets the frame rate, hence photons per frame); None = the first
    window_scale: float = 1.0           # the radiographer's window: width times this
    level_shift: float = 0.0            # the radiographer's level: centre moved by this fraction of the width


@dataclass(frozen=True)
class Frame:
    """One rendered image and the technique it was made with."""

    image: np.ndarray                   # (rows, cols) float32: the quantity asked for
    exposure_factor: float = 1.0        # tube output relative to the reference technique (the dose rate follows it)
    attenuation: float | None = None    # median -ln(I/I0) over the measuring field, as the exposure control saw it
    limited: bool = False               # the exposure control was at its lowest or highest output
    photons_per_pixel: float = 0.0      # photons per pixel per frame in the measuring field (median of its sample)
    window: tuple[float, float] | None = None   # (centre, width) of the display window on -ln(I/I0)
    signal: np.ndarray | None = None    # display frames: the detector signal (after the recursive filter) the LUT was given
    kvp: float | None = None            # the tube voltage the exposure control set (kV); None: the profile's tube.kvp
    ma: float | None = None             # the tube current it set (mA); None: tube.ma x exposure_factor


def _device_chain(dev) -> DeviceChain | None:
    """The detector's kernels on `dev`, or None (the host's chain) where its compiler refuses
    them: a display frame then costs what it did before, and the technician reads why."""
    try:
        return DeviceChain(dev)
    except dev.cl.Error as e:
        log.warning("the detector stays on the host: %s cannot build %s (%s)", dev.device.name.strip(),
                    SOURCE.name, str(e).strip().splitlines()[0][:200])
        return None


class Renderer:
    """Renders X-ray images of prepared CT phases for one fluoroscope and one case's materials."""

    def __init__(self, fluoroscope: FluoroscopeProfile, materials: Materials, contrast: Contrast | None = None,
                 device: str = "auto", packet: bool | None = None, device_chain: bool | None = None):
        """`device`: "auto" (a GPU if present, else PoCL's CPU device), "cpu" or "gpu".
        `packet`: use the 16-pixel vector kernel (default: on CPU devices). `device_chain`: run
        a display frame's detector on the device (device_chain.py; default: on GPUs)."""
        self.dev = ClDevice(device)
        self.device = self.dev.device
        self._lock: threading.Lock = self.dev.lock
        self._noise = self.dev.kernel("quantum_noise_packet" if self.dev.is_cpu else "quantum_noise")
        self._seeds = np.random.default_rng()        # a fresh noise pattern each frame unless View.seed
        self.caster = Caster(self.dev, fluoroscope, materials, contrast, packet,
                             layouts=SlabCache(self.dev, LAYOUT_PHASES, thickness=1))
        self.packet = self.caster.packet
        self.chain = _device_chain(self.dev) if (not self.dev.is_cpu if device_chain is None else device_chain) else None
        self.materials, self.contrast = materials, contrast
        self._owner_id = id(self)                # prepared volumes serve this renderer and its other matrices
        self._matrices: dict[tuple[int, int], Renderer] = {}
        self._adopt(fluoroscope)

    # -- profile ---------------------------------------------------------------------
    def set_fluoroscope(self, fluoroscope: FluoroscopeProfile) -> None:
        """Adopt a (reloaded) fluoroscope profile: spectrum, attenuation tables, ray maps, detector."""
        with self._lock:
            self.caster.set_fluoroscope(fluoroscope)
            self._adopt(fluoroscope)
            self._matrices.clear()

    def _adopt(self, fluoroscope: FluoroscopeProfile) -> None:
        self.fluoroscope = fluoroscope
        self.spectrum = self.caster.spectrum
        self.mu_water_per_mm = self.caster.mu_water_per_mm
        self.detector = Detector(fluoroscope, self.mu_water_per_mm)
        self.lag = RecursiveFilter(fluoroscope.image.recursive_weight)
        self._edges: dict = {}

    @property
    def shape(self) -> tuple[int, int]:
        return self.fluoroscope.detector.rows, self.fluoroscope.detector.columns

    # -- volumes and casting -----------------------------------------------------------
    def prepare(self, volume: Volume) -> PreparedVolume:
        """Copy one phase to the device as padded int16 HU, padding below the CT scale read as
        air (`padding_as_air`). Thread-safe (OpenCL calls are)."""
        hu = np.asarray(volume.hu)
        air = padding_as_air(hu)
        if air is not hu:
            volume = Volume(hu=air, T_ct_from_voxel=volume.T_ct_from_voxel, source=volume.source)
        return self.caster.prepare(volume, self._owner_id)

    def _check(self, *vols: PreparedVolume) -> None:
        for vol in vols:
            if vol._renderer_id != self._owner_id:
                raise ValueError("this PreparedVolume was prepared by another Renderer")

    def _circle(self, circle: bool | None) -> bool:
        return self.fluoroscope.detector.kind == "image_intensifier" if circle is None else circle

    def field_mask(self, zoom: int, collimation_mm, circle: bool) -> np.ndarray:
        """(rows, cols) bool: pixels the beam reaches (see casting.field_mask)."""
        return field_mask(self.fluoroscope, zoom, collimation_mm, circle)

    def material_integrals(self, volume: PreparedVolume, T_xray_from_ct, view: View,
                           blend: tuple[PreparedVolume, float] | None = None, distorted: bool = True,
                           circle: bool | None = None) -> np.ndarray:
        """(rows, cols, 4) float32: each material's density integrated along each ray
        (g/cm^3 * mm), Joseph's method; zero outside the beam."""
        self._check(volume, *(() if blend is None else (blend[0],)))
        with self._lock:
            return self.caster.material_integrals(volume, T_xray_from_ct, view.zoom, view.collimation_mm, blend,
                                                  distorted, self._circle(circle))

    def line_integral(self, volume: PreparedVolume, T_xray_from_ct, zoom: int = 1, collimation_mm=None) -> np.ndarray:
        """(rows, cols) float32 exact (Siddon) water-equivalent line integrals; see Caster.line_integral."""
        self._check(volume)
        with self._lock:
            return self.caster.line_integral(volume, T_xray_from_ct, zoom, collimation_mm)

    # -- detector ----------------------------------------------------------------------
    def photons_per_pixel(self, zoom: int, mode: str | None = None) -> float:
        """Photons one pixel counts per frame with nothing in the beam at the reference technique."""
        return self.detector.open_photons_per_pixel(zoom, mode)

    def focal_blur_px(self, zoom: int, depth_mm: float | None = None) -> float:
        return self.detector.focal_blur_px(zoom, depth_mm)

    @staticmethod
    def depth_mm(volume: PreparedVolume, T_xray_from_ct) -> float | None:
        """Distance from the source (mm, along the beam) of the middle of what the volume holds:
        the depth whose focal-spot penumbra the frame is given."""
        if volume.box is None:
            return None
        centre = np.append((np.asarray(volume.box[0], float) + volume.box[1]) / 2.0, 1.0)
        return float((np.asarray(T_xray_from_ct, float) @ np.linalg.inv(volume.T_index_from_ct) @ centre)[2])

    def quantum_noise(self, image: np.ndarray, photons_open_field: float, seed: int | None = None) -> np.ndarray:
        """Poisson counting noise on a relative intensity image (kernel quantum_noise):
        `image` x `photons_open_field` photons expected per pixel, returned relative to the open
        field again (float32). The same `seed` gives the same noise; None a new one."""
        image = np.ascontiguousarray(image, dtype=np.float32)
        out = np.empty_like(image)
        with self._lock:
            buf = self.dev.upload(image, writable=True)     # the upload is the copy the kernel draws into
            self._noise_in(buf, out.size, photons_open_field, seed)
            self.dev.download(buf, out)
        return out

    def _noise_in(self, buf, n: int, photons_open_field: float, seed: int | None) -> None:
        """quantum_noise on the device buffer `buf` of n pixels, in place (under the lock)."""
        seed = int(self._seeds.integers(2 ** 32)) if seed is None else int(seed) & 0xFFFFFFFF
        args = (buf, np.float32(photons_open_field), np.uint32(seed))
        if self.dev.is_cpu:
            self._noise(self.dev.queue, (-(-n // PACKET),), None, *args, np.int32(n))
        else:
            self._noise(self.dev.queue, (n,), None, *args)

    def display_edge(self, view: View) -> np.ndarray:
        """(rows, cols) float32: the fade of a display frame at the field's edge (1 inside, 0
        beyond), as `render` applies it for `view`'s zoom and collimation."""
        circle = self._circle(None)
        mask = self.caster.beam(view.zoom, view.collimation_mm, circle).mask
        return self._edge(view.zoom, view.collimation_mm, circle, mask)

    def _edge(self, zoom: int, collimation_mm, circle: bool, mask: np.ndarray) -> np.ndarray:
        key = (zoom, None if collimation_mm is None else tuple(float(c) for c in collimation_mm), circle)
        if key not in self._edges:
            if len(self._edges) > 64:
                self._edges.clear()
            self._edges[key] = self.detector.edge(mask, zoom)
        return self._edges[key]

    def at_matrix(self, columns: int, rows: int) -> Renderer:
        """This renderer read out at another matrix (the detector's native one for a saved image):
        the same device, lock and prepared volumes, its own rays, masks and detector model."""
        if (columns, rows) == (self.shape[1], self.shape[0]):
            return self
        key = (columns, rows)
        if key not in self._matrices:
            other = Renderer.__new__(Renderer)
            other.__dict__.update({k: v for k, v in self.__dict__.items() if k != "_matrices"})
            other._matrices = {}
            fl = at_resolution(self.fluoroscope, columns, rows)
            other.caster = Caster(self.dev, fl, self.materials, self.contrast, self.packet, self.caster.layouts)
            other.caster.fit_in_background = self.caster.fit_in_background
            other._adopt(fl)
            self._matrices[key] = other
        return self._matrices[key]

    # -- rendering -------------------------------------------------------------------
    def render(self, volume: PreparedVolume, T_xray_from_ct: np.ndarray, view: View,
               blend: tuple[PreparedVolume, float] | None = None, *, cast=None,
               concentration_factor: float | None = None, bands: int | None = None,
               cancelled: Callable[[], bool] | None = None) -> Frame:
        """A `Frame` whose image is `view.quantity`:

        - "line-integral": see `line_integral` (no blend, noise, blur, distortion);
        - "intensity": detector signal relative to the open beam (1 = nothing in the beam) at
          the reference technique, with its blurs, noise (if view.noise), glare and vignetting;
          0 outside the beam;
        - "display": in [0, 1], what the monitor shows: the exposure control's technique, the
          detector, the recursive filter (view.temporal), the log display with its window;
          bright = more attenuation unless view.invert; black outside the beam.

        `cast` stands in for the ray cast (Caster.cast's arguments and result: the projection
        cache's cached line integrals); `concentration_factor` scales the case's iodine (None:
        as the case gives it); `bands`: cast in that many bands of rows, letting other frames on
        this device in between (see Caster.cast), for a long render beside the live one;
        `cancelled()` is asked between them and, true, ends the render with CastCancelled.
        """
        import cv2

        if view.quantity not in QUANTITIES:
            raise FluorosimError(f"quantity '{view.quantity}' is not one of {', '.join(QUANTITIES)}")
        if view.temporal not in TEMPORAL:
            raise FluorosimError(f"temporal '{view.temporal}' is not one of {', '.join(TEMPORAL)}")
        zoomed_K(self.fluoroscope, view.zoom)       # refuses a zoom level the fluoroscope lacks
        if view.quantity == "line-integral":
            return Frame(self.line_integral(volume, T_xray_from_ct, view.zoom, view.collimation_mm))
        self._check(volume, *(() if blend is None else (blend[0],)))
        circle = self._circle(None)
        display = view.quantity == "display"
        args = (volume, T_xray_from_ct, view.zoom, view.collimation_mm, blend, True, circle)
        if bands is not None:
            done, _ = self.caster.cast(*args, bands=(self._lock, bands, cancelled))
            cast = lambda *_: (done, None)  # noqa: E731 - the cast is done; the rest takes the lock once
        with self._lock:
            lines, _ = (cast or self.caster.cast)(*args)
            beam = self.caster.beam(view.zoom, view.collimation_mm, circle)
            mask, exposed, central = beam.mask, beam.exposed, beam.central
            detector, chain, abc = self.detector, self.fluoroscope.image, self.fluoroscope.abc
            exposure = None
            if display and abc.enabled and abc.curve and central.any():
                # The control sets kV and mA from the rays of its measuring field, before the frame.
                gain = detector.gain(view.zoom)
                exposure = detector.exposure_on_curve(
                    self.caster.sample_lines(lines, beam), None if gain is None else gain.ravel()[beam.sample],
                    view.zoom, view.mode, lambda kv: self.caster.tables(kv, None, True, nodes=False))
            tables = self.caster.tables(None if exposure is None else exposure.kvp, concentration_factor, view.polychromatic)
            if display and self.chain is not None:
                return self._display_on_device(volume, T_xray_from_ct, view, lines, tables, beam, exposure, circle)
            image = self.caster.intensity(lines, tables, view.zoom, view.collimation_mm, circle)
        sigma = detector.focal_blur_px(view.zoom, self.depth_mm(volume, T_xray_from_ct))
        if sigma > BLUR_MIN_SIGMA_PX:
            image = cv2.GaussianBlur(image, (0, 0), sigma)
        exposure, photons = self._technique(view, display, exposure, tables, beam, lambda: image[central])
        if view.noise:
            image = self.quantum_noise(image, photons, view.seed)
        # The detector sees the exposed field: the geometric field and the edge's penumbra.
        image = detector.spread(image, exposed, view.zoom)      # 0 outside `exposed`
        if not display:
            image[~mask] = 0.0
        # The photon figure reads the control's sample of its measuring field (ABC_SAMPLE_PIXELS:
        # its median to a few tenths of a per cent), not all of it, a whole-frame partition.
        measured = float(np.median(image.ravel()[beam.sample])) if len(beam.central_index) else 0.0
        if not display:
            return Frame(image, exposure.factor, exposure.attenuation, exposure.limited, photons * measured,
                         kvp=exposure.kvp, ma=exposure.ma)
        if view.temporal == "live":
            image = self.lag.step(image, (view.zoom, view.collimation_mm, image.shape))
        # Half a photon stands in for none, so a pixel that caught nothing reads as very dense.
        floor = 0.5 / photons if view.noise else 1e-12
        p = np.maximum(image, np.float32(floor))
        np.log(p, out=p)
        np.negative(p, out=p)
        pitch = pixel_pitch_at_zoom_mm(self.fluoroscope, view.zoom)
        p = unsharp(p, chain.unsharp_amount, chain.unsharp_sigma_mm / pitch)
        if abc.enabled:
            centre, width = auto_window(p, mask, central, chain.display_latitude, chain.display_min_window,
                                        (beam.mask_index, beam.central_index))
        else:
            centre, width = self.fluoroscope.display.level, self.fluoroscope.display.window
        centre, width = self._radiographers_window(view, centre, width)
        edge = self._edge(view.zoom, view.collimation_mm, circle, mask)
        out = to_display(p, edge, chain, view.invert, centre, width)
        return Frame(out, exposure.factor, exposure.attenuation, exposure.limited, photons * measured, (centre, width), image,
                     exposure.kvp, exposure.ma)

    def _technique(self, view: View, display: bool, exposure: Exposure | None, tables, beam,
                   measuring: Callable[[], np.ndarray]) -> tuple[Exposure, float]:
        """The frame's exposure and photons per open-field pixel: the control's exposure from
        its curve, else (a display frame) from the median of the measuring field's signal,
        `measuring()` (its pixels in beam.central_index order) times the vignetting."""
        detector = self.detector
        if exposure is None:
            exposure = Exposure(1.0, float("nan"), False)
            if display and self.fluoroscope.abc.enabled and len(beam.central_index):
                gain = detector.gain(view.zoom)
                seen = measuring() if gain is None else measuring() * gain.ravel()[beam.central_index]
                exposure = detector.exposure(float(np.median(seen)), view.zoom, view.mode)
        photons = detector.open_photons_per_pixel(view.zoom, view.mode, tables.spectrum) * exposure.factor
        if display and view.temporal == "settled":
            photons *= settled_noise_gain(self.fluoroscope.image.recursive_weight)
        return exposure, photons

    @staticmethod
    def _radiographers_window(view: View, centre: float, width: float) -> tuple[float, float]:
        """The automatic (or the profile's) window moved by the radiographer's window and level."""
        width *= view.window_scale
        return centre + view.level_shift * width, width

    def _display_on_device(self, volume: PreparedVolume, T_xray_from_ct, view: View, lines, tables, beam,
                           exposure: Exposure | None, circle: bool) -> Frame:
        """`render`'s display frame with its detector on the device (device_chain.py), under
        the lock: the same steps in the same order, the image in device memory from the cast
        to the grey scale; the frame, its signal and the samples the exposure control and the
        window read come back to the host."""
        chain, detector, fl = self.chain, self.detector, self.fluoroscope
        assert chain is not None
        image_chain, abc = fl.image, fl.abc
        shape = self.shape
        n = shape[0] * shape[1]
        buf = self.caster.intensity(lines, tables, view.zoom, view.collimation_mm, circle, on_device=True)
        sigma = detector.focal_blur_px(view.zoom, self.depth_mm(volume, T_xray_from_ct))
        if sigma > BLUR_MIN_SIGMA_PX:
            buf = chain.blur(buf, shape, sigma)
        exposure, photons = self._technique(view, True, exposure, tables, beam,
                                            lambda: chain.gather(buf, beam.central_index))
        if view.noise:
            self._noise_in(buf, n, photons, view.seed)
        buf = chain.spread(buf, shape, detector, beam.exposed, view.zoom)
        measured = float(np.median(chain.gather(buf, beam.sample))) if len(beam.central_index) else 0.0
        if view.temporal == "live":
            buf = self.lag.step_on_device(chain, buf, shape, (view.zoom, view.collimation_mm, shape))
        signal = chain.download(buf, shape)
        p = chain.neg_log(buf, n, 0.5 / photons if view.noise else 1e-12)
        chain.unsharp(p, shape, image_chain.unsharp_amount,
                      image_chain.unsharp_sigma_mm / pixel_pitch_at_zoom_mm(fl, view.zoom))
        if abc.enabled:
            centre, width = window_of(chain.gather(p, chain.every(beam.mask_index, WINDOW_STEP)),
                                      chain.gather(p, chain.every(beam.central_index, WINDOW_STEP)),
                                      image_chain.display_latitude, image_chain.display_min_window)
        else:
            centre, width = fl.display.level, fl.display.window
        centre, width = self._radiographers_window(view, centre, width)
        edge = self._edge(view.zoom, view.collimation_mm, circle, beam.mask)
        out = chain.display(p, shape, edge, image_chain.display_knee, view.invert, centre, width)
        return Frame(out, exposure.factor, exposure.attenuation, exposure.limited, photons * measured, (centre, width),
                     signal, exposure.kvp, exposure.ma)
