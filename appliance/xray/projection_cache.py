"""A frame costs only what changed: material line integrals cached for an unchanged pose.

A projection is linear in the volume. While the C-arm stands still, each CT phase's four
material integrals (air, soft tissue, bone, contrast; the `lines` of `Caster.cast`) are
the same from frame to frame, so they are cast once per phase and kept on the device; a
frame between two phases blends the two phases' integrals in projection space, which is
exactly the projection of the linear blend of the two phases' material densities; and only
the detector (spectrum, blur, ABC, quantum noise, display) runs per frame. Breathing and a
changing contrast concentration then cost no ray cast at all.

"Unchanged" is judged where it shows: the pose counts as unchanged while no corner of the
patient's content box moves by more than `cache_pose_tolerance_px` on the detector.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .casting import BlendedLines
from .renderer import PACKET, Frame, PreparedVolume, Renderer, View, zoomed_K
from .slabs import Through

if TYPE_CHECKING:
    import pyopencl as cl


def pose_unchanged(fluoroscope, volume: PreparedVolume, zoom: int, T_before: np.ndarray | None,
                   T_now: np.ndarray, tolerance_px: float) -> bool:
    """Whether going from pose `T_before` to `T_now` (T_xray_from_ct) moves no corner of the
    volume's content box by more than `tolerance_px` on the detector at `zoom`: the one rule for
    "the C-arm has not moved" that the projection cache and progressive resolution share.
    No earlier pose: moved; an empty volume: unchanged."""
    if T_before is None:
        return False
    corners = box_corners_ct(volume)
    if corners is None:
        return True
    return detector_shift_px(zoomed_K(fluoroscope, zoom), corners, T_before, T_now) <= tolerance_px


@dataclass
class CacheCounts:
    """What the cache did: casts (phases cast), of them pairs cast in one pass, hits (phases
    reused), frames drawn."""

    casts: int = 0
    paired: int = 0
    hits: int = 0
    frames: int = 0


def box_corners_ct(volume: PreparedVolume) -> np.ndarray | None:
    """(8, 3) corners of the volume's content box in the ct frame (mm), or None when empty."""
    if volume.box is None:
        return None
    lo, hi = np.asarray(volume.box[0], float) - 0.5, np.asarray(volume.box[1], float) + 0.5
    idx = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return (np.linalg.inv(volume.T_index_from_ct) @ idx.T).T[:, :3]


def detector_shift_px(K: np.ndarray, corners_ct: np.ndarray, T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Largest displacement on the detector (pixels, pinhole K) of `corners_ct` between poses
    T_a and T_b (T_xray_from_ct); infinite when a corner lies behind the focal spot."""
    def project(T):
        p = (T[:3, :3] @ corners_ct.T).T + T[:3, 3]
        if np.any(p[:, 2] <= 1e-6):
            return None
        uv = (K @ (p / p[:, 2:3]).T).T
        return uv[:, :2]
    a, b = project(np.asarray(T_a, float)), project(np.asarray(T_b, float))
    if a is None or b is None:
        return float("inf")
    return float(np.max(np.linalg.norm(a - b, axis=1)))


class ProjectionCache:
    """Wraps a `Renderer`: `render` takes the renderer's arguments and gives its images, casting
    a phase only when the pose (or the view's geometry) changed since that phase was cast."""

    def __init__(self, renderer: Renderer, pose_tolerance_px: float = 0.25, max_phases: int = 12,
                 through: Callable[[PreparedVolume, np.ndarray, int], Through] | None = None):
        """`through(phase, T_xray_from_ct, zoom)`: how a phase is cast at that pose (slabs.Through:
        through its slab copy, packet by packet, or the phase itself; slabs.slab_through), asked
        with the device's lock held; None: the phase itself. The integrals are kept as the phase's."""
        self.renderer = renderer
        self._through = through
        self.pose_tolerance_px = float(pose_tolerance_px)
        self.max_phases = int(max_phases)
        self.counts = CacheCounts()
        self._pose: np.ndarray | None = None
        self._key: tuple | None = None
        self._lines: dict[PreparedVolume, cl.Buffer] = {}     # phase -> device buffer of its integrals
        # phase -> (its integrals' buffer, the exposure control's sample of them on the host)
        self._samples: dict[PreparedVolume, tuple[cl.Buffer, np.ndarray]] = {}
        self._split: cl.Kernel | None = None    # the two-phase cast kernel, built on first use
        self._blend: cl.Kernel | None = None

    # -- what is cached ------------------------------------------------------------------
    def _geometry_key(self, zoom: int, collimation_mm, distorted: bool, circle) -> tuple:
        r = self.renderer
        c = None if collimation_mm is None else tuple(float(x) for x in collimation_mm)
        # A reloaded fluoroscope profile replaces the renderer's ray tables: a new key.
        return (id(r.fluoroscope), r.shape, zoom, c, distorted, circle)

    def unchanged(self, volume: PreparedVolume, T_xray_from_ct: np.ndarray, zoom: int) -> bool:
        """True when the pose moves the content box's corners by no more than the tolerance
        since the cached pose."""
        return pose_unchanged(self.renderer.fluoroscope, volume, zoom, self._pose, T_xray_from_ct,
                              self.pose_tolerance_px)

    def _adopt(self, volume: PreparedVolume, T_xray_from_ct, zoom: int, collimation_mm, distorted: bool,
               circle) -> None:
        key = self._geometry_key(zoom, collimation_mm, distorted, circle)
        if key != self._key or not self.unchanged(volume, T_xray_from_ct, zoom):
            self._lines.clear()
            self._samples.clear()
            self._key = key
            self._pose = np.array(T_xray_from_ct, dtype=np.float64)

    def adopted(self, T_xray_from_ct, zoom: int, collimation_mm, distorted: bool, circle) -> bool:
        """Whether the cache holds projections of this field at this pose (within the tolerance):
        a frame here casts at most the phases it has not cast yet."""
        # A copy of the keys: a cast beside the live frames may keep phases meanwhile.
        volume = next(iter(list(self._lines)), None)
        return (volume is not None and self._geometry_key(zoom, collimation_mm, distorted, circle) == self._key
                and self.unchanged(volume, T_xray_from_ct, zoom))

    def holds(self, phases: list[PreparedVolume]) -> bool:
        """Whether every one of `phases` is cached (at the adopted pose)."""
        return all(p in self._lines for p in phases)

    def fill(self, phases: list[PreparedVolume], T_xray_from_ct, zoom: int, collimation_mm, distorted: bool, circle,
             bands: int, cancelled: Callable[[], bool]) -> bool:
        """Cast `phases` at this pose in `bands` bands of rows each (Caster.cast: the device's lock
        is held one band at a time, so live frames of other matrices go on in between) and keep
        them as `render` would have. Meant for a thread of its own; live frames may render
        through this cache meanwhile (what is kept is kept under the device's lock), and one that
        needs a phase still being cast here casts it itself. `cancelled()` true between bands
        ends it (CastCancelled). False when the fluoroscope profile was replaced meanwhile
        (nothing kept)."""
        r = self.renderer
        key = self._geometry_key(zoom, collimation_mm, distorted, circle)
        with r._lock:
            cast_as = {p: self._cast_as(p, T_xray_from_ct, zoom) for p in dict.fromkeys(phases)}
        banded = (r._lock, bands, cancelled)
        if self._pairs(list(cast_as.values())):
            # A breathing patient's two phases in one pass, as a frame casts them: at the adult
            # chest's 512 matrix a quarter less device time than one after the other, in half the
            # bands (each waits for the live frames between them).
            first, second = cast_as.values()
            lines = dict(zip(cast_as, self.cast_two(first, second, T_xray_from_ct, zoom, collimation_mm,
                                                    distorted, circle, bands=banded)))
            self.counts.paired += 1
        else:
            lines = {p: r.caster.cast(t.volume, T_xray_from_ct, zoom, collimation_mm, None, distorted, circle,
                                      bands=banded, thin=t.cast_thin)[0] for p, t in cast_as.items()}
        with r._lock:           # live frames may draw from this cache meanwhile (a held view's)
            if self._geometry_key(zoom, collimation_mm, distorted, circle) != key:
                return False
            self.keep(lines, T_xray_from_ct, zoom, collimation_mm, distorted, circle)
            self.counts.casts += len(lines)
        return True

    def keep(self, lines: dict[PreparedVolume, cl.Buffer], T_xray_from_ct, zoom: int, collimation_mm,
             distorted: bool, circle) -> None:
        """Keep integrals cast elsewhere at this pose and field (phase -> device buffer, as
        `Caster.cast` gives them) as the cached projections of those phases."""
        self._adopt(next(iter(lines)), T_xray_from_ct, zoom, collimation_mm, distorted, circle)
        self._lines.update(lines)
        self._keep_at_most(lines)

    # -- the cast the renderer calls -------------------------------------------------------
    def _cast_phases(self, phases: list[PreparedVolume], T, zoom, collimation_mm, distorted, circle) -> None:
        """Cast the phases not cached yet (two on one grid in one pass where the kernel can)."""
        r = self.renderer
        missing = [p for p in phases if p not in self._lines]
        self.counts.hits += len(phases) - len(missing)
        cast_as = [self._cast_as(p, T, zoom) for p in missing]
        if self._pairs(cast_as):
            self._lines.update(zip(missing, self.cast_two(cast_as[0], cast_as[1], T, zoom, collimation_mm,
                                                           distorted, circle)))
            self.counts.casts += 2
            self.counts.paired += 1
            missing = []
        for p, t in zip(missing, cast_as):
            self._lines[p], _ = r.caster.cast(t.volume, T, zoom, collimation_mm, None, distorted, circle,
                                              thin=t.cast_thin)
            self.counts.casts += 1
        self._keep_at_most(phases)

    def _pairs(self, cast_as: list[Through]) -> bool:
        """Whether these phases are cast in one pass of the two-phase kernel (cast_two): two, on
        one grid, both through slab copies or neither, on the packet kernel."""
        return (len(cast_as) == 2 and self.renderer.packet and cast_as[0].volume.same_grid(cast_as[1].volume)
                and (cast_as[0].thin is None) == (cast_as[1].thin is None))

    def _cast_as(self, phase: PreparedVolume, T, zoom: int) -> Through:
        """How `phase` is cast at this pose (see `through`)."""
        return Through(phase) if self._through is None else self._through(phase, T, zoom)

    def _keep_at_most(self, wanted) -> None:
        """Drop the oldest cached phases beyond `max_phases`, never one of `wanted` (this frame's)."""
        while len(self._lines) > self.max_phases:
            del self._lines[next(k for k in self._lines if k not in wanted)]

    def cast_two(self, ta: Through, tb: Through, T, zoom, collimation_mm, distorted, circle, bands=None):
        """Both phases' integrals from one pass of the SPLIT packet kernel over the two volumes
        (packet by packet through their slab copies too where `ta` and `tb` say so); in `bands`
        as Caster.cast says."""
        dev, caster = self.renderer.dev, self.renderer.caster
        cl = dev.cl
        if self._split is None:
            self._split = dev.kernel("joseph_packet", "SPLIT")
        a, b = ta.volume, tb.volume
        rows, cols = caster.shape
        out_a, out_b = dev.scratch(rows * cols * 16), dev.scratch(rows * cols * 16)
        box = caster._box(a, b)
        if box is None:
            for out in (out_a, out_b):
                cl.enqueue_fill_buffer(dev.queue, out, np.float32(0), 0, rows * cols * 16)
            return out_a, out_b
        mask_buf = caster.beam(zoom, collimation_mm, circle).exposed_buf
        kernel, thin = self._split, ()
        if ta.thin is not None and tb.thin is not None:
            kernel, thin = caster.thin_args((ta.thin[0], tb.thin[0]), ta.thin[1], "SPLIT", T, zoom, distorted)
        if bands is None:
            a, b = caster.laid_out([a, b], T, zoom, distorted)
        else:
            with bands[0]:
                a, b = caster.laid_out([a, b], T, zoom, distorted)
        nx, ny, nz = a.shape_xyz
        caster.run_rows(kernel, -(-cols // PACKET), (
            a.buffer, b.buffer, np.int32(nx), np.int32(ny), np.int32(nz), np.int32(a.slab_axis),
            caster._dirs_buffer(zoom, distorted), mask_buf, dev.upload(caster._geometry(a, T)), dev.upload(box),
            dev.upload(caster._field_planes((a, b), box, T, zoom, distorted)), caster._mat_buf, np.int32(cols),
            out_a, out_b, *thin), bands)
        return out_a, out_b

    def _cached_cast(self, volume, T, zoom, collimation_mm, blend, distorted, circle, fused: bool = True):
        """`Caster.cast`'s stand-in: (the frame's material integrals, beam mask): a device buffer,
        or with `fused` between two phases the two phases' buffers as `BlendedLines`."""
        r = self.renderer
        dev = r.dev
        self._adopt(volume, T, zoom, collimation_mm, distorted, circle)
        # In projection space, phases on different grids blend as well.
        phases = [volume] if blend is None or blend[1] == 0.0 else [volume, blend[0]]
        self._cast_phases(phases, T, zoom, collimation_mm, distorted, circle)
        mask = r.caster.beam(zoom, collimation_mm, circle).exposed
        if not fused:
            if len(phases) == 1:
                return self._lines[volume], mask
        else:
            # The detector's kernel blends as it reads; the control's sample, gathered once per
            # cast phase, blends on the host.
            beam = r.caster.beam(zoom, collimation_mm, circle)
            a, b = phases[0], phases[-1]
            w = float(blend[1]) if len(phases) == 2 else 0.0
            return BlendedLines(self._lines[a], self._lines[b], w, (self._sample(a, beam), self._sample(b, beam))), mask
        if self._blend is None:
            self._blend = dev.kernel("blend_lines")
        rows, cols = r.shape
        out = dev.scratch(rows * cols * 16)
        self._blend(dev.queue, (rows * cols,), None, self._lines[volume], self._lines[blend[0]],
                    np.float32(blend[1]), out)
        return out, mask

    def _sample(self, volume: PreparedVolume, beam) -> np.ndarray:
        """The exposure control's sample of the phase's cached integrals (Caster.sample_lines),
        gathered from the device once per cast."""
        lines = self._lines[volume]
        held = self._samples.get(volume)
        if held is None or held[0] is not lines:
            held = self._samples[volume] = (lines, self.renderer.caster.sample_lines(lines, beam))
            for stale in [v for v in self._samples if v not in self._lines]:
                del self._samples[stale]
        return held[1]

    # -- frames ----------------------------------------------------------------------------
    def render(self, volume: PreparedVolume, T_xray_from_ct: np.ndarray, view: View,
               blend: tuple[PreparedVolume, float] | None = None,
               concentration_factor: float | None = None) -> Frame:
        """The renderer's frame (see `Renderer.render`) from cached line integrals where the pose
        is unchanged. `concentration_factor` scales the case's iodine concentration (contrast
        filling or washing out); None keeps it."""
        self.counts.frames += 1
        if view.quantity == "line-integral":
            return self.renderer.render(volume, T_xray_from_ct, view)
        return self.renderer.render(volume, T_xray_from_ct, view, blend, cast=self._cached_cast,
                                    concentration_factor=concentration_factor)

    def material_integrals(self, volume: PreparedVolume, T_xray_from_ct, view: View,
                           blend: tuple[PreparedVolume, float] | None = None) -> np.ndarray:
        """(rows, cols, 4) float32 material integrals (g/cm^3 * mm) of the frame, as the detector
        receives them: blended in projection space between cached phases."""
        r = self.renderer
        r._check(volume, *(() if blend is None else (blend[0],)))
        with r._lock:
            lines, _ = self._cached_cast(volume, T_xray_from_ct, view.zoom, view.collimation_mm, blend, True,
                                         r._circle(None), fused=False)
            return r.dev.download(lines, np.empty(r.shape + (4,), dtype=np.float32))

    def clear(self) -> None:
        """Forget every cached projection (a new case, a replaced renderer)."""
        self._lines.clear()
        self._samples.clear()
        self._pose = None
        self._key = None
