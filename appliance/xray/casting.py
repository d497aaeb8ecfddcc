"""Ray casting: CT phases on the device, the rays of the fluoroscope's pixels, line integrals.

One frame's casting:
  1. per pixel, the ray from the focal spot through the (distorted) pixel centre, clipped to
     the part of the volume that holds anything but air;
  2. per ray, each material's density integrated along it (Joseph's method: one bilinear
     sample per slice along the dominant axis; `line_integral` uses exact Siddon path
     lengths instead);
  3. per pixel, the energy-integrating detector's signal relative to the open beam: the sum
     over the spectrum's bins of N0(E) E exp(-sum_m (mu/rho)_m(E) L_m), or one bin at the
     effective energy.

Units: lengths mm, energies keV, densities g/cm^3, mass attenuation cm^2/g.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..config.case import Contrast, Materials
from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError
from ..geometry import invert, rigid_problem
from ..patient.materials import (
    Spectrum,
    curve_spectrum,
    density_model,
    mass_attenuation,
    spectrum_at,
    tube_spectrum,
    water_mu_per_mm,
)
from ..patient.volume import Volume
from .device import ClDevice
from .energy_nodes import FIT_FACTORS, NodeQuadrature, fit_nodes, fit_soon
from .outline import Outline, content_outline, cutting, projections, union
from .pixel_geometry import (
    field_edge,
    field_mask,
    measuring_field,
    penumbra_px,
    ray_directions,
)

if TYPE_CHECKING:
    import pyopencl as cl

    from .slabs import SlabCache

#: Voxels of air added on every side of a prepared volume, so bilinear samples never leave it.
PAD = 2
#: Voxels at or below this CT number are treated as empty when clipping rays to the
#: volume's content: their density is at most 0.1 g/cm^3, and only voxels outside the
#: bounding box and the outline (outline.py) of everything denser are dropped (HU). A
#: scanner's air reads -1000 with 5-20 HU of noise, so a threshold closer to -1000 would count
#: the noise as content.
EMPTY_MAX_HU = -900
#: A plane of voxels (along an axis for the box, along an outline's direction for its planes)
#: belongs to the content where more than this many of its voxels are above EMPTY_MAX_HU
#: (count), or any is above SURE_CONTENT_HU: single noise spikes in the air do not stretch the
#: box or the outline to the whole grid, a small dense object (a steel ball, a catheter tip) is
#: never dropped, whichever plane cuts it.
EMPTY_PLANE_MAX_VOXELS = 4
SURE_CONTENT_HU = -500
#: Joseph's samples blend a slice's neighbours bilinearly: a sample reaches a voxel less than
#: one index away along each axis, so an outline plane n.p is grown by 1 x sum |n_i| for them
#: (voxels). (Siddon's exact path is clipped to the box alone: see siddon_water in drr.cl.)
JOSEPH_REACH = 1.0
#: Added to each grown outline plane (voxels of n.p): a ray's t-interval and its samples'
#: positions are float, rounded to about 1e-4 voxels over a few thousand voxels of
#: focal-spot distance, so a sample the exact plane keeps with a weight of zero might be lost
#: with a weight of that rounding's size; a hundredth keeps it, and costs nothing measurable.
OUTLINE_MARGIN = 0.01
#: A prepared volume keeps the voxels of its content box, the box's bounds rounded out to
#: multiples of this many voxels (see `Caster.prepare`).
CROP_BLOCK = 16
#: Energy bins of the polychromatic detector (the issue asks for at least 16).
ENERGY_BINS = 24
#: Pixels per work-item of the CPU kernel (LANES in drr.cl).
PACKET = 16
#: Pixels of the measuring field the exposure control samples: its median to a few tenths of a
#: per cent, far below the 1 kV step's few per cent.
ABC_SAMPLE_PIXELS = 1024
#: Pause between the bands of a banded cast (s): long enough for a waiting thread to take the lock.
BAND_YIELD_S = 0.002
#: A field is cast through a phase laid out for rays along an axis only where every ray's step
#: along it exceeds its steps across by this factor (dimensionless): the kernels would pick that
#: axis for every ray anyway (then the integrals are the plain layout's to the bit), and float
#: rounding on a near tie cannot make a kernel pick another.
DOMINANCE_MARGIN = 1.0001


@dataclass(frozen=True, eq=False)
class BlendedLines:
    """Two phases' cast material integrals (device buffers) and the weight of the second: the
    frame's integrals are (1 - w) a + w b. The polychromatic kernel and the exposure control's
    sample blend them as they read them, so a frame between two cached phases costs no pass of
    its own for the blend."""

    a: cl.Buffer
    b: cl.Buffer
    w: float
    #: The exposure control's sample (Beam.sample) of `a` and of `b` on the host, where the
    #: caller holds them (the projection cache: a cached phase's integrals do not change, so
    #: a frame between two reads no device at all for its control); None: gathered per frame.
    samples: tuple[np.ndarray, np.ndarray] | None = None


class CastCancelled(Exception):
    """A banded cast stopped between bands because its caller asked (see Caster.cast)."""


@dataclass(frozen=True, eq=False)
class DetectorTables:
    """One technique's detector tables: the spectrum, each energy bin's share of the open-field
    signal (weights) and each material's mass attenuation there (mu, cm^2/g), on the host; on
    the device, the same for the `device_bins` energies the frame's sum is evaluated at: the
    fitted nodes of `quadrature` (energy_nodes.py), or every bin where it is None."""

    spectrum: Spectrum
    weights: np.ndarray          # (n_e,) float32, sum 1
    mu: np.ndarray               # (n_e, 4) float32
    weights_buf: cl.Buffer
    mu_buf: cl.Buffer
    device_bins: int = 0
    quadrature: NodeQuadrature | None = None
    #: Built while its kV's nodes were still being fitted on the side thread: every bin is
    #: summed until the fit has come, then the tables are built again with the nodes.
    awaiting_nodes: bool = False

    def transmission(self, lines: np.ndarray) -> np.ndarray:
        """I/I0 of (n, 4) material integrals (g/cm^3 * mm), as the polychromatic kernel computes it."""
        return np.exp(np.float32(-0.1) * (np.asarray(lines, np.float32) @ self.mu.T)) @ self.weights


@dataclass(eq=False)
class PreparedVolume:
    """One phase on the device: padded int16 HU and where it lies.

    `T_index_from_ct` maps the `ct` frame (mm) into padded voxel indices; `box` holds the
    inclusive padded-index bounds (lo, hi) of the voxels denser than EMPTY_MAX_HU, `outline`
    the planes around them (outline.py; None: the box alone clips). `slab_axis`:
    -1 for the plain layout [z][y][x]; 0-2 for a slab copy laid out for rays along that axis,
    which they are cast along (drr.cl's LAYOUT: the rows of its slices contiguous).
    """

    buffer: cl.Buffer
    shape_xyz: tuple[int, int, int]
    T_index_from_ct: np.ndarray
    box: tuple[tuple[int, int, int], tuple[int, int, int]] | None
    nbytes: int
    source: str = ""
    time_s: float = 0.0
    _renderer_id: int = field(default=0, repr=False)
    slab_axis: int = -1
    outline: Outline | None = None

    def same_grid(self, other: PreparedVolume) -> bool:
        return (self.shape_xyz == other.shape_xyz and self.slab_axis == other.slab_axis
                and np.allclose(self.T_index_from_ct, other.T_index_from_ct, atol=1e-6))


@dataclass(frozen=True, eq=False)
class Beam:
    """One field's masks: `mask` the geometric field (inside the blades and the intensifier's
    circle), `exposed` that and the edge's penumbra outside it (the pixels rays are cast for),
    `central` the exposure control's measuring field, `sample` the pixels of it (flat indices)
    the control reads; with their device buffers. `mask_index` and `central_index` are the
    flat indices of `mask` and `central` (what boolean indexing by them reads, in its order),
    so a frame's statistics over them take their pixels without scanning a whole-frame mask."""

    mask: np.ndarray
    mask_buf: cl.Buffer
    central: np.ndarray
    exposed: np.ndarray
    exposed_buf: cl.Buffer
    sample: np.ndarray
    sample_buf: cl.Buffer
    mask_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    central_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))


class Caster:
    """Casts rays of one fluoroscope through prepared CT phases of one case's materials."""

    def __init__(self, dev: ClDevice, fluoroscope: FluoroscopeProfile, materials: Materials,
                 contrast: Contrast | None = None, packet: bool | None = None, layouts: SlabCache | None = None):
        """`layouts`: copies of phases laid out for rays along x (slabs.py's SlabCache of one-slice
        slabs), which a field whose every ray runs along x is cast through; None: never. Only the
        packet kernel (CPU devices) takes them, whose row loads they serve: what they would do for
        the one-ray-per-work-item kernel of a GPU, a phase's memory more, has not been measured."""
        self.dev = dev
        self.packet = dev.is_cpu if packet is None else packet
        self.layouts = layouts if self.packet else None
        name = "joseph_packet" if self.packet else "joseph_materials"
        self._joseph_name = name
        self._joseph = dev.kernel(name)
        self._joseph_blend = None
        self._joseph_slabbed: dict[str, cl.Kernel] = {}
        self._poly_kernel = dev.kernel("polychromatic_packet" if self.packet else "polychromatic")
        self._siddon = dev.kernel("siddon_water")
        self._gather = dev.kernel("gather_lines")
        self.materials = materials
        self.contrast = contrast
        dm = density_model(materials)
        self._mat = np.array([dm.air_max_hu, dm.bone_min_hu, dm.contrast_min_hu, dm.offset[2], dm.slope[2], 0, 0, 0],
                             dtype=np.float32)
        self._mat_buf = dev.upload(self._mat)
        #: Fit a new kV's energy nodes on a side thread (a live renderer: no frame waits for a
        #: fit) instead of in the frame that first needs them (offline renders, benches, tests).
        self.fit_in_background = False
        self.set_fluoroscope(fluoroscope)

    def set_fluoroscope(self, fluoroscope: FluoroscopeProfile) -> None:
        """Adopt a (reloaded) fluoroscope profile: spectrum, attenuation tables, ray maps.
        Call with the device's lock held if frames may be in flight."""
        spectrum = tube_spectrum(fluoroscope.tube, ENERGY_BINS)
        self.fluoroscope = fluoroscope
        self.spectrum = spectrum
        self.mu_water_per_mm = water_mu_per_mm(spectrum.effective_kev)
        self._tables: dict = {}
        self._quads: dict[float, NodeQuadrature | None] = {}
        self._fitting: dict = {}          # kV -> the side thread's fit of it (fit_in_background)
        self._dirs: dict = {}
        self._masks: dict = {}

    def tables(self, kvp: float | None = None, concentration_factor: float | None = None,
               polychromatic: bool = True, nodes: bool = True) -> DetectorTables:
        """The detector's tables for a technique: the spectrum at `kvp` (None: tube.kvp; rounded to
        1 kV, as a generator sets it) in ENERGY_BINS bins, or its effective energy alone for a
        monochromatic frame, and the materials' mass attenuation there, with the iodine at
        `concentration_factor` times the case's (None: the case's; mass attenuation is linear
        in the concentration). Cached: a frame of a known technique builds nothing. `nodes`: the
        device sums the spectrum at the fitted energy nodes (energy_nodes.py), fitted on first
        use of a kV; False for tables only the host reads (the exposure control's kV search
        visits many kV values and sums every bin of each on its sample)."""
        tube = self.fluoroscope.tube
        kv = float(tube.kvp) if kvp is None else float(round(kvp))
        factor = None if concentration_factor is None else round(max(float(concentration_factor), 0.0), 4)
        key = (kv, factor, polychromatic, nodes)
        table = self._tables.get(key)
        if table is not None and table.awaiting_nodes and (kv not in self._fitting or self._fitting[kv].done()):
            del self._tables[key]           # the nodes have come: build it again with them
        if key not in self._tables:
            if len(self._tables) > 512:
                self._tables.clear()
            abc = self.fluoroscope.abc
            anchors = tuple(sorted({point.kvp for point in abc.curve})) if abc.enabled else ()
            if kv == float(tube.kvp):
                spectrum = self.spectrum
            elif anchors and anchors[0] <= kv <= anchors[-1]:
                spectrum = curve_spectrum(kv, anchors, float(tube.filtration_mm_al), ENERGY_BINS)
            else:
                spectrum = spectrum_at(kv, float(tube.filtration_mm_al), ENERGY_BINS)
            contrast = self.contrast
            if contrast is not None and factor is not None:
                contrast = None if factor == 0.0 else Contrast(
                    agent=contrast.agent, concentration_mg_per_ml=min(contrast.concentration_mg_per_ml * factor, 400.0))
            energies = spectrum.energies_kev if polychromatic else [spectrum.effective_kev]
            weights = (spectrum.energy_weights() if polychromatic else np.ones(1)).astype(np.float32)
            mu = np.ascontiguousarray(mass_attenuation(energies, contrast).astype(np.float32))
            quad = self._quadrature(kv, spectrum, weights) if polychromatic and nodes else None
            on_device = (weights, mu) if quad is None else (quad.weights, np.ascontiguousarray(mu[quad.bins]))
            self._tables[key] = DetectorTables(spectrum, weights, mu, self.dev.upload(on_device[0]),
                                               self.dev.upload(on_device[1]), len(on_device[0]), quad,
                                               awaiting_nodes=polychromatic and nodes and kv in self._fitting)
        return self._tables[key]

    def _quadrature(self, kv: float, spectrum: Spectrum, weights: np.ndarray) -> NodeQuadrature | None:
        """The energy nodes of the spectrum at `kv` for the case's materials (energy_nodes.py),
        fitted once per kV over the case's iodine and every lower concentration; None: sum every bin."""
        limits = self.fluoroscope.energy_nodes
        if not limits.enabled:
            return None
        if kv in self._fitting:
            if not self._fitting[kv].done():
                return None
            self._quads[kv] = self._fitting.pop(kv).result()
        if kv not in self._quads:
            c = self.contrast
            mus = [mass_attenuation(spectrum.energies_kev, None if f == 0.0 or c is None else Contrast(
                agent=c.agent, concentration_mg_per_ml=c.concentration_mg_per_ml * f)) for f in FIT_FACTORS]
            mus = mus if c is not None else mus[:1]
            if self.fit_in_background:
                self._fitting[kv] = fit_soon(weights, mus, limits)
                return None
            self._quads[kv] = fit_nodes(weights, mus, limits)
        return self._quads[kv]

    @property
    def shape(self) -> tuple[int, int]:
        return self.fluoroscope.detector.rows, self.fluoroscope.detector.columns

    def prepare(self, volume: Volume, owner: int) -> PreparedVolume:
        """Copy one phase's content box to the device as padded int16 HU. Thread-safe (OpenCL
        calls are). Voxels outside the box are air (see EMPTY_MAX_HU) and no ray samples them."""
        hu = np.asarray(volume.hu)
        if hu.ndim != 3 or hu.dtype != np.int16:
            raise FluorosimError(f"{volume.source or 'volume'}: expected a 3D int16 HU array, got {hu.dtype} {hu.shape}")
        # The mask's projections onto the index axes' pairs serve both the box's planes (their
        # sums) and the outline's.
        maps = projections(hu > EMPTY_MAX_HU, hu > SURE_CONTENT_HU)
        (xy, xy_sure), (xz, xz_sure) = maps[(0, 1)], maps[(0, 2)]     # array axes (y, x), (z, x)
        ks, js, is_ = (np.flatnonzero((c > EMPTY_PLANE_MAX_VOXELS) | any_sure) for c, any_sure in (
            (xz.sum(axis=1), xz_sure.any(axis=1)), (xy.sum(axis=1), xy_sure.any(axis=1)),
            (xy.sum(axis=0), xy_sure.any(axis=0))))
        box: tuple[tuple[int, int, int], tuple[int, int, int]] | None = None
        outline = None
        start = np.zeros(3, dtype=int)            # (i, j, k) of the first voxel kept
        if len(ks) and len(js) and len(is_):
            lo, hi = np.array([is_[0], js[0], ks[0]]), np.array([is_[-1], js[-1], ks[-1]])
            # Only the content box travels to the device (a CT's air around the patient is
            # a third to a half of it). Its bounds are rounded out to CROP_BLOCK voxels, so
            # the phases of one 4D CT, whose outlines differ by a few voxels, keep one grid
            # and can still be blended.
            n = np.array(hu.shape[::-1])
            start = lo // CROP_BLOCK * CROP_BLOCK
            stop = np.minimum(-(-(hi + 1) // CROP_BLOCK) * CROP_BLOCK, n)
            hu = hu[start[2]:stop[2], start[1]:stop[1], start[0]:stop[0]]
            l0, l1, l2 = (int(x) for x in lo - start + PAD)
            h0, h1, h2 = (int(x) for x in hi - start + PAD)
            box = ((l0, l1, l2), (h0, h1, h2))
            outline = content_outline(maps, PAD - start, EMPTY_PLANE_MAX_VOXELS)
        else:
            hu = hu[:1, :1, :1]
        padded = np.pad(hu, PAD, mode="constant", constant_values=-1000)
        T_index_from_voxel = np.eye(4)
        T_index_from_voxel[:3, 3] = PAD - start
        T_index_from_ct = T_index_from_voxel @ np.linalg.inv(np.asarray(volume.T_ct_from_voxel, dtype=np.float64))
        nz, ny, nx = padded.shape
        return PreparedVolume(buffer=self.dev.upload(padded), shape_xyz=(nx, ny, nz), T_index_from_ct=T_index_from_ct,
                              box=box, nbytes=padded.nbytes, source=volume.source, _renderer_id=owner,
                              outline=outline)

    # -- per-view caches -------------------------------------------------------------
    def _dirs_buffer(self, zoom: int, distorted: bool):
        return self._rays(zoom, distorted)[0]

    def _rays(self, zoom: int, distorted: bool):
        """The pixels' ray directions on the device, and on the host those of the detector's outer
        rows and columns (every pixel's ray lies within their convex hull, distorted or not)."""
        key = (zoom, distorted)
        if key not in self._dirs:
            dirs = ray_directions(self.fluoroscope, zoom, distorted)
            rim = np.concatenate([dirs[0], dirs[-1], dirs[:, 0], dirs[:, -1]]).astype(np.float64)
            self._dirs[key] = (self.dev.upload(dirs), rim)
        return self._dirs[key]

    def dominant_axis_of_field(self, volume: PreparedVolume, T_xray_from_ct, zoom: int, distorted: bool) -> int | None:
        """The voxel axis (0 x, 1 y, 2 z) every ray of the field steps along most (by
        DOMINANCE_MARGIN), or None where the rays differ. A ray's step along index axis i is
        linear in its direction (x, y, 1), so the condition holds for every pixel where it holds,
        one sign throughout, at the rim's."""
        rim = self._rays(zoom, distorted)[1]
        A = (volume.T_index_from_ct @ invert(np.asarray(T_xray_from_ct, float)))[:3, :3]
        d = np.abs(rim @ A[:, :2].T + A[:, 2])                          # (n, 3) index steps
        axis = int(np.argmax(d[0]))
        across = np.delete(d, axis, axis=1).max(axis=1)
        signs = np.sign(rim @ A[axis, :2] + A[axis, 2])
        if np.all(d[:, axis] > DOMINANCE_MARGIN * across) and np.all(signs == signs[0]):
            return axis
        return None

    def laid_out(self, phases: list[PreparedVolume], T_xray_from_ct, zoom: int, distorted: bool) -> list[PreparedVolume]:
        """The phases to cast the field through: their copies laid out for rays along x (`layouts`)
        where every ray runs along x, whose samples a packet then reads a row at a time (the plain
        layout has x fastest: its rows run along such rays, not across them) for the same
        integrals; else the phases themselves. Call with the device's lock held (the copies'
        cache is shared by the renderer's matrices)."""
        if self.layouts is not None:
            self.layouts.drop_dead()        # a case switched to views of other axes frees them too
        if (self.layouts is None or any(p.slab_axis >= 0 for p in phases)
                or self.dominant_axis_of_field(phases[0], T_xray_from_ct, zoom, distorted) != 0):
            return phases
        return [self.layouts.get(p, 0) for p in phases]

    def beam(self, zoom: int, collimation_mm, circle: bool) -> Beam:
        """The field's masks and their device buffers (see Beam), cached."""
        key = (zoom, None if collimation_mm is None else tuple(float(c) for c in collimation_mm), circle)
        if key not in self._masks:
            if len(self._masks) > 64:
                self._masks.clear()
            m = field_mask(self.fluoroscope, zoom, collimation_mm, circle)
            exposed = field_edge(m, penumbra_px(self.fluoroscope, zoom)) > 0
            central = measuring_field(m)
            inside = np.flatnonzero(central).astype(np.int32)
            step = max(1, len(inside) // ABC_SAMPLE_PIXELS)
            sample = np.ascontiguousarray(inside[::step]) if len(inside) else np.zeros(1, np.int32)
            self._masks[key] = Beam(m, self.dev.upload(m.astype(np.uint8)), central, exposed,
                                    self.dev.upload(exposed.astype(np.uint8)), sample, self.dev.upload(sample),
                                    np.flatnonzero(m), np.flatnonzero(central))
        return self._masks[key]

    # -- casting ---------------------------------------------------------------------
    def _geometry(self, vol: PreparedVolume, T_xray_from_ct: np.ndarray):
        T = np.asarray(T_xray_from_ct, dtype=np.float64)
        problem = rigid_problem(T)
        if problem:
            raise FluorosimError(f"T_xray_from_ct {problem}")
        T_index_from_xray = vol.T_index_from_ct @ invert(T)
        geo = np.zeros(16, dtype=np.float32)
        geo[:9] = T_index_from_xray[:3, :3].ravel()
        geo[9:12] = T_index_from_xray[:3, 3]
        edge = self.fluoroscope.ct_sampling.voxel_edge_px
        geo[12] = 0.0 if edge is None else edge        # 0: linear interpolation everywhere (drr.cl)
        return geo

    @staticmethod
    def _box(*vols: PreparedVolume) -> np.ndarray | None:
        boxes = [v.box for v in vols if v.box is not None]
        if not boxes:
            return None
        lo = np.min([b[0] for b in boxes], axis=0)
        hi = np.max([b[1] for b in boxes], axis=0)
        return np.array([*lo, 0, *hi, 0], dtype=np.int32)

    @staticmethod
    def _planes(*vols: PreparedVolume) -> np.ndarray:
        """The Joseph kernels' outline planes (drr.cl's clip_planes) holding every one of `vols`'
        content (the union of each plane's ranges); no plane where one has no outline."""
        outline = union(v.outline for v in vols if v.box is not None)
        return np.zeros(1, np.float32) if outline is None else outline.planes(JOSEPH_REACH, OUTLINE_MARGIN)

    def _field_planes(self, vols, box: np.ndarray, T_xray_from_ct, zoom: int, distorted: bool) -> np.ndarray:
        """`_planes(*vols)` less those that cut no ray of the field within the kernels' `box`
        grown by a voxel (outline.cutting): the same integrals, without their cost."""
        T_index_from_xray = vols[0].T_index_from_ct @ invert(np.asarray(T_xray_from_ct, float))
        return cutting(self._planes(*vols), T_index_from_xray, self._rays(zoom, distorted)[1],
                       box[:3] - 1.0, box[4:7] + 1.0)

    def cast(self, volume, T_xray_from_ct, zoom, collimation_mm, blend, distorted, circle, bands=None, thin=None):
        """Device buffer of (rows, cols, 4) float32 material integrals over the exposed field
        (the edge's penumbra included; zero beyond it), and that field's mask.

        `thin` = (slab, slab_blend, rule), the packet kernel only: each packet whose rays allow by
        `rule` (slabs.thin_rule) reads `slab`, the slab copy of `volume` (and `slab_blend`, of the
        blended phase), instead of the full volume (drr.cl's SLABBED).

        `bands` = (lock, n) or (lock, n, cancelled): cast in n bands of detector rows, holding
        `lock` for one band at a time, so that a long cast (a saved image at the native matrix on
        a CPU device) lets the live frames in between its bands instead of freezing the screen
        for its length; between bands, `cancelled()` true raises CastCancelled (a shutdown must
        not wait for the whole cast)."""
        dev, cl = self.dev, self.dev.cl
        rows, cols = self.shape
        if blend is not None and not volume.same_grid(blend[0]):
            raise ValueError("phases to blend must share one voxel grid")
        # The pose is checked before any copy is made; a copy laid out for the rays keeps the
        # phase's voxel indices, hence this geometry.
        geo = self._geometry(volume, T_xray_from_ct)
        phases = [volume] if blend is None else [volume, blend[0]]
        if bands is None:
            phases = self.laid_out(phases, T_xray_from_ct, zoom, distorted)
        else:
            with bands[0]:
                phases = self.laid_out(phases, T_xray_from_ct, zoom, distorted)
        volume, blend = phases[0], None if blend is None else (phases[1], blend[1])
        beam = self.beam(zoom, collimation_mm, circle)
        mask, mask_buf = beam.exposed, beam.exposed_buf
        dirs = self._dirs_buffer(zoom, distorted)
        vols = (volume,) if blend is None else (volume, blend[0])
        box = self._box(*vols)
        lines = dev.scratch(rows * cols * 16)
        if box is None:
            cl.enqueue_fill_buffer(dev.queue, lines, np.float32(0), 0, rows * cols * 16)
            return lines, mask
        nx, ny, nz = volume.shape_xyz
        if blend is None:
            kernel, first = self._joseph, (volume.buffer,)
        else:
            if self._joseph_blend is None:
                self._joseph_blend = dev.kernel(self._joseph_name, "BLEND")
            kernel, first = self._joseph_blend, (volume.buffer, blend[0].buffer, np.float32(blend[1]))
        args = (*first, np.int32(nx), np.int32(ny), np.int32(nz), np.int32(volume.slab_axis), dirs, mask_buf,
                dev.upload(geo), dev.upload(box),
                dev.upload(self._field_planes(vols, box, T_xray_from_ct, zoom, distorted)), self._mat_buf)
        tail = (np.int32(cols), lines) if self.packet else (lines,)
        if thin is not None and self.packet:
            slab, slab_blend, rule = thin
            kernel, extra = self.thin_args((slab,) if blend is None else (slab, slab_blend), rule,
                                           None if blend is None else "BLEND", T_xray_from_ct, zoom, distorted)
            tail = (*tail, *extra)
        width = -(-cols // PACKET) if self.packet else cols
        self.run_rows(kernel, width, (*args, *tail), bands)
        return lines, mask

    def run_rows(self, kernel, width: int, args: tuple, bands=None) -> None:
        """Run a cast kernel over the detector's rows (global size (width, rows)): at once, or in
        `bands` as `cast` says, holding the lock one band at a time and finishing each."""
        queue, rows = self.dev.queue, self.shape[0]
        if bands is None:
            kernel(queue, (width, rows), None, *args)
            return
        lock, n, *rest = bands
        cancelled = rest[0] if rest else None
        step = -(-rows // max(1, n))
        for r0 in range(0, rows, step):
            if cancelled is not None and cancelled():
                raise CastCancelled(f"cast cancelled after {r0} of {rows} rows")
            with lock:
                kernel(queue, (width, min(step, rows - r0)), None, *args, global_offset=(0, r0))
                queue.finish()
            time.sleep(BAND_YIELD_S)    # a frame waiting for the lock gets it (Python's lock is not fair)

    def slabbed_kernel(self, second: str | None = None):
        """The packet kernel's SLABBED build (with `second`'s, BLEND or SPLIT, for two phases),
        built on first use: a renderer's warm-up asks for them, since a fresh build takes seconds
        on PoCL."""
        variant = "SLABBED" if second is None else f"SLABBED {second}"
        if variant not in self._joseph_slabbed:
            self._joseph_slabbed[variant] = self.dev.kernel(self._joseph_name, variant)
        return self._joseph_slabbed[variant]

    def thin_args(self, slabs: tuple[PreparedVolume, ...], rule: np.ndarray, second: str | None, T_xray_from_ct,
                  zoom: int, distorted: bool):
        """The SLABBED build of the packet kernel (`second`: see slabbed_kernel) and its arguments
        after the plain build's: the slab copies of the phases (one, or two on one grid), their
        grid's shape, layout, geometry, box and outline, then the rule (slabs.thin_rule)."""
        box = self._box(*slabs)
        assert box is not None, "a slab copy keeps its phase's content box"     # cast() returned on none
        nx, ny, nz = slabs[0].shape_xyz
        dev = self.dev
        return self.slabbed_kernel(second), (
            *(v.buffer for v in slabs), np.int32(nx), np.int32(ny), np.int32(nz), np.int32(slabs[0].slab_axis),
            dev.upload(self._geometry(slabs[0], T_xray_from_ct)), dev.upload(box),
            dev.upload(self._field_planes(slabs, box, T_xray_from_ct, zoom, distorted)),
            dev.upload(np.asarray(rule, np.float32)))

    def material_integrals(self, volume, T_xray_from_ct, zoom, collimation_mm, blend, distorted, circle) -> np.ndarray:
        """(rows, cols, 4) float32: each material's density integrated along each ray
        (g/cm^3 * mm), Joseph's method; zero outside the beam."""
        lines, _ = self.cast(volume, T_xray_from_ct, zoom, collimation_mm, blend, distorted, circle)
        return self.dev.download(lines, np.empty(self.shape + (4,), dtype=np.float32))

    def sample_lines(self, lines: cl.Buffer | BlendedLines, beam: Beam) -> np.ndarray:
        """(n, 4) float32 material integrals of the cast `lines` at the beam's sample of its
        measuring field: what the exposure control reads (gathered on the device)."""
        n = len(beam.sample)

        def gather(buf) -> np.ndarray:
            out = self.dev.scratch(n * 16)
            self._gather(self.dev.queue, (n,), None, buf, beam.sample_buf, out)
            return self.dev.download(out, np.empty((n, 4), dtype=np.float32))
        if not isinstance(lines, BlendedLines):
            return gather(lines)
        a, b = lines.samples if lines.samples is not None else (gather(lines.a), gather(lines.b))
        return a + np.float32(lines.w) * (b - a)

    def intensity(self, lines: cl.Buffer | BlendedLines, tables: DetectorTables, zoom, collimation_mm,
                  circle, on_device: bool = False):
        """(rows, cols) float32 detector signal relative to the open beam, before any blur, of the
        cast `lines` through the detector `tables`; 0 outside the beam. `on_device`: the device
        buffer that holds it instead (device_chain.py goes on from there)."""
        dev = self.dev
        rows, cols = self.shape
        weights, mu_rho, n_e = tables.weights_buf, tables.mu_buf, tables.device_bins
        mask_buf = self.beam(zoom, collimation_mm, circle).exposed_buf
        out_buf = dev.scratch(rows * cols * 4)
        if isinstance(lines, BlendedLines):
            first, second, w = lines.a, lines.b, np.float32(lines.w)
        else:
            first, second, w = lines, lines, np.float32(0.0)
        if self.packet:
            self._poly_kernel(dev.queue, (-(-rows * cols // PACKET),), None, first, second, w, mask_buf, weights,
                              mu_rho, np.int32(n_e), np.int32(rows * cols), out_buf)
        else:
            self._poly_kernel(dev.queue, (rows * cols,), None, first, second, w, mask_buf, weights, mu_rho,
                              np.int32(n_e), out_buf)
        if on_device:
            return out_buf
        return dev.download(out_buf, np.empty((rows, cols), dtype=np.float32))

    def line_integral(self, volume: PreparedVolume, T_xray_from_ct, zoom: int = 1, collimation_mm=None) -> np.ndarray:
        """(rows, cols) float32: sum of mu * length along the ray through each undistorted
        pixel centre, mu = mu_water (1 + HU/1000) clipped at 0 at the effective energy;
        exact Siddon path lengths through constant voxels."""
        dev = self.dev
        rows, cols = self.shape
        geo = self._geometry(volume, T_xray_from_ct)
        mask_buf = self.beam(zoom, collimation_mm, False).mask_buf
        dirs = self._dirs_buffer(zoom, False)
        out = np.zeros((rows, cols), dtype=np.float32)
        box = self._box(volume)
        if box is None:
            return out
        out_buf = dev.scratch(out.nbytes)
        nx, ny, nz = volume.shape_xyz
        self._siddon(dev.queue, (cols, rows), None, volume.buffer, np.int32(nx), np.int32(ny), np.int32(nz),
                     dirs, mask_buf, dev.upload(geo), dev.upload(box), out_buf)
        dev.download(out_buf, out)
        return out * np.float32(self.mu_water_per_mm)
