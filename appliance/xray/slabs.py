"""Pre-integrated slabs: a phase with each pair of slices along one axis averaged into one, so
that a moving frame's cast takes half the samples and still counts every voxel.

Joseph's method samples a ray once per slice along its dominant axis. Sampling every second
slice halves the cost but aliases: a face on a voxel boundary moves in steps of two voxels,
and a thin structure between two samples is lost. A slab is the average of two slices, so a
ray through the slab grid (voxels twice as deep along that axis, `slab_rows` in drr.cl)
integrates the same density: what the slab approximates is the ray's shift within a slab,
where the two slices are read at the slab's middle instead of where the ray crosses each.
That shift is (slab thickness) x (the ray's slope across the axis); it is used only where,
seen on the detector, it stays below `rendering.slab_max_shift_px` of the cast matrix's
pixel, for every ray of the field (the corner rays are the steepest), for moving frames; a
held view only with `rendering.rest_slab_max_shift_px`, by the same rule at the held matrix's
pixel (ProjectionCache's `through`), else from the full volume. Where the shift stays within the
detector's own point-spread it does not show.

A slab copy is half a phase on the device, made once per phase and axis when a moving frame
first needs it and kept for the last `rendering.slab_phases` of them. It is laid out for rays
along its axis (drr.cl's LAYOUT: rows across the rays contiguous, whatever the axis), so a
lateral view's samples are read as a posterior-anterior view's are, a row at a time, not voxel
by voxel.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..geometry import invert
from .casting import PAD, PreparedVolume
from .pixel_geometry import zoomed_K

#: Slices averaged into one slab (count): `slab_rows` averages pairs.
SLAB = 2
#: Slices averaged into one of the thicker slabs a field's middle takes where the whole field
#: allows SLAB (count; `slab_rows` averages four).
THICK = 2 * SLAB
#: Phases kept as THICK slabs: the two a frame blends (count; a quarter phase each, 10 MB for the
#: adult chest's content box; the slab copies' cache keeps more, rendering.slab_phases).
THICK_PHASES = 2
#: Phases a renderer keeps laid out for rays along x (one-slice slabs, Caster.laid_out), each as
#: large as the phase (39 MB for the adult chest's content box): the two a frame blends (count).
#: Breathing changes the pair every few tenths of a second, one copy pass each (see README).
LAYOUT_PHASES = 2
#: Buffers a copies' cache keeps of copies gone, to write the next one of that size into (count,
#: SlabCache._spare): one, since a breathing patient's next copy replaces the one evicted for it.
SPARE_BUFFERS = 1


def slab_index_from_index(shape_xyz: tuple[int, int, int], axis: int,
                          thickness: int = SLAB) -> tuple[np.ndarray, tuple[int, int, int]]:
    """The map from a phase's padded voxel indices to its slab grid's along `axis` (slabs of
    `thickness` slices), and the slab grid's padded shape (x, y, z). Slab q >= PAD spans padded
    slices from n (q - PAD) + PAD on (n the thickness), whose middle is index
    n (q - PAD) + PAD + (n - 1) / 2: q = (p - PAD - (n - 1) / 2) / n + PAD (the identity for n = 1)."""
    S = np.eye(4)
    S[axis, axis] = 1.0 / thickness
    S[axis, 3] = PAD - (PAD + (thickness - 1) / 2.0) / thickness
    shape = list(shape_xyz)
    shape[axis] = -(-(shape[axis] - 2 * PAD) // thickness) + 2 * PAD
    return S, (shape[0], shape[1], shape[2])


def slab_box(box, axis: int, thickness: int = SLAB):
    """The content box (inclusive padded indices) in the slab grid along `axis`."""
    if box is None:
        return None
    lo, hi = list(box[0]), list(box[1])
    lo[axis] = (lo[axis] - PAD) // thickness + PAD
    hi[axis] = (hi[axis] - PAD) // thickness + PAD
    return (lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2])


def slab_outline(outline, S: np.ndarray, axis: int, thickness: int = SLAB):
    """The content's outline (outline.py) in the slab grid q = S p along `axis`: a slab holds
    slices up to (thickness - 1) / 2 from its middle along the axis, whose content it keeps."""
    if outline is None:
        return None
    half = np.zeros(3)
    half[axis] = (thickness - 1) / 2.0
    return outline.moved(S, half)


def dominant_axis(volume: PreparedVolume, T_xray_from_ct: np.ndarray) -> int:
    """The voxel axis (0 x, 1 y, 2 z) the principal ray crosses most slices of."""
    d = volume.T_index_from_ct[:3, :3] @ invert(np.asarray(T_xray_from_ct, float))[:3, :3] @ np.array([0.0, 0.0, 1.0])
    return int(np.argmax(np.abs(d)))


def shift_scale(K: np.ndarray, volume: PreparedVolume, T_xray_from_ct: np.ndarray, axis: int) -> np.ndarray:
    """(r_b, r_c): a ray with direction d in `volume`'s voxel indices moves |(r_b d_b, r_c d_c)| / |d_a|
    pixels of the matrix of `K` across `axis` (a) within one slab, seen on the detector at the depth
    of the volume's middle (b < c the other two axes). Within a slab the ray advances SLAB voxels
    along a; across it, in mm, SLAB d_b / |d_a| voxels of b's spacing and as many of c's."""
    T = np.asarray(T_xray_from_ct, float)
    ct_from_index = np.linalg.inv(volume.T_index_from_ct)[:3, :3]
    per_voxel_mm = np.linalg.norm(ct_from_index, axis=0)
    box = volume.box
    if box is None:                     # nothing but air: no ray crosses anything to shift
        return np.zeros(2)
    centre = np.append((np.asarray(box[0], float) + box[1]) / 2.0, 1.0)
    depth = float((T @ np.linalg.inv(volume.T_index_from_ct) @ centre)[2])
    return np.delete(per_voxel_mm, axis) * SLAB * K[0, 0] / max(depth, 1e-6)


def in_slab_shift_px(K: np.ndarray, shape: tuple[int, int], volume: PreparedVolume, T_xray_from_ct: np.ndarray,
                     axis: int, principal: bool = False) -> float:
    """How far the steepest ray of the field (a corner's; `principal`: the principal ray) moves
    across `axis` within one slab, seen on the detector at the depth of the volume's middle
    (pixels of the matrix of `K`, see shift_scale)."""
    if volume.box is None:
        return 0.0
    rows, cols = shape
    index_from_xray = volume.T_index_from_ct @ invert(np.asarray(T_xray_from_ct, float))
    rays = [[K[0, 2], K[1, 2], 1]] if principal else [[0, 0, 1], [cols - 1, 0, 1], [0, rows - 1, 1],
                                                      [cols - 1, rows - 1, 1], [K[0, 2], K[1, 2], 1]]
    d_index = np.array(rays, float) @ np.linalg.inv(K).T @ index_from_xray[:3, :3].T
    r = shift_scale(K, volume, T_xray_from_ct, axis)
    d_b, d_c = np.delete(d_index, axis, axis=1).T
    return float(np.max(np.hypot(r[0] * d_b, r[1] * d_c) / np.abs(d_index[:, axis])))


class SlabCache:
    """Copies of phases on one renderer's device, slabs of `thickness` slices (SLAB for moving
    frames' pre-integrated slabs, 1 for a phase laid out for rays along an axis), the last
    `keep` (phase, axis) pairs."""

    def __init__(self, dev, keep: int, thickness: int = SLAB, thicker: bool = False):
        self.dev, self.keep, self.thickness = dev, keep, thickness
        self._kernel = dev.kernel("slab_rows")
        self._slabs: OrderedDict[tuple[int, int], tuple[weakref.ref[PreparedVolume], PreparedVolume]] = OrderedDict()
        self._lock = threading.Lock()
        #: Device buffers of copies evicted and no longer held anywhere, by size (bytes): the next
        #: copy of that size is written into one. A fresh buffer's pages fault in on the copy's
        #: first write, which doubled a lateral layout copy's time (a new breathing phase every
        #: few tenths of a second makes one); at most SPARE_BUFFERS are kept.
        self._spare: OrderedDict[int, list] = OrderedDict()
        self._spare_lock = threading.RLock()      # a copy may die, and retire, inside _get
        #: Copies made (count): one per phase and axis while they stay in the cache.
        self.made = 0
        #: With `thicker`, the slabs twice as thick (THICK), for the middle of a field whose every
        #: ray allows SLAB (slab_through), at most THICK_PHASES kept; else None (the whole field
        #: through SLAB).
        self.thicker = SlabCache(dev, min(keep, THICK_PHASES), THICK) if thicker and thickness == SLAB else None

    def drop_dead(self) -> None:
        """Let go of the copies of phases no longer held elsewhere (a case switched, a timeline
        replaced); their ids may then be new phases', which the weak references tell apart."""
        dead = [k for k, (ref, _) in self._slabs.items() if ref() is None]
        for key in dead:
            del self._slabs[key]
        if dead:                            # the case moved on: its spares go with its copies
            with self._spare_lock:
                self._spare.clear()

    def get(self, volume: PreparedVolume, axis: int) -> PreparedVolume:
        # A held view's cast beside the live frames (ProjectionCache's `through`) asks on its own
        # thread while a moving frame may ask on the renderer's.
        with self._lock:
            return self._get(volume, axis)

    def _get(self, volume: PreparedVolume, axis: int) -> PreparedVolume:
        self.drop_dead()
        key = (id(volume), axis)
        hit = self._slabs.get(key)
        if hit is not None and hit[0]() is volume:
            self._slabs.move_to_end(key)
            return hit[1]
        S, shape = slab_index_from_index(volume.shape_xyz, axis, self.thickness)
        nbytes = 2 * shape[0] * shape[1] * shape[2]
        while len(self._slabs) >= self.keep:
            self._slabs.popitem(last=False)         # its buffer a spare once nothing holds the copy
        out = self._buffer(nbytes)
        nx, ny, _ = volume.shape_xyz
        # One work-item per slice c of the layout (its slowest axis), each its own work-group:
        # left to itself, PoCL put them all in one, on one core.
        slowest = shape[2] if axis != 2 else shape[1]
        self._kernel(self.dev.queue, (slowest,), (1,), volume.buffer, np.int32(nx), np.int32(ny), np.int32(axis),
                     np.int32(self.thickness), np.int32(volume.shape_xyz[axis]), np.int32(shape[0]), np.int32(shape[1]),
                     np.int32(shape[2]), out)
        what = "slabs" if self.thickness > 1 else "rows along the rays"
        slab = PreparedVolume(buffer=out, shape_xyz=shape, T_index_from_ct=S @ volume.T_index_from_ct,
                              box=slab_box(volume.box, axis, self.thickness), nbytes=nbytes,
                              source=f"{volume.source} ({what})", time_s=volume.time_s,
                              _renderer_id=volume._renderer_id, slab_axis=axis,
                              outline=slab_outline(volume.outline, S, axis, self.thickness))
        self._slabs[key] = (weakref.ref(volume), slab)
        weakref.finalize(slab, self._retire, out, nbytes).atexit = False
        self.made += 1
        return slab

    def _buffer(self, nbytes: int):
        with self._spare_lock:
            spare = self._spare.get(nbytes)
            if spare:
                buffer = spare.pop()
                if not spare:
                    del self._spare[nbytes]
                return buffer
        return self.dev.scratch(nbytes)

    def _retire(self, buffer, nbytes: int) -> None:
        # Called when a copy is gone (any thread, at garbage collection). The device's one
        # in-order queue runs a later copy into the buffer after every cast that read it.
        with self._spare_lock:
            self._spare.setdefault(nbytes, []).append(buffer)
            self._spare.move_to_end(nbytes)
            while sum(len(b) for b in self._spare.values()) > SPARE_BUFFERS:
                oldest = next(iter(self._spare))
                self._spare[oldest].pop(0)
                if not self._spare[oldest]:
                    del self._spare[oldest]

    def clear(self) -> None:
        with self._lock:
            self._slabs.clear()
        with self._spare_lock:
            self._spare.clear()
        if self.thicker is not None:
            self.thicker.clear()

    @property
    def nbytes(self) -> int:
        """Device memory the copies and their spare buffers hold (bytes), the thicker slabs' included."""
        with self._spare_lock:
            spare = sum(n * len(b) for n, b in self._spare.items())
        return (spare + sum(slab.nbytes for _, slab in self._slabs.values())
                + (0 if self.thicker is None else self.thicker.nbytes))


@dataclass(frozen=True)
class Through:
    """How a phase is cast at one pose: `volume` (the phase itself, or its slab copy for the whole
    field) and, for slabs packet by packet, `thin` = (the thinner grid's copy, drr.cl's SLABBED
    rule): Caster.cast's `thin`, the packets whose rays allow reading that copy, the rest
    `volume`. `copies` and `axis` say where the copies came from (None: the phase itself), for
    another phase on the same grid (`like`)."""
    volume: PreparedVolume
    thin: tuple[PreparedVolume, np.ndarray] | None = None
    copies: tuple[SlabCache | None, SlabCache | None] = (None, None)
    axis: int = -1

    @property
    def cast_thin(self):
        """Caster.cast's `thin` for this phase alone."""
        return None if self.thin is None else (self.thin[0], None, self.thin[1])

    def like(self, phase: PreparedVolume) -> Through:
        """The same decision for `phase`, a phase on this one's grid (a blend's other phase)."""
        base, thin = self.copies
        volume = phase if base is None else base.get(phase, self.axis)
        if self.thin is None or thin is None:
            return Through(volume, None, self.copies, self.axis)
        return Through(volume, (thin.get(phase, self.axis), self.thin[1]), self.copies, self.axis)


def slab_through(caster, cache: SlabCache, volume: PreparedVolume, T_xray_from_ct: np.ndarray, zoom: int,
                 max_shift_px: float) -> Through:
    """How to cast `volume` at this pose through its slabs where the rays shift at most
    `max_shift_px` (pixels of the caster's matrix) within a slab. Where the field's steepest ray
    does, through the slab copy, and with the packet kernel, where the principal ray does within
    a slab twice as thick, each packet all of whose rays do through those (drr.cl's SLABBED).
    Else, with the packet kernel, each packet all of whose rays shift that little within a slab
    through the slab copy, the others through the full volume; the full volume alone where not
    even the principal ray does."""
    axis = dominant_axis(volume, T_xray_from_ct)
    K = zoomed_K(caster.fluoroscope, zoom)
    if in_slab_shift_px(K, caster.shape, volume, T_xray_from_ct, axis) <= max_shift_px:
        slab = cache.get(volume, axis)
        thicker = cache.thicker
        # Within a slab of the thicker grid a ray shifts what it does within SLAB of the slab
        # copy's voxels: the same rule, asked of the slab copy's grid.
        if (thicker is None or not caster.packet
                or in_slab_shift_px(K, caster.shape, slab, T_xray_from_ct, axis, True) > max_shift_px):
            return Through(slab, None, (cache, None), axis)
        return Through(slab, (thicker.get(volume, axis), thin_rule(K, slab, T_xray_from_ct, axis, max_shift_px)),
                       (cache, thicker), axis)
    if not caster.packet or in_slab_shift_px(K, caster.shape, volume, T_xray_from_ct, axis, True) > max_shift_px:
        return Through(volume)
    return Through(volume, (cache.get(volume, axis), thin_rule(K, volume, T_xray_from_ct, axis, max_shift_px)),
                   (None, cache), axis)


def slab_cast(caster, cache: SlabCache, volume: PreparedVolume, T_xray_from_ct: np.ndarray, zoom: int,
              blend: tuple[PreparedVolume, float] | None, max_shift_px: float):
    """A stand-in for `caster.cast` (Renderer.render's `cast`) through the slabs of `volume` and
    of the blended phase as slab_through decides, or None where that is the full volume alone
    (then the frame is cast through the full volume)."""
    through = slab_through(caster, cache, volume, T_xray_from_ct, zoom, max_shift_px)
    if through.volume is volume and through.thin is None:
        return None
    other = None if blend is None else through.like(blend[0])
    cast_blend = None if other is None or blend is None else (other.volume, blend[1])
    thin = None
    if through.thin is not None:
        thin = (through.thin[0], None if other is None or other.thin is None else other.thin[0], through.thin[1])

    def cast(_volume, T, zoom_, collimation_mm, _blend, distorted, circle):
        return caster.cast(through.volume, T, zoom_, collimation_mm, cast_blend, distorted, circle, thin=thin)
    return cast


def thin_rule(K: np.ndarray, volume: PreparedVolume, T_xray_from_ct: np.ndarray, axis: int,
              max_shift_px: float) -> np.ndarray:
    """drr.cl's SLABBED rule: the slab's axis, shift_scale's (r_b, r_c) and the most pixels a ray
    may shift within a slab for its packet to read the slab copy."""
    r = shift_scale(K, volume, T_xray_from_ct, axis)
    return np.array([axis, r[0], r[1], max_shift_px], np.float32)


def every_packet_rule(axis: int) -> np.ndarray:
    """A SLABBED rule by which no ray shifts, so every packet reads the slab copy (the warm-up's)."""
    return np.array([axis, 0.0, 0.0, 1.0], np.float32)
