"""Progressive resolution: the matrix that keeps the frame rate while the C-arm moves, the full
matrix once it rests.

While the pose changes every frame, each frame needs a new ray cast, and the cast costs in
proportion to the pixels: the moving matrix (`rendering.moving_matrix_px`, e.g. 256 of 512)
is cast instead and scaled up to the full matrix. A moving image is blurred by the motion
and by the recursive filter of a real unit anyway, so the coarser matrix does not show. With
`rendering.moving_matrix_min_px` the moving matrix is the largest that keeps
`rendering.frame_budget_ms`, chosen one step at a time from the frame times the render worker
reports (`frame_shown`; matrix_control.py). A step between moving matrices is hidden as the
switch to the full one is: every matrix is scaled up into the same full matrix (pixel centres
kept where the camera model puts them, so nothing shifts), and the recursive filter's state
carries over. Adjacent steps differ by an eighth to a fifth in pixel pitch, within a moving,
motion-blurred image. With `rendering.slab_max_shift_px` a moving cast goes through
pre-integrated slabs (slabs.py), half the samples, where the field's rays allow; with
`rendering.rest_slab_max_shift_px` a held view's casts too, by their own matrix's pixel. Once
the pose has stayed unchanged (within the projection cache's tolerance) for
`rendering.settle_s`, the full matrix is cast once and then served from the projection cache,
so a held view is sharp and costs only the detector per frame. With `rendering.rest_hold_px`
rest is judged against the hold instead (no move beyond it for `settle_s`; where the tracker
gives its measured pose, before the filter, that pose's stop counts, so the filter's creep is
no wait), and the rested view is held at the pose it rested at until the tracked pose leaves it
by more than the hold:
the pose filter's creep as the C-arm stops and the tracker's jitter, steps beyond the cache's
tolerance but under a pixel, would otherwise count as motion, put off the full matrix and,
once it is shown, drop the sharp view to the moving matrix and cast it again.

The switch to the full matrix is a change of sharpness and of the noise's grain, not of
brightness: both matrices are the same detector (same spectrum, photons per mm^2 and ABC),
and the ABC's median over its measuring field is the same at either. The recursive filter
hides what remains, as on a real unit: at a switch its state is resampled to the new matrix
and carried over (`RecursiveFilter.carry_over`), so the first sharp frame enters the filter
like any new frame and the image sharpens over the filter's time constant instead of
jumping; in the other direction the moving matrix takes over the sharp state and blurs into
the motion. Where a profile runs without the filter, `rendering.crossfade_s` blends the first
full-matrix frames into the last moving one instead (linearly, so the refine takes a known
time).

On a CPU device the full matrix's cast takes several frame periods (three to six at 512 on
two cores): cast within one frame, it holds the screen that long each time the C-arm comes to
rest. With `rendering.refine_bands` it is cast on a thread of its own in bands of rows, the
live frames taking the device between bands, while the moving matrix's image of the resting
pose stays on screen, from the last moving frame's integrals kept in the moving matrix's
cache, at that frame's matrix (the pose is not cast again while the bands wait); the first
frame after the cast shows the full matrix. A pose that moves on cancels the cast at its next
band. A moving frame casts its phases into the moving matrix's cache, two in one pass
(ProjectionCache.cast_two), so frames at rest between two phases (breathing) find both kept too.
Only the switch waits so: a phase that comes while the view is held at the full matrix
(breathing, a 4D CT) is cast within the frame that first needs it, as without the setting, so a
held view never drops back to the coarser matrix; with the timeline's look ahead (`upcoming`:
the phases it gives a few tenths of a second on) a held view casts those beside the live frames
first, and a frame at rest casts a phase itself only where breathing reached it sooner (the
first phase after the rest's own cast, mostly).

With `rendering.rest_matrix_px` as well (512 where the full matrix is the detector's native
1024), a rest goes through two casts beside the live frames: the rest matrix first, shown as
soon as it is done, then the full matrix, four times its pixels. A held view is then sharp about
as soon as before and reaches the native matrix later. A phase new to a view held at the full
matrix is shown at the rest matrix (cast within its frame) while the full matrix casts it
beside the live frames: casting the native matrix within one frame would hold the screen for
a few hundred ms each time breathing brought a phase the cache does not hold.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..config.rendering import Rendering
from .casting import CastCancelled
from .matrix_control import MatrixController
from .projection_cache import ProjectionCache, pose_unchanged
from .renderer import Frame, PreparedVolume, Renderer, View, at_resolution
from .slabs import SlabCache, Through, dominant_axis, every_packet_rule, slab_cast, slab_through

log = logging.getLogger(__name__)

#: A scaled-up moving frame's own field edge below this is taken as no image (fraction).
EDGE_FLOOR = 0.05


def _geometry(view: View) -> tuple:
    """What of a view a cast depends on beside the pose: (zoom, collimation_mm)."""
    return view.zoom, None if view.collimation_mm is None else tuple(float(c) for c in view.collimation_mm)


@dataclass
class Refine:
    """The full matrix being cast beside the live frames at a resting pose (`rendering.refine_bands`)."""

    T_xray_from_ct: np.ndarray
    geometry: tuple                # (zoom, collimation_mm) it is cast for
    target: Renderer               # the matrix cast: the full one, or the rest matrix before it
    cancel: bool = False           # set by the renderer when the pose or the field moves on
    done: threading.Event = field(default_factory=threading.Event)


class ProgressiveRenderer:
    """Wraps a full-matrix `Renderer` (and everything else of it is reached through this object):
    `render` gives full-matrix images, cast at the moving matrix while the pose moves."""

    def __init__(self, renderer: Renderer, settings: Rendering, clock: Callable[[], float] = time.monotonic):
        self.full = renderer
        self.settings = settings
        self.clock = clock
        #: Slab copies of the phases for moving casts, and held views' where the profile says (slabs.py);
        #: None where the profile casts none.
        self.slabs = (SlabCache(renderer.dev, settings.slab_phases, thicker=True)
                      if settings.slab_max_shift_px is not None or settings.rest_slab_max_shift_px is not None else None)
        self._caches = {id(renderer): ProjectionCache(renderer, settings.cache_pose_tolerance_px,
                                                      settings.cache_max_phases,
                                                      self._through(renderer, settings.rest_slab_max_shift_px))}
        #: Picks the moving matrix from the frame times `frame_shown` is given (matrix_control.py).
        self.control = MatrixController(settings, max(renderer.shape))
        self._movers = {n: renderer.at_matrix(n, n) for n in self.control.ladder}
        for mover in self._movers.values():
            self._caches[id(mover)] = ProjectionCache(mover, settings.cache_pose_tolerance_px,
                                                      settings.cache_max_phases,
                                                      self._through(mover, settings.slab_max_shift_px, noted=True))
        n = settings.rest_matrix_px
        #: The matrix a resting view is shown at before the full one (`rendering.rest_matrix_px`); None without.
        self.interim = renderer.at_matrix(n, n) if n is not None and n < max(renderer.shape) else None
        if self.interim is not None:
            self._caches[id(self.interim)] = ProjectionCache(self.interim, settings.cache_pose_tolerance_px,
                                                             settings.cache_max_phases,
                                                             self._through(self.interim, settings.rest_slab_max_shift_px))
        self._timed: int | None = None       # the matrix of the last frame if it was a moving cast
        self._slabbed = False                # whether the moving cache's last cast went through slabs
        self._edge_fixes: dict[tuple, np.ndarray] = {}
        #: Moving casts that went through the slabs (count).
        self.slab_casts = 0
        self._last_pose: np.ndarray | None = None
        #: The pose a rested view is held at (`rendering.rest_hold_px`); None while not held.
        self._held: np.ndarray | None = None
        #: With the hold: the pose the tracked pose has stayed within the hold of, and since when.
        self._still_pose: np.ndarray | None = None
        self._still_since = np.inf
        #: The same for the measured pose (before the tracker's filter), where the caller gives it.
        self._measured_pose: np.ndarray | None = None
        self._measured_since = np.inf
        self._last_motion = -np.inf
        self._last_used: Renderer = renderer
        self._last_image: np.ndarray | None = None
        self._fade_from: np.ndarray | None = None
        self._fade_t0 = 0.0
        #: How long after the pose came to rest (the start of the last frame that moved) the first
        #: full-matrix image after it was ready for the screen, its cast included (s, `clock`): the
        #: "native matrix within 500 ms" figure.
        self.refined_after_s: list[float] = []
        #: When (s, `clock`) each of those first full-matrix images was ready for the screen.
        self.refined_at: list[float] = []
        #: When (s, `clock`) the rest matrix was first shown after motion (with `interim`).
        self.interim_at: list[float] = []
        self._refined_since_motion = False
        #: Moving frames cast straight through the renderer, past the cache (count).
        self.moving_casts = 0
        #: Moving frames cast at a new pose, per matrix (pixels -> count): what the controller chose.
        self.moving_frames: Counter[int] = Counter()
        #: The full matrix's cast beside the live frames, the last one begun (None before any).
        self.refine: Refine | None = None
        #: When (s, `clock`) each cast of upcoming phases beside the live frames for a held view began (`_prefetch`).
        self.prefetched_at: list[float] = []
        #: (when, how long) (s, `clock`) of the frames at a held view's matrix (the full one or the
        #: rest matrix, the pose unchanged) that cast a phase within themselves: the frames a
        #: breathing patient at rest holds longer than the detector alone would.
        self.held_casts: list[tuple[float, float]] = []
        #: Why a cast beside the live frames failed (None while none has): the full matrix is then
        #: cast within the frame again, where the fault reaches the caller.
        self.refine_fault: str | None = None

    def __getattr__(self, name):
        # Everything but rendering (prepare, device, fluoroscope, photons_per_pixel, ...) is the
        # full-matrix renderer's; only called for names this object does not have.
        return getattr(self.__dict__["full"], name)

    @property
    def moving(self) -> Renderer | None:
        """The renderer of the moving matrix now (None without one)."""
        n = self.control.matrix
        return None if n is None else self._movers[n]

    @property
    def matrix(self) -> int:
        """Columns of the matrix the last frame was cast at."""
        return self._last_used.shape[1]

    def cache(self, renderer: Renderer | None = None) -> ProjectionCache:
        return self._caches[id(renderer or self.full)]

    def set_fluoroscope(self, fluoroscope) -> None:
        self.full.set_fluoroscope(fluoroscope)
        self._edge_fixes.clear()                # the field's edge may be another
        for other in self._others():
            rows, cols = other.shape
            other.set_fluoroscope(at_resolution(fluoroscope, cols, rows))

    def warm(self, volume: PreparedVolume, T_xray_from_ct: np.ndarray) -> None:
        """Build every matrix's kernels and ray tables (a plain and a blended frame each, and the
        casts in bands beside the live frames), so the first live frames cost what later ones do.
        PoCL compiles a kernel again for each work-group size on its first run at that size (a
        second or more on an empty cache), so each build runs here at each size it will run at."""
        circle = self.full._circle(None)
        for r in (self.full, *self._others()):
            r.render(volume, T_xray_from_ct, View())
            r.render(volume, T_xray_from_ct, View(), blend=(volume, 0.5))
            self.cache(r).render(volume, T_xray_from_ct, View(), blend=(volume, 0.5))
            if r.caster.packet:
                # The two-phase pass on the phase itself, which the cache's `through` may not
                # have taken at this pose (a moving frame's where no slab is allowed).
                self.cache(r).cast_two(Through(volume), Through(volume), T_xray_from_ct, 1, None, True, circle)
            self.cache(r).clear()
        thin = None
        if self.slabs is not None:
            # The slab kernel (a quarter second on PoCL), and the packet kernel's builds for slabs
            # packet by packet (slabs.slab_through), which a frame a few degrees off the volume's
            # axis first needs in the middle of a session: every packet through the slab copy.
            slab = self.slabs.get(volume, dominant_axis(volume, T_xray_from_ct))
            if self.slabs.thicker is not None:
                self.slabs.thicker.get(volume, slab.slab_axis)
            thin = (slab, every_packet_rule(slab.slab_axis))
            for r in (self.full, *self._others()):
                if r.caster.packet:
                    r.caster.cast(volume, T_xray_from_ct, 1, None, None, True, circle, thin=(thin[0], None, thin[1]))
                    r.caster.cast(volume, T_xray_from_ct, 1, None, (volume, 0.5), True, circle,
                                  thin=(thin[0], thin[0], thin[1]))
                    self.cache(r).cast_two(Through(volume, thin), Through(volume, thin), T_xray_from_ct, 1, None,
                                           True, circle)
        for target in self._refined():
            bands = self._bands(target)
            if bands is None:
                break
            cache = self.cache(target)
            cache.fill([volume], T_xray_from_ct, 1, None, True, circle, bands, lambda: False)
            cache.clear()
            if target.caster.packet:
                # A breathing patient's rest casts its two phases in one pass (ProjectionCache.fill).
                ways = [Through(volume)] + ([] if thin is None else [Through(volume, thin)])
                for way in ways:
                    cache.cast_two(way, way, T_xray_from_ct, 1, None, True, circle, bands=(target._lock, bands))
            if thin is not None and target.caster.packet:
                target.caster.cast(volume, T_xray_from_ct, 1, None, None, True, circle, bands=(target._lock, bands),
                                   thin=(thin[0], None, thin[1]))
        self.full.dev.queue.finish()
        if self.slabs is not None:
            self.slabs.clear()

    def _refined(self) -> tuple[Renderer, ...]:
        """The matrices a resting view is cast into beside the live frames, in order."""
        return (self.full,) if self.interim is None else (self.interim, self.full)

    def _bands(self, target: Renderer) -> int | None:
        """The bands of rows `target` is cast in beside the live frames (rendering.refine_bands for
        the full matrix, as many of its cost for a smaller one); None: it is not."""
        bands = self.settings.refine_bands
        if bands is None or target is self.full:
            return bands
        return max(1, round(bands * (target.shape[0] / self.full.shape[0]) ** 2))

    def _through(self, renderer: Renderer, limit: float | None, noted: bool = False):
        """A projection cache's `through` for `renderer`'s matrix: its slab copies where the
        field's steepest ray shifts within a slab by less than `limit` of that matrix's pixels,
        else the phase itself (slabs.slab_through); None without the setting or the slab cache.
        A held view's matrices take `rendering.rest_slab_max_shift_px` (half the samples, the
        shift inside the detector's point-spread; the profile's comment gives the figures), the
        moving ones the moving frames' `rendering.slab_max_shift_px`, so what they cast at rest
        is cast as the moving frames were; with `noted` (the moving ones, on the render thread
        alone) whether the cast went through slabs is kept for `slab_casts`."""
        slabs = self.slabs
        if limit is None or slabs is None:
            return None

        def through(phase: PreparedVolume, T: np.ndarray, zoom: int) -> Through:
            way = slab_through(renderer.caster, slabs, phase, T, zoom, limit)
            if noted:
                self._slabbed = way.volume is not phase or way.thin is not None
            return way
        return through

    def _others(self) -> list[Renderer]:
        """The renderers of the other matrices: the moving ones and the rest matrix."""
        return [*self._movers.values(), *(() if self.interim is None else (self.interim,))]

    def _moved(self, volume: PreparedVolume, T: np.ndarray, zoom: int) -> bool:
        return not pose_unchanged(self.full.fluoroscope, volume, zoom, self._last_pose, T,
                                  self.settings.cache_pose_tolerance_px)

    def render(self, volume: PreparedVolume, T_xray_from_ct: np.ndarray, view: View,
               blend: tuple[PreparedVolume, float] | None = None,
               concentration_factor: float | None = None, measured: np.ndarray | None = None,
               upcoming: tuple[PreparedVolume, ...] = ()) -> Frame:
        """The full-matrix frame of `Renderer.render` (line integrals always at the full matrix).
        `measured`: the tracked pose before its smoothing filter (T_xray_from_ct), whose stop
        `rendering.rest_hold_px` may judge sooner than the filtered pose's (`_rested`); None:
        the pose given is the measured one. `upcoming`: phases the patient will need soon (the
        timeline's look ahead), which a view held at the full matrix casts beside the live
        frames (`_prefetch`)."""
        import cv2

        now = self.clock()
        T = np.asarray(T_xray_from_ct, dtype=np.float64)
        T, released = self._hold(volume, T, view)
        moved = self._note_motion(volume, T, view, now)
        resting = self._rested(volume, T, view, now, released, measured)
        if resting and self._held is not None and self._held is not T:
            # Rest was judged on the measured pose: the view is held there from this frame on.
            T = self._held
            moved = self._note_motion(volume, T, view, now) or moved
        moving = self.moving
        if not moved and self._last_used is not self.full:
            # The controller picks the matrix of a moving cast. A pose that stays keeps the matrix
            # it was last cast at, whose cache holds it, and the grain it was shown with.
            moving = self._last_used
        use = self.full if resting or moving is None or view.quantity == "line-integral" else moving
        if use is self.full and moving is not None and view.quantity != "line-integral":
            use = self._refining(volume, T, view, blend, moving) or use
            if use is self.full:
                self._prefetch(T, view, upcoming)
        # Only a frame cast at a new pose tells what a moving frame costs; one the cache served
        # while the pose settles would make the matrix look cheaper than it is.
        self._timed = use.shape[1] if use is not self.full and use is not self.interim and moved else None
        if self._timed is not None:
            self.moving_frames[self._timed] += 1
        if use is not self._last_used:
            # The recursive filter goes on across the switch: its state, resampled to the new
            # matrix, is what the first frame of that matrix is blended into.
            use.lag.carry_over(self._last_used.lag, use.shape)
        if use is moving and moved and use.caster.packet:
            # A new pose: the moving matrix's cache casts the frame's phases, two in one pass of
            # the packet kernel that keeps each phase's integrals (ProjectionCache.cast_two; as
            # fast as the pass that blends them, within this machine's noise), and the detector
            # blends them as it reads. Should the pose come to rest here, the frames that show
            # the moving matrix while the full one is cast beside them find both phases kept:
            # a breathing patient's first resting frame would otherwise cast both again within
            # the frame (60-190 ms on two cores for the adult chest at 256), on the device the
            # full matrix's bands wait for.
            self._slabbed = False
            frame = self.cache(use).render(volume, T, view, blend, concentration_factor)
            self.slab_casts += self._slabbed
            self.moving_casts += 1
        elif use is moving and moved and (blend is None or volume.same_grid(blend[0])):
            # The per-ray kernel (a GPU's) casts two phases in one pass only blended: the two
            # phases are blended in the cast (as Renderer.render does) rather than each cast into
            # the cache, and one phase alone is kept in it (_kept).
            cast = None
            if self.slabs is not None and self.settings.slab_max_shift_px is not None:
                cast = slab_cast(use.caster, self.slabs, volume, T, view.zoom, blend, self.settings.slab_max_shift_px)
                self.slab_casts += cast is not None
            if blend is None:
                cast = self._kept(use, cast)
            frame = use.render(volume, T, view, blend, cast=cast, concentration_factor=concentration_factor)
            self.moving_casts += 1
        else:
            cache = self.cache(use)
            casts = cache.counts.casts
            frame = cache.render(volume, T, view, blend, concentration_factor)
            if cache.counts.casts > casts and not moved and (use is self.full or use is self.interim):
                self.held_casts.append((now, self.clock() - now))
        image = frame.image
        rows, cols = self.full.shape
        if image.shape != (rows, cols):
            image = cv2.resize(image, (cols, rows), interpolation=cv2.INTER_LINEAR)
            if view.quantity == "display":
                image = cv2.multiply(image, self._edge_fix(use, view))
        if use is self.full and self._last_used is not self.full:
            if not self._refined_since_motion:
                ready = self.clock()
                self.refined_after_s.append(ready - self._last_motion)
                self.refined_at.append(ready)
                self._refined_since_motion = True
            if self.settings.crossfade_s > 0 and self._last_image is not None:
                self._fade_from, self._fade_t0 = self._last_image, now
        elif use is not self.full:
            self._fade_from = None
            if use is self.interim and self._last_used is not self.interim and not self._refined_since_motion:
                self.interim_at.append(self.clock())
        if self._fade_from is not None:
            a = (now - self._fade_t0) / self.settings.crossfade_s
            if a >= 1.0 or self._fade_from.shape != image.shape:
                self._fade_from = None
            else:
                image = ((1.0 - a) * self._fade_from + a * image).astype(np.float32)
        self._last_used = use
        self._last_image = image
        return frame if image is frame.image else dataclasses.replace(frame, image=image)

    def _note_motion(self, volume: PreparedVolume, T: np.ndarray, view: View, now: float) -> bool:
        """Whether `T` moved from the last frame's pose (beyond the cache's tolerance); a move
        starts the rest anew and stops a cast beside the live frames for a pose left behind."""
        moved = self._moved(volume, T, view.zoom)
        if moved:
            self._last_motion = now
            self._refined_since_motion = False
            self._last_pose = T
            # A cast beside the live frames for a pose left behind stops at its next band; the
            # tracker's jitter about the resting pose (within the tolerance of it) does not stop it.
            if self.refine is not None and not self._fits(self.refine, volume, T, view):
                self.refine.cancel = True
        return moved

    def _hold(self, volume: PreparedVolume, T: np.ndarray, view: View) -> tuple[np.ndarray, bool]:
        """(the pose to render, whether a held view was let go at this frame). A rested view is
        held at the pose it came to rest at while the tracked pose stays within
        `rendering.rest_hold_px` of it: after a stop the pose filter's output still creeps
        toward the phantom's pose for a second or so, and the tracker jitters about it, by more
        than the projection cache's tolerance but less than a pixel. Each such step would be
        motion, and the sharp view would drop to the moving matrix and be cast again; a real
        C-arm at rest shows a still image. A move beyond the hold lets go of it, and the rest
        is judged anew from that frame (`_rested`)."""
        hold = self.settings.rest_hold_px
        if self._held is None or hold is None or view.quantity == "line-integral":
            return T, False
        if pose_unchanged(self.full.fluoroscope, volume, view.zoom, self._held, T, hold):
            return self._held, False
        self._held = None
        return T, True

    def _rested(self, volume: PreparedVolume, T: np.ndarray, view: View, now: float, released: bool,
                measured: np.ndarray | None = None) -> bool:
        """Whether the pose has rested `rendering.settle_s`: no move beyond the cache's tolerance
        for that long; with `rendering.rest_hold_px`, none beyond the hold. The filter's creep
        after a stop, steps of a few tenths of a pixel for a tenth of a second or two, then
        counts as rest, as the hold will count it: the full matrix is begun that much sooner,
        at a pose within the hold of where the view comes to rest, and the view is held there.

        With the hold and the `measured` pose (before the filter) as well, rest comes as soon
        as the measured pose has stayed within the hold that long and the filtered one is within
        the hold of it: the filter's creep after a stop (a first-order lag, a pixel or two for a
        tenth of a second and more) then costs no wait, and the view is held at the measured
        pose, where the creep ends. A camera whose measured pose jitters by more than the hold
        at rest leaves this to the filtered pose's rule."""
        hold = self.settings.rest_hold_px
        if hold is None or view.quantity == "line-integral":
            return now - self._last_motion >= self.settings.settle_s
        if self._held is not None:
            return True
        fluoroscope, zoom = self.full.fluoroscope, view.zoom
        if released or not pose_unchanged(fluoroscope, volume, zoom, self._still_pose, T, hold):
            self._still_pose, self._still_since = T, now
        if measured is not None:
            measured = np.asarray(measured, dtype=np.float64)
            if released or not pose_unchanged(fluoroscope, volume, zoom, self._measured_pose, measured, hold):
                self._measured_pose, self._measured_since = measured, now
        if now - self._still_since >= self.settings.settle_s:
            self._held = T              # the pose the view rests at, held from here (`_hold`)
            return True
        if (measured is not None and now - self._measured_since >= self.settings.settle_s
                and pose_unchanged(fluoroscope, volume, zoom, measured, T, hold)):
            self._held = measured
            return True
        return False

    def _kept(self, use: Renderer, cast: Callable | None) -> Callable:
        """A stand-in for `use`'s cast (`cast`, or the caster's own) that keeps the one phase's
        integrals in `use`'s projection cache: should the pose come to rest here, the frames that
        show the moving matrix while it settles and while the full one is cast beside them
        reuse them instead of casting the same pose again, on the device the full matrix's
        bands are waiting for."""
        cache, cast = self.cache(use), cast or use.caster.cast

        def keeping(volume, T, zoom, collimation_mm, blend, distorted, circle):
            lines, mask = cast(volume, T, zoom, collimation_mm, blend, distorted, circle)
            cache.keep({volume: lines}, T, zoom, collimation_mm, distorted, circle)
            return lines, mask
        return keeping

    def _refining(self, volume: PreparedVolume, T: np.ndarray, view: View,
                  blend: tuple[PreparedVolume, float] | None, moving: Renderer) -> Renderer | None:
        """What this resting frame shows while its matrices are cast beside the live frames: the
        largest of the rest matrix (`interim`) and `moving` whose cache holds this pose, or None
        once the full matrix holds it (then the full matrix). The first of them that does not is
        cast on a thread of its own (begun here; one at a time). None without
        `rendering.refine_bands` or after a fault of that cast."""
        bands = self.settings.refine_bands
        if bands is None or self.refine_fault is not None:
            return None
        refine = self.refine
        running = refine is not None and not refine.done.is_set()
        if refine is not None and running and not self._fits(refine, volume, T, view):
            # It ends at its next band (a later frame begins this pose's), and keeps nothing of
            # the pose left behind in place of what the caches hold of this one.
            refine.cancel = True
        circle = self.full._circle(None)
        phases = [volume] if blend is None or blend[1] == 0.0 else [volume, blend[0]]
        shown, missing = moving, None
        for target in self._refined():
            if not self._holds(target, phases, T, view, circle):
                missing = target
                break
            shown = target
        if missing is None:
            return None
        if running:
            return shown
        bands = self._bands(missing)
        refine = self.refine = Refine(T, _geometry(view), missing)
        threading.Thread(target=self._cast_full, args=(refine, phases, view, circle, bands),
                         name="fluorosim-refine", daemon=True).start()
        return shown

    def _prefetch(self, T: np.ndarray, view: View, upcoming: tuple[PreparedVolume, ...]) -> None:
        """A view held at the full matrix: the `upcoming` phases its cache does not hold are cast
        beside the live frames (one cast at a time, as the refine's), so breathing that brings
        them finds them cast. Without this each new phase of a breathing patient is cast within
        the frame that first needs it: at the adult chest's 512 matrix on two cores, a frame of
        60 ms instead of 6 every time the breath reaches another of its states. A phase needed
        before its cast is done is cast within its frame as before."""
        if not upcoming or self.settings.refine_bands is None or self.refine_fault is not None:
            return
        refine = self.refine
        if refine is not None and not refine.done.is_set():
            return
        cache, circle = self.cache(self.full), self.full._circle(None)
        missing = [p for p in upcoming if not cache.holds([p])]
        if not missing or not cache.adopted(T, view.zoom, view.collimation_mm, True, circle):
            return
        self.prefetched_at.append(self.clock())
        refine = self.refine = Refine(T, _geometry(view), self.full)
        threading.Thread(target=self._cast_full, args=(refine, missing, view, circle, self.settings.refine_bands),
                         name="fluorosim-prefetch", daemon=True).start()

    def _holds(self, target: Renderer, phases: list[PreparedVolume], T: np.ndarray, view: View, circle) -> bool:
        """Whether `target`'s cache holds this pose and field. The full matrix after a rest matrix
        must hold the frame's phases too: a phase new to the held view is cast beside the live
        frames, the rest matrix showing it meanwhile; otherwise (the rest matrix, or the full one
        without one) a new phase is cast within the frame, so the view keeps its matrix."""
        cache = self.cache(target)
        if not cache.adopted(T, view.zoom, view.collimation_mm, True, circle):
            return False
        return target is not self.full or self.interim is None or cache.holds(phases)

    def _fits(self, refine: Refine, volume: PreparedVolume, T: np.ndarray, view: View) -> bool:
        """Whether `refine` is this frame's full matrix: the same field, the pose within the tolerance."""
        return refine.geometry == _geometry(view) and pose_unchanged(
            self.full.fluoroscope, volume, view.zoom, refine.T_xray_from_ct, T, self.settings.cache_pose_tolerance_px)

    def _cast_full(self, refine: Refine, phases: list[PreparedVolume], view: View, circle: bool, bands: int) -> None:
        """The refine thread: the phases into the target matrix's cache, band by band."""
        try:
            self.cache(refine.target).fill(phases, refine.T_xray_from_ct, view.zoom, view.collimation_mm, True,
                                           circle, bands, lambda: refine.cancel)
        except CastCancelled:
            pass
        except Exception as e:  # noqa: BLE001 - reported by the frame that casts it inline next
            log.error("the full matrix's cast beside the live frames failed (%s); casting it within the frame", e)
            self.refine_fault = f"{type(e).__name__}: {e}"
        finally:
            refine.done.set()

    def wait_refined(self, timeout_s: float) -> bool:
        """Wait up to `timeout_s` (s) for a cast beside the live frames to end; True when none is left."""
        refine = self.refine
        return refine is None or refine.done.wait(timeout_s)

    def _edge_fix(self, use: Renderer, view: View) -> np.ndarray:
        """The factor that gives a scaled-up display frame the full matrix's field edge: the
        coarse frame's own edge, scaled up, steps in whole coarse pixels (a jagged circle at
        128 of 512), so it is divided out and the full matrix's smooth edge put in its place.
        Where the coarse edge has faded to under EDGE_FLOOR there is no image to restore and
        the factor is 0. Made once per matrix and field."""
        import cv2

        key = (use.shape, view.zoom, None if view.collimation_mm is None else tuple(view.collimation_mm))
        fix = self._edge_fixes.get(key)
        if fix is None:
            rows, cols = self.full.shape
            coarse = cv2.resize(use.display_edge(view), (cols, rows), interpolation=cv2.INTER_LINEAR)
            fine = self.full.display_edge(view)
            fix = np.where(coarse >= EDGE_FLOOR, fine / np.maximum(coarse, EDGE_FLOOR), 0.0).astype(np.float32)
            if len(self._edge_fixes) > 64:
                self._edge_fixes.clear()
            self._edge_fixes[key] = fix
        return fix

    def frame_shown(self, seconds: float) -> None:
        """The last frame took `seconds` (s) from the start of its render to the screen: a moving
        cast's time picks the next moving matrix; other frames are not counted."""
        if self._timed is not None:
            self.control.observe(self._timed, seconds)
            self._timed = None
