"""The render worker: the path of one frame, from the newest pose to the screen.

    poses ─┐
    phases ┼─> T_xray_from_ct -> Renderer.render -> Compositor.compose -> Display.show
    console┘        (only when the console says an image is due; else the last image is held)

`T_xray_from_ct = T_xray_from_webcam @ T_webcam_from_phantom @ T_phantom_from_ct`. The
console decides whether an image is due, the collimation and the display settings; the
renderer makes the image; the compositor lays the overlays over it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from ..config import ApplianceConfig
from ..config.fluoroscope import FluoroscopeProfile
from ..console.state import ConsoleState
from ..display.compositor import Overlay
from ..errors import FluorosimError
from ..teaching.live import TeachingStatus
from ..teaching.views import view_detail
from ..xray.renderer import Frame, View
from .frame_stats import FrameStats
from .handoff import LatestValue, PhaseValue, SavedImage, ShownFrame, ShownImage, Technique, TrackedPose
from .health import banners_for_frame
from .native_save import LIVE_GAP_S, native_frame
from .parts import Parts, is_cpu
from .pose_demand import PoseDemand
from .reload import ProfileKeeper
from .stage_times import FrameStamps, StageTimes
from .worker import Worker

log = logging.getLogger(__name__)

#: How long the saved-image flash stays on screen (s, wall clock).
SAVED_FLASH_S = 1.0
#: The first frames build kernels and tables: seconds on a CPU device, not a hang. Until this
#: many frames are on screen a render may take up to WARM_UP_GRACE_S (s).
WARM_UP_FRAMES = 3
WARM_UP_GRACE_S = 60.0
#: How long the worker waits for the console's first state before looking again (s).
CONSOLE_WAIT_S = 0.1
#: Longest wait for a new pose while holding the last image (s): short, so overlays stay current.
POSE_WAIT_S = 0.02
#: Renderer faults are kept to this many characters for the screen's banner.
FAULT_CHARS = 120


def view_for(cfg: ApplianceConfig, state: ConsoleState) -> View:
    """What the renderer is asked for: the console's zoom, collimation and inversion."""
    # Live frames run through the recursive filter, so moving the C-arm leaves its trail.
    return View(zoom=state.zoom, collimation_mm=state.collimated_mm, invert=state.invert,
                noise=cfg.fluoroscope.display.noise, temporal="live", mode=state.mode,
                window_scale=state.window_scale, level_shift=state.level_shift)


def breathes(case) -> bool:
    """Whether the case's patient breathes: under the breathing model, as the built-in child, or
    as a 4D CT's phases. A breath hold on a static CT holds nothing, and the monitor must not say so."""
    return case.respiration is not None or case.builtin is not None or len(case.phases or ()) > 1


def overlay_for(cfg: ApplianceConfig, state: ConsoleState, *, live: bool, saved_flash: bool, warnings: list[str],
                fps: float | None, teaching: TeachingStatus | None = None, breathing: str = "") -> Overlay:
    """What the compositor draws over the image: the console's readings, the session's names and,
    with an exercise or the shot counter, the teaching lines."""
    shots = teaching.exposures if teaching is not None and cfg.appliance.teaching.shot_counter else None
    return Overlay(shots=shots, task=teaching.task if teaching is not None else "",
                   cue=teaching.cue if teaching is not None else "",
                   live=live, zoom=state.zoom, fov_mm=state.fov_mm, collimation_mm=state.collimated_mm,
                   fluoro_time_s=state.fluoro_time_s, air_kerma_mgy=state.air_kerma_mgy,
                   air_kerma_rate_mgy_per_min=state.air_kerma_rate_mgy_per_min,
                   dap_gy_cm2=state.dap_gy_cm2, mode=state.mode, alarm=state.alarm_sounding,
                   technique=(state.kvp, state.ma) if state.fluoro_on else None,
                   saved_flash=saved_flash, invert=state.invert, breath_hold=state.breath_hold and breathes(cfg.case),
                   case=cfg.case.title, operator=(teaching.trainee if teaching is not None and teaching.trainee
                                                  else cfg.appliance.operator), fluoroscope=cfg.fluoroscope.name,
                   warnings=list(warnings), fps=fps, breathing=breathing)


class RenderWorker(Worker):
    """Newest pose + phase + console state -> image -> overlays -> display, once per pose.

    Holds the last image (last-image-hold) and redraws it at `daemon.hold_refresh_hz` so the
    overlays stay current while fluoroscopy is off. Publishes each live image to `shown`
    (what a save writes, with its pose) and the tube output the brightness control chose to `exposure_factor`.
    """

    def __init__(self, parts: Parts, keeper: ProfileKeeper, *, poses: LatestValue[TrackedPose],
                 phases: LatestValue[PhaseValue], console_state: LatestValue[ConsoleState],
                 saves: LatestValue[SavedImage], shown: LatestValue[ShownImage], exposure_factor: LatestValue[Technique],
                 banners: Callable[[], list[str]], on_first_frame: Callable[[], None],
                 on_shown: Callable[[ShownFrame], None] | None = None,
                 views: LatestValue[tuple[float, dict]] | None = None,
                 teaching: LatestValue[TeachingStatus] | None = None, demand: PoseDemand | None = None):
        super().__init__("render", idle_s=0.0)
        self.demand = demand        # told when each render begins and ends (pose_demand.py)
        self.parts, self.keeper = parts, keeper
        self.poses, self.phases, self.console_state, self.saves = poses, phases, console_state, saves
        self.shown, self.exposure_factor = shown, exposure_factor
        self.banners, self.on_first_frame, self.on_shown = banners, on_first_frame, on_shown
        # Teaching: the geometry of each live image goes to the input worker (its records), the
        # shot counter and task line come back.
        self.views, self.teaching = views, teaching
        self.stats = FrameStats()
        self.stages = StageTimes()      # where each live frame's latency went (stage_times.py)
        #: Why rendering left the profile's OpenCL device (None while it has not), for the health check.
        self.fault: str | None = None
        self._last_pose_seq = 0
        self._image: np.ndarray | None = None          # the image on screen (last-image-hold)
        self._image_T: np.ndarray | None = None        # the pose it was rendered at (T_xray_from_ct)
        self._drawn: ConsoleState | None = None        # the console state it was rendered at
        self._last_compose = 0.0
        self._alarm_since: float | None = None       # when the alarm's banner began (time.monotonic s)
        self._factor_sent = Technique(1.0)
        self._request: tuple | None = None        # what the last live frame was rendered from
        self._screen: np.ndarray | None = None    # the screen the compositor draws into, reused

    def step(self) -> bool:
        state, _ = self.console_state.get()
        if state is None:
            self.console_state.wait_newer(0, CONSOLE_WAIT_S)
            return False
        # Each pose is looked at once: drawn if an image is due, else skipped for the next one.
        got_pose = self.poses.newer(self._last_pose_seq)
        tracked = None
        if got_pose is not None:
            tracked, self._last_pose_seq = got_pose
        phase, _ = self.phases.get()
        cfg = self.keeper.current
        now = time.monotonic()
        live = False
        t_rendered = now
        if (tracked is not None and tracked.pose.ok and phase is not None
                and phase.generation == self.parts.generation and state.image_due(self._drawn)):
            T_xray_from_webcam = cfg.fluoroscope.T_xray_from_webcam()
            T_phantom_from_ct = np.asarray(cfg.case.T_phantom_from_ct, dtype=np.float64)
            T_xray_from_ct = T_xray_from_webcam @ tracked.pose.T_webcam_from_phantom @ T_phantom_from_ct
            # Where the filtered pose is headed: the renderer may judge a stop on it (progressive.py).
            measured = (None if tracked.pose.T_measured is None
                        else T_xray_from_webcam @ tracked.pose.T_measured @ T_phantom_from_ct)
            # The renderer wants no pose until this frame is on screen (pose_demand.py).
            if self.demand is not None:
                self.demand.rendering(now)
            frame = None
            try:
                frame = self._render(cfg, T_xray_from_ct, phase, state, measured)
                t_rendered = time.monotonic()
            finally:
                if frame is None and self.demand is not None:
                    self.demand.rendered(now, time.monotonic())
            if frame is not None:
                self._image, self._image_T, self._drawn, live = frame.image, T_xray_from_ct, state, True
                self._send_technique(Technique(frame.exposure_factor, frame.kvp, frame.ma))
                if self.views is not None:
                    self.views.put((state.t, view_detail(self.parts.renderer.fluoroscope, T_xray_from_ct, state.zoom,
                                                         state.collimated_mm, phase.t_case_s)))
        hold_period = 1.0 / cfg.appliance.daemon.hold_refresh_hz
        if not live and now - self._last_compose < hold_period:
            # Nothing new to draw: wait for the next pose rather than spin.
            self.poses.wait_newer(self._last_pose_seq, min(hold_period, POSE_WAIT_S))
            return False
        banners = banners_for_frame(self.banners(), live)
        saved, _ = self.saves.get()
        saved_flash = saved is not None and now < saved.t_saved + SAVED_FLASH_S
        teaching = self.teaching.get()[0] if self.teaching is not None else None
        overlay = overlay_for(cfg, state, live=live, saved_flash=saved_flash, warnings=banners,
                              fps=self.stats.fps(now), teaching=teaching,
                              breathing=phase.breathing if phase is not None else "")
        if state.alarm_sounding and self._alarm_since is None:
            self._alarm_since = now
        elif not state.alarm_sounding:
            self._alarm_since = None
        overlay.alarm_since = self._alarm_since
        t_compose = time.monotonic()
        compositor = self.parts.compositor
        if self._screen is None or self._screen.shape != (compositor.height, compositor.width, 3):
            self._screen = np.zeros((compositor.height, compositor.width, 3), np.uint8)
        # One screen buffer, drawn over every frame: the display copies it out in show().
        screen = compositor.compose(self._image, overlay, now, out=self._screen)
        t_composed = time.monotonic()
        self.parts.display.show(screen)
        t_shown = time.monotonic()
        self._last_compose = t_shown
        if live and self.demand is not None:
            self.demand.rendered(now, t_shown)
        if live:
            # The moving matrix is chosen from what a frame takes to the screen (matrix_control.py).
            self.parts.renderer.frame_shown(t_shown - now)
        latency = None
        if live and tracked is not None and self._image is not None and self._image_T is not None:
            latency = t_shown - tracked.t_frame
            self.stats.add(t_shown, latency, state.runs if state.pulse_rate_per_s is None else None)
            if tracked.t_picked is not None and tracked.t_tracked is not None:
                self.stages.add(FrameStamps(tracked.t_frame, tracked.t_picked, tracked.t_tracked, tracked.filter_s,
                                            now, t_rendered, t_compose, t_composed, t_shown))
            self.shown.put(ShownImage(self._image, self._image_T))
        self.on_first_frame()
        if self.on_shown is not None:
            self.on_shown(ShownFrame(self.parts.display.read_back, self._image, state, tracked if live else None,
                                     live, t_shown, latency, banners, saved_flash,
                                     phase.inspired if live and phase is not None else None,
                                     phase.t_case_s if live and phase is not None else None))
        return True

    def _render(self, cfg: ApplianceConfig, T_xray_from_ct: np.ndarray, phase: PhaseValue,
                state: ConsoleState, measured: np.ndarray | None = None) -> Frame | None:
        blend = (phase.prepared_b, phase.weight) if phase.prepared_b is not None else None
        view = view_for(cfg, state)
        self._request = (phase.prepared_a, T_xray_from_ct, view, blend)
        grace = WARM_UP_GRACE_S if self.stats.frames < WARM_UP_FRAMES else cfg.appliance.daemon.stall_timeout_s
        try:
            with self.grace(grace):
                return self.parts.renderer.render(phase.prepared_a, T_xray_from_ct, view, blend=blend,
                                                  measured=measured, upcoming=phase.upcoming)
        except FluorosimError:
            raise
        except Exception as e:  # noqa: BLE001 - an OpenCL fault must not end the appliance
            if is_cpu(self.parts.renderer):
                raise
            log.error("renderer failed on %s (%s); falling back to the CPU device", self.parts.renderer_device, e)
            self.parts.fall_back_to_cpu(cfg)
            # Reported once it is true: the banner says rendering is on the CPU.
            self.fault = f"{type(e).__name__}: {e}"[:FAULT_CHARS]
            return None

    def native_image(self, cancelled: Callable[[], bool] | None = None) -> tuple[np.ndarray, FluoroscopeProfile] | None:
        """The last live view again at the detector's native matrix, the C-arm still (the
        recursive filter settled): a saved image as the unit stores it, 16-bit. With the
        profile read out at that matrix, for the saved image's pixel spacing. None before any
        live frame. On a CPU device a native frame takes a second or more: it is cast in bands
        of rows, paced to its share of the time while live frames come (native_save.py), so the
        live view keeps most of its rate; `cancelled()` is asked between bands and every slice
        of the pacing, and true ends it with CastCancelled (the records worker stopping)."""
        request = self._request
        if request is None:
            return None
        cfg = self.keeper.current
        shown = self.stats.shown_at

        def live() -> bool:
            return bool(shown) and time.monotonic() - shown[-1] < LIVE_GAP_S
        native, _ = native_frame(self.parts.renderer, request, cfg.fluoroscope, cfg.appliance.daemon,
                                 is_cpu(self.parts.renderer), cancelled, live)
        return native

    def _send_technique(self, technique: Technique) -> None:
        """The console doses at the technique the renderer's brightness control set (and records
        its kV and mA); tell it on change."""
        if technique != self._factor_sent:
            self._factor_sent = technique
            self.exposure_factor.put(technique)
