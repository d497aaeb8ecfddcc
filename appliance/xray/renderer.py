"""The DRR engine: OpenCL ray casting of a CT phase, X-ray physics, detector and display.

One frame:
  1. per pixel, the ray from the focal spot through the (distorted) pixel centre, clipped to
     the part of the volume that holds anything but air;
  2. per ray, each material's density integrated along it (Joseph's method: one bilinear
     sample per slice along the dominant axis; `line-integral` uses exact Siddon path
     lengths instead, see `render`);
  3. per pixel, the energy-integrating detector: sum over the spectrum's bins of
     N0(E) E exp(-sum_m (mu/rho)_m(E) L_m), or one bin at the effective energy;
  4. focal-spot blur, quantum noise, the intensifier's circular field and vignetting;
  5. log, window/level and invert for the monitor.

Units: lengths mm, energies keV, densities g/cm^3, mass attenuation cm^2/g.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from importlib import resources

import numpy as np

from ..config.case import Contrast, Materials
from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError
from ..geometry import invert, rigid_problem
from ..patient.materials import density_model, mass_attenuation, tube_spectrum, water_mu_per_mm
from ..patient.volume import Volume

#: Voxels of air added on every side of a prepared volume, so bilinear samples never leave it.
PAD = 2
#: Voxels at or below this CT number are treated as empty when clipping rays to the
#: volume's content: their density is at most 0.01 g/cm^3, and only voxels outside the
#: bounding box of everything denser are dropped (HU).
EMPTY_MAX_HU = -990
#: Energy bins of the polychromatic detector (the issue asks for at least 16).
ENERGY_BINS = 24
QUANTITIES = ("display", "intensity", "line-integral")
#: Pixels per work-item of the CPU kernel (LANES in drr.cl).
PACKET = 16


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


@dataclass(eq=False)
class PreparedVolume:
    """One phase on the device: padded int16 HU and where it lies.

    `T_index_from_ct` maps the `ct` frame (mm) into padded voxel indices; `box` holds the
    inclusive padded-index bounds (lo, hi) of the voxels denser than EMPTY_MAX_HU.
    """

    buffer: object
    shape_xyz: tuple[int, int, int]
    T_index_from_ct: np.ndarray
    box: tuple[tuple[int, int, int], tuple[int, int, int]] | None
    nbytes: int
    source: str = ""
    time_s: float = 0.0
    _renderer_id: int = field(default=0, repr=False)

    def same_grid(self, other: PreparedVolume) -> bool:
        return self.shape_xyz == other.shape_xyz and np.allclose(self.T_index_from_ct, other.T_index_from_ct, atol=1e-6)


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


#: Expected photon counts above this get Gaussian noise of the same mean and variance
#: (Poisson sampling costs ten times more; the two differ by < 1 % in any moment here).
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


def pick_device(device: str):
    """An OpenCL device: "auto" prefers a GPU and falls back to PoCL's CPU device; "cpu" PoCL only."""
    import pyopencl as cl

    try:
        platforms = cl.get_platforms()
    except cl.Error:
        platforms = []
    gpus, cpus = [], []
    for p in platforms:
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        for d in devs:
            if d.type & cl.device_type.GPU:
                gpus.append(d)
            elif d.type & cl.device_type.CPU:
                cpus.append(d)
    if device not in ("auto", "cpu", "gpu"):
        raise FluorosimError(f"OpenCL device '{device}' is not one of auto, cpu, gpu")
    choice = (gpus if device == "gpu" else cpus if device == "cpu" else gpus + cpus)
    if not choice:
        raise FluorosimError(f"no OpenCL {'device' if device == 'auto' else device + ' device'} found; "
                             "install PoCL (pip install 'pyopencl[pocl]') or the GPU's OpenCL driver")
    return choice[0]


class Renderer:
    """Renders X-ray images of prepared CT phases for one fluoroscope and one case's materials."""

    def __init__(self, fluoroscope: FluoroscopeProfile, materials: Materials, contrast: Contrast | None = None,
                 device: str = "auto", packet: bool | None = None):
        """`device`: "auto" (a GPU if present, else PoCL's CPU device), "cpu" or "gpu".
        `packet`: use the 16-pixel vector kernel (default: on CPU devices)."""
        import pyopencl as cl

        self._cl = cl
        self.device = pick_device(device)
        self.ctx = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.ctx)
        src = resources.files("appliance.xray").joinpath("drr.cl").read_text()
        self._options = ["-DUNALIGNED_PAIRS"] if self.device.type & cl.device_type.CPU else []
        self._program = cl.Program(self.ctx, src).build(options=self._options)
        self._source = src
        # CPUs get the explicitly vectorised packet kernel; GPUs one ray per work-item.
        self.packet = bool(self.device.type & cl.device_type.CPU) if packet is None else packet
        self._joseph_name = "joseph_packet" if self.packet else "joseph_materials"
        self._joseph = cl.Kernel(self._program, self._joseph_name)
        self._joseph_blend = None        # built on the first blended frame
        self._poly_kernel = cl.Kernel(self._program, "polychromatic_packet" if self.packet else "polychromatic")
        self._siddon = cl.Kernel(self._program, "siddon_water")
        self._noise = cl.Kernel(self._program, "quantum_noise")
        self._seeds = np.random.default_rng()        # a fresh noise pattern each frame unless View.seed
        # Tube output of the last displayed frame relative to the reference technique, as set
        # by automatic brightness control (1 without it): the console's dose rate follows it.
        self.exposure_factor = 1.0
        self._lock = threading.Lock()        # one frame at a time on the queue
        self.materials = materials
        self.contrast = contrast
        dm = density_model(materials)
        self._mat = np.array([dm.air_max_hu, dm.bone_min_hu, dm.contrast_min_hu, dm.offset[2], dm.slope[2], 0, 0, 0],
                             dtype=np.float32)
        self._mat_buf = cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=self._mat)
        self.set_fluoroscope(fluoroscope)

    # -- profile ---------------------------------------------------------------------
    def set_fluoroscope(self, fluoroscope: FluoroscopeProfile) -> None:
        """Adopt a (reloaded) fluoroscope profile: spectrum, attenuation tables, ray maps."""
        cl = self._cl
        spectrum = tube_spectrum(fluoroscope.tube, ENERGY_BINS)
        poly_mu = mass_attenuation(spectrum.energies_kev, self.contrast).astype(np.float32)
        mono_mu = mass_attenuation([spectrum.effective_kev], self.contrast).astype(np.float32)
        mf = cl.mem_flags
        with self._lock:
            self.fluoroscope = fluoroscope
            self.spectrum = spectrum
            self.mu_water_per_mm = water_mu_per_mm(spectrum.effective_kev)
            self._poly = (cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=spectrum.energy_weights().astype(np.float32)),
                          cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(poly_mu)),
                          len(spectrum.energies_kev))
            self._mono = (cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ones(1, np.float32)),
                          cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(mono_mu)), 1)
            self._dirs: dict = {}
            self._masks: dict = {}
            self._gains: dict = {}

    @property
    def shape(self) -> tuple[int, int]:
        return self.fluoroscope.detector.rows, self.fluoroscope.detector.columns

    # -- volumes ---------------------------------------------------------------------
    def prepare(self, volume: Volume) -> PreparedVolume:
        """Copy one phase to the device as padded int16 HU. Thread-safe (OpenCL calls are)."""
        cl = self._cl
        hu = np.asarray(volume.hu)
        if hu.ndim != 3 or hu.dtype != np.int16:
            raise FluorosimError(f"{volume.source or 'volume'}: expected a 3D int16 HU array, got {hu.dtype} {hu.shape}")
        padded = np.pad(hu, PAD, mode="constant", constant_values=-1000)
        mask = hu > EMPTY_MAX_HU
        box = None
        if mask.any():
            ks = np.flatnonzero(mask.any(axis=(1, 2)))
            js = np.flatnonzero(mask.any(axis=(0, 2)))
            is_ = np.flatnonzero(mask.any(axis=(0, 1)))
            box = ((int(is_[0]) + PAD, int(js[0]) + PAD, int(ks[0]) + PAD),
                   (int(is_[-1]) + PAD, int(js[-1]) + PAD, int(ks[-1]) + PAD))
        del mask
        T_index_from_voxel = np.eye(4)
        T_index_from_voxel[:3, 3] = PAD
        T_index_from_ct = T_index_from_voxel @ np.linalg.inv(np.asarray(volume.T_ct_from_voxel, dtype=np.float64))
        buf = cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=padded)
        nz, ny, nx = padded.shape
        return PreparedVolume(buffer=buf, shape_xyz=(nx, ny, nz), T_index_from_ct=T_index_from_ct, box=box,
                              nbytes=padded.nbytes, source=volume.source, _renderer_id=id(self))

    # -- per-view caches -------------------------------------------------------------
    def _dirs_buffer(self, zoom: int, distorted: bool):
        key = (zoom, distorted)
        if key not in self._dirs:
            d = ray_directions(self.fluoroscope, zoom, distorted)
            self._dirs[key] = self._cl.Buffer(self.ctx, self._cl.mem_flags.READ_ONLY | self._cl.mem_flags.COPY_HOST_PTR, hostbuf=d)
        return self._dirs[key]

    def field_mask(self, zoom: int, collimation_mm, circle: bool) -> np.ndarray:
        """(rows, cols) bool: pixels the beam reaches (inside the blades, and inside the
        intensifier's circular field when `circle`)."""
        rows, cols = self.shape
        det = self.fluoroscope.detector
        fovs = [z.fov_mm for z in self.fluoroscope.zoom_levels]
        pitch = det.pixel_pitch_mm * fovs[zoom - 1] / fovs[0]     # mm per pixel at this zoom
        u = np.arange(cols) - (cols - 1) / 2.0
        v = np.arange(rows) - (rows - 1) / 2.0
        m = np.ones((rows, cols), dtype=bool)
        if collimation_mm is not None:
            half_u, half_v = collimation_mm[0] / 2.0 / pitch, collimation_mm[1] / 2.0 / pitch
            m &= (np.abs(v)[:, None] <= half_v) & (np.abs(u)[None, :] <= half_u)
        if circle:
            r = fovs[0] / det.pixel_pitch_mm / 2.0               # the field fills the same circle at every zoom
            m &= (v[:, None] ** 2 + u[None, :] ** 2) <= r * r
        return m

    def _mask_buffer(self, zoom: int, collimation_mm, circle: bool):
        """(beam mask, its device buffer, the brightness control's measuring field), cached."""
        key = (zoom, None if collimation_mm is None else tuple(float(c) for c in collimation_mm), circle)
        if key not in self._masks:
            if len(self._masks) > 64:
                self._masks.clear()
            m = self.field_mask(zoom, collimation_mm, circle)
            buf = self._cl.Buffer(self.ctx, self._cl.mem_flags.READ_ONLY | self._cl.mem_flags.COPY_HOST_PTR,
                                  hostbuf=m.astype(np.uint8))
            self._masks[key] = (m, buf, measuring_field(m))
        return self._masks[key]

    def _gain(self, zoom: int) -> np.ndarray | None:
        """Intensifier vignetting as a multiplicative gain, 1 at the centre."""
        det = self.fluoroscope.detector
        if det.kind != "image_intensifier" or det.vignetting == 0:
            return None
        if zoom not in self._gains:
            rows, cols = self.shape
            r = self.fluoroscope.zoom_levels[0].fov_mm / det.pixel_pitch_mm / 2.0
            v = np.arange(rows) - (rows - 1) / 2.0
            u = np.arange(cols) - (cols - 1) / 2.0
            rr = (v[:, None] ** 2 + u[None, :] ** 2) / (r * r)
            self._gains[zoom] = (1.0 - det.vignetting * np.minimum(rr, 1.0)).astype(np.float32)
        return self._gains[zoom]

    # -- rendering -------------------------------------------------------------------
    def _geometry(self, vol: PreparedVolume, T_xray_from_ct: np.ndarray):
        T = np.asarray(T_xray_from_ct, dtype=np.float64)
        problem = rigid_problem(T)
        if problem:
            raise FluorosimError(f"T_xray_from_ct {problem}")
        T_index_from_xray = vol.T_index_from_ct @ invert(T)
        geo = np.zeros(16, dtype=np.float32)
        geo[:9] = T_index_from_xray[:3, :3].ravel()
        geo[9:12] = T_index_from_xray[:3, 3]
        return geo

    def _box(self, *vols: PreparedVolume) -> np.ndarray | None:
        boxes = [v.box for v in vols if v.box is not None]
        if not boxes:
            return None
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
        return np.array([*lo, 0, *hi, 0], dtype=np.int32)

    def _check(self, vol: PreparedVolume) -> None:
        if vol._renderer_id != id(self):
            raise ValueError("this PreparedVolume was prepared by another Renderer")

    def material_integrals(self, volume: PreparedVolume, T_xray_from_ct, view: View,
                           blend: tuple[PreparedVolume, float] | None = None, distorted: bool = True,
                           circle: bool | None = None) -> np.ndarray:
        """(rows, cols, 4) float32: each material's density integrated along each ray
        (g/cm^3 * mm), Joseph's method; zero outside the beam."""
        lines, _ = self._cast(volume, T_xray_from_ct, view, blend, distorted, circle)
        out = np.empty(self.shape + (4,), dtype=np.float32)
        self._cl.enqueue_copy(self.queue, out, lines)
        return out

    def _cast(self, volume, T_xray_from_ct, view, blend, distorted, circle):
        cl = self._cl
        self._check(volume)
        if circle is None:
            circle = self.fluoroscope.detector.kind == "image_intensifier"
        rows, cols = self.shape
        geo = self._geometry(volume, T_xray_from_ct)
        mask, mask_buf, _ = self._mask_buffer(view.zoom, view.collimation_mm, circle)
        dirs = self._dirs_buffer(view.zoom, distorted)
        vols = (volume,) if blend is None else (volume, blend[0])
        if blend is not None:
            self._check(blend[0])
            if not volume.same_grid(blend[0]):
                raise ValueError("phases to blend must share one voxel grid")
        box = self._box(*vols)
        mf = cl.mem_flags
        lines = cl.Buffer(self.ctx, mf.READ_WRITE, rows * cols * 16)
        if box is None:
            cl.enqueue_fill_buffer(self.queue, lines, np.float32(0), 0, rows * cols * 16)
            return lines, mask
        geo_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=geo)
        box_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=box)
        nx, ny, nz = volume.shape_xyz
        if blend is None:
            kernel, first = self._joseph, (volume.buffer,)
        else:
            if self._joseph_blend is None:
                program = cl.Program(self.ctx, self._source).build(options=["-DBLEND", *self._options])
                self._joseph_blend = cl.Kernel(program, self._joseph_name)
            kernel, first = self._joseph_blend, (volume.buffer, blend[0].buffer, np.float32(blend[1]))
        args = (*first, np.int32(nx), np.int32(ny), np.int32(nz), dirs, mask_buf, geo_buf, box_buf, self._mat_buf)
        if self.packet:
            kernel(self.queue, (-(-cols // PACKET), rows), None, *args, np.int32(cols), lines)
        else:
            kernel(self.queue, (cols, rows), None, *args, lines)
        return lines, mask

    def line_integral(self, volume: PreparedVolume, T_xray_from_ct, zoom: int = 1, collimation_mm=None) -> np.ndarray:
        """(rows, cols) float32: sum of mu * length along the ray through each undistorted
        pixel centre, mu = mu_water (1 + HU/1000) clipped at 0 at the effective energy;
        exact Siddon path lengths through constant voxels."""
        cl = self._cl
        self._check(volume)
        rows, cols = self.shape
        with self._lock:
            geo = self._geometry(volume, T_xray_from_ct)
            _, mask_buf, _ = self._mask_buffer(zoom, collimation_mm, False)
            dirs = self._dirs_buffer(zoom, False)
            out = np.zeros((rows, cols), dtype=np.float32)
            box = self._box(volume)
            if box is None:
                return out
            mf = cl.mem_flags
            out_buf = cl.Buffer(self.ctx, mf.WRITE_ONLY, out.nbytes)
            geo_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=geo)
            box_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=box)
            nx, ny, nz = volume.shape_xyz
            self._siddon(self.queue, (cols, rows), None, volume.buffer, np.int32(nx), np.int32(ny),
                                       np.int32(nz), dirs, mask_buf, geo_buf, box_buf, out_buf)
            cl.enqueue_copy(self.queue, out, out_buf)
        return out * np.float32(self.mu_water_per_mm)

    def photons_per_pixel(self, zoom: int) -> float:
        """Expected photons reaching one detector pixel in one pulse with nothing in the beam.

        Fluence from spekpy at 1 m scaled to the SID, times mA x pulse width, times the pixel's
        area at the detector; at higher zoom the automatic brightness control raises the dose
        in proportion to the profile's reference air-kerma rates.
        """
        f = self.fluoroscope
        fovs = [z.fov_mm for z in f.zoom_levels]
        pitch = f.detector.pixel_pitch_mm * fovs[zoom - 1] / fovs[0]
        mas = f.tube.ma * f.tube.pulse_width_ms / 1000.0
        fluence = float(self.spectrum.photons_per_mm2_per_mas.sum()) * (1000.0 / f.geometry.source_to_image_mm) ** 2
        mode = f.tube.modes[0].name
        abc = f.zoom_levels[zoom - 1].air_kerma_rate_mgy_per_min[mode] / f.zoom_levels[0].air_kerma_rate_mgy_per_min[mode]
        return fluence * mas * pitch * pitch * abc

    def quantum_noise(self, image: np.ndarray, photons_open_field: float, seed: int | None = None) -> np.ndarray:
        """Poisson counting noise on a relative intensity image (kernel quantum_noise):
        `image` x `photons_open_field` photons expected per pixel, returned relative to the open
        field again (float32). The same `seed` gives the same noise; None a new one."""
        cl = self._cl
        out = np.ascontiguousarray(image, dtype=np.float32).copy()
        seed = int(self._seeds.integers(2 ** 32)) if seed is None else int(seed) & 0xFFFFFFFF
        with self._lock:
            buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=out)
            self._noise(self.queue, (out.size,), None, buf, np.float32(photons_open_field), np.uint32(seed))
            cl.enqueue_copy(self.queue, out, buf)
        return out

    def abc_response(self, measured_intensity: float) -> tuple[float, float]:
        """What automatic brightness control makes of the median relative intensity over its
        measuring field: (window centre, tube output relative to the reference technique).
        The output makes up the attenuation beyond (or short of) the reference patient's,
        exp(attenuation - reference), within the tube's limits; the video chain's gain keeps
        the measured attenuation at the window's centre even where the tube is at a limit."""
        abc = self.fluoroscope.abc
        attenuation = -math.log(max(measured_intensity, 1e-12))
        factor = math.exp(attenuation - abc.reference_attenuation)
        return attenuation, min(max(factor, abc.min_factor), abc.max_factor)

    def focal_blur_px(self, zoom: int) -> float:
        """Gaussian sigma (pixels) of the focal spot's penumbra for an object at the isocentre:
        spot size x (SID - SOD) / SOD, taken as the FWHM."""
        f = self.fluoroscope
        fovs = [z.fov_mm for z in f.zoom_levels]
        pitch = f.detector.pixel_pitch_mm * fovs[zoom - 1] / fovs[0]
        sid, sod = f.geometry.source_to_image_mm, f.geometry.source_to_isocentre_mm
        return f.tube.focal_spot_mm * (sid - sod) / sod / pitch / 2.3548

    def render(self, volume: PreparedVolume, T_xray_from_ct: np.ndarray, view: View,
               blend: tuple[PreparedVolume, float] | None = None) -> np.ndarray:
        """(rows, cols) float32 image of `view.quantity`:

        - "line-integral": see `line_integral` (no blend, noise, blur, distortion);
        - "intensity": detector signal relative to the open beam (1 = nothing in the beam),
          with blur, noise (if view.noise) and vignetting; 0 outside the beam;
        - "display": in [0, 1], what the monitor shows: window/level of -log(intensity),
          bright = more attenuation unless view.invert; 0 (black) outside the beam.
        """
        import cv2

        if view.quantity not in QUANTITIES:
            raise FluorosimError(f"quantity '{view.quantity}' is not one of {', '.join(QUANTITIES)}")
        zoomed_K(self.fluoroscope, view.zoom)       # refuses a zoom level the fluoroscope lacks
        if view.quantity == "line-integral":
            return self.line_integral(volume, T_xray_from_ct, view.zoom, view.collimation_mm)
        cl = self._cl
        rows, cols = self.shape
        with self._lock:
            lines, mask = self._cast(volume, T_xray_from_ct, view, blend, True, None)
            weights, mu_rho, n_e = self._poly if view.polychromatic else self._mono
            _, mask_buf, central = self._mask_buffer(view.zoom, view.collimation_mm,
                                                     self.fluoroscope.detector.kind == "image_intensifier")
            out_buf = cl.Buffer(self.ctx, cl.mem_flags.WRITE_ONLY, rows * cols * 4)
            if self.packet:
                self._poly_kernel(self.queue, (-(-rows * cols // PACKET),), None, lines, mask_buf, weights, mu_rho,
                                  np.int32(n_e), np.int32(rows * cols), out_buf)
            else:
                self._poly_kernel(self.queue, (rows * cols,), None, lines, mask_buf, weights, mu_rho,
                                  np.int32(n_e), out_buf)
            image = np.empty((rows, cols), dtype=np.float32)
            cl.enqueue_copy(self.queue, image, out_buf)
            gain = self._gain(view.zoom)
            display, abc = self.fluoroscope.display, self.fluoroscope.abc
        sigma = self.focal_blur_px(view.zoom)
        if sigma > 0.3:
            image = cv2.GaussianBlur(image, (0, 0), sigma)
        # What the monitor shows runs under automatic brightness control; the "intensity"
        # quantity is the physics at the profile's reference technique.
        level, factor = display.level, 1.0
        if abc.enabled and view.quantity == "display" and central.any():
            seen = image[central] if gain is None else image[central] * gain[central]
            level, factor = self.abc_response(float(np.median(seen)))
        self.exposure_factor = factor
        photons = self.photons_per_pixel(view.zoom) * factor
        if view.noise:
            image = self.quantum_noise(image, photons, view.seed)
        if gain is not None:
            image *= gain
        image[~mask] = 0.0
        if view.quantity == "intensity":
            return image
        # Half a photon stands in for none, so a pixel that caught nothing reads as very dense.
        floor = 0.5 / photons if view.noise else 1e-12
        p = -np.log(np.maximum(image, floor))
        lo = level - display.window / 2.0
        out = np.clip((p - lo) / display.window, 0.0, 1.0).astype(np.float32)
        if view.invert:
            out = 1.0 - out
        out[~mask] = 0.0
        return out
