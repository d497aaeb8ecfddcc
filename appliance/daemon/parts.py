"""Open the appliance's parts from its profiles: camera, tracker, patient timeline, renderer,
console, input devices, compositor and display.

This is the one place that knows how each area's objects are built, so the workers in
`pipeline` only call the agreed interfaces. Devices that are absent at start (camera,
keypad, pedal) open in a "lost"/"unplugged" state and reattach by themselves; only a
display that cannot be opened, or profiles that cannot be used, stop the start.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.camera import CameraSource, SyntheticCamera
from drivers.framebuffer import Display
from drivers.input_event import InputDevice

from ..config import ApplianceConfig, resolve
from ..config.base import matrix
from ..config.fluoroscope import FluoroscopeProfile
from ..console.alarm_sound import AlarmSound
from ..console.inputs import open_badge_reader, open_inputs
from ..console.state import Console
from ..display.compositor import Compositor, Overlay
from ..display.target import open_target
from ..patient.timeline import PhaseTimeline, Timeline
from ..tracking.tracker import Tracker
from ..xray.device import is_cpu_device, pick_device
from ..xray.progressive import ProgressiveRenderer
from ..xray.renderer import Renderer, at_resolution

log = logging.getLogger(__name__)


def patient_phases(cfg: ApplianceConfig, progress: Callable[[str], None] | None = None) -> list[tuple[float, Any]]:
    """(time stamp s, loader) for each phase of the active case; builds the built-in patient once."""
    case = cfg.case
    if case.builtin is not None:
        from ..patient.builtin import builtin_phases
        return builtin_phases(case.builtin, cfg.data_dir / "cache", progress=progress)
    from ..patient.volume_io import load_volume
    return [(ph.time_s, (lambda p=resolve(cfg.case_path, ph.volume): load_volume(p))) for ph in case.phases or ()]


def rendered_fluoroscope(cfg: ApplianceConfig, fallback: bool = False, cpu: bool = False) -> FluoroscopeProfile:
    """The fluoroscope as rendered: read out at `daemon.render_matrix_px` when the profile sets it,
    and at no more than `daemon.cpu_fallback_matrix_px` once rendering fell back to the CPU
    (`fallback`) or where it renders on a CPU device (`cpu`) and the profile sets no matrix: the
    detector's own is a GPU's (1024 x 1024 renders under 2 frames/s on two CPU cores)."""
    d = cfg.appliance.daemon
    n = d.render_matrix_px or cfg.fluoroscope.detector.columns
    if fallback or (cpu and d.render_matrix_px is None):
        n = min(n, d.cpu_fallback_matrix_px)
    if n == cfg.fluoroscope.detector.columns == cfg.fluoroscope.detector.rows:
        return cfg.fluoroscope
    return at_resolution(cfg.fluoroscope, n, n)


def make_renderer(cfg: ApplianceConfig, device: str = "auto") -> ProgressiveRenderer:
    """The renderer behind its projection cache and progressive matrix (the `rendering` section),
    at the matrix `rendered_fluoroscope` gives for the OpenCL device `device` picks.
    A live renderer fits a new kV's energy nodes on a side thread: the exposure control moves
    the kV while the trainee images, and no frame may wait for a fit."""
    d = cfg.appliance.daemon
    on_cpu = is_cpu_device(pick_device(device))
    fluoroscope = rendered_fluoroscope(cfg, fallback=device == "cpu", cpu=on_cpu)
    if device == "auto" and on_cpu and d.render_matrix_px is None and fluoroscope is not cfg.fluoroscope:
        det = cfg.fluoroscope.detector
        log.warning("no GPU: rendering on the CPU at %d x %d (daemon.cpu_fallback_matrix_px), shown scaled up; "
                    "the detector's %d x %d needs a GPU and its OpenCL driver (README), or set "
                    "daemon.render_matrix_px for this computer", fluoroscope.detector.columns,
                    fluoroscope.detector.rows, det.columns, det.rows)
    renderer = Renderer(fluoroscope, cfg.case.materials, contrast=cfg.case.contrast, device=device)
    renderer.caster.fit_in_background = True
    return ProgressiveRenderer(renderer, cfg.appliance.rendering)


def device_label(renderer: Renderer | ProgressiveRenderer) -> str:
    d = renderer.device
    return f"{d.name.strip()} ({'CPU' if is_cpu(renderer) else 'GPU'})"


def is_cpu(renderer: Renderer | ProgressiveRenderer) -> bool:
    return is_cpu_device(renderer.device)


def open_camera(cfg: ApplianceConfig, clock: Callable[[], float]) -> CameraSource:
    from ..tracking.sources import open_camera as open_source
    return open_source(cfg, clock)


def open_tracker(cfg: ApplianceConfig) -> Tracker:
    from ..tracking.sources import tracker_for
    return tracker_for(cfg)


def open_timeline(cfg: ApplianceConfig, renderer: Renderer | ProgressiveRenderer) -> Timeline:
    """The active case's phases, loaded and prepared for `renderer` by the timeline's own thread."""
    if cfg.case.respiration is not None:
        from ..patient.breathing_timeline import breathing_timeline
        return breathing_timeline(cfg.case_path, cfg.case, renderer, cfg.data_dir / "cache")
    return PhaseTimeline(patient_phases(cfg), renderer, at_end=cfg.case.at_end)


@dataclass
class Parts:
    camera: CameraSource
    tracker: Tracker
    renderer: ProgressiveRenderer
    timeline: Timeline
    console: Console
    keypad: InputDevice
    pedal: InputDevice
    compositor: Compositor
    display: Display
    alarm: AlarmSound
    badge: InputDevice | None = None      # teaching's badge reader: its keys go to the trainee's name only
    #: The appliance clock's reading when the console started: the session's and the case's time 0 (s).
    t0: float = 0.0
    closed: bool = False
    #: Counts replacements of the renderer or the case: phases prepared under an older one are not drawn.
    generation: int = 0

    @property
    def renderer_device(self) -> str:
        return device_label(self.renderer)

    def fall_back_to_cpu(self, cfg: ApplianceConfig) -> None:
        """Replace a failed OpenCL device by PoCL's CPU device; phases are prepared again there."""
        self.renderer = make_renderer(cfg, device="cpu")
        self._replace_timeline(open_timeline(cfg, self.renderer))

    def switch_case(self, cfg: ApplianceConfig) -> None:
        """Take up the case of a reloaded profile set: its phases are prepared from now on."""
        self._replace_timeline(open_timeline(cfg, self.renderer))

    def _replace_timeline(self, timeline: Timeline) -> None:
        old = self.timeline
        self.timeline = timeline
        self.generation += 1
        old.close()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        badge = self.badge.close if self.badge is not None else (lambda: None)
        for name, close in (("camera", self.camera.stop), ("keypad", self.keypad.close), ("pedal", self.pedal.close),
                            ("badge reader", badge), ("alarm", self.alarm.stop), ("phase loader", self.timeline.close),
                            ("display", self.display.close)):
            try:
                close()
            except Exception as e:  # noqa: BLE001 - closing one part must not leave the others open
                log.warning("closing the %s: %s", name, e)


#: How long start-up waits for the first phase of the case to be loaded and prepared (s).
FIRST_PHASE_TIMEOUT_S = 300.0


def warm_up(cfg: ApplianceConfig, renderer: ProgressiveRenderer, timeline: Timeline) -> float:
    """Render two throw-away frames (plain and blended) so kernels and ray tables are built
    before the session starts; returns the seconds it took."""
    import time

    from ..tracking.trajectory import pose_from_angles

    t0 = time.monotonic()
    # On a clock running faster than the wall (the demo's), a phase window of an exercise lasts
    # a fraction of a second: every phase is prepared before the session starts, rather than
    # beside it, slowing the frames that have to land in those windows. A real appliance (x1)
    # starts on the first phase and prepares the rest as it runs.
    timeline.wait_ready(FIRST_PHASE_TIMEOUT_S, all_phases=cfg.appliance.daemon.clock_rate > 1)
    a, _, _ = timeline.at(0.0)
    # The box straight under the webcam: any pose that puts the patient in the beam will do.
    T = cfg.fluoroscope.T_xray_from_webcam() @ pose_from_angles([0.0, 0.0, 550.0]) @ matrix(cfg.case.T_phantom_from_ct)
    renderer.warm(a, T)
    return time.monotonic() - t0


def open_parts(cfg: ApplianceConfig, console_clock: Callable[[], float]) -> Parts:
    """Every part the workers need, opened from the active profiles.

    The display comes first and shows that the appliance is starting; the console and its
    inputs come last, after the renderer is warm, so a scripted session starts on time.
    """
    # Under the data_dir in force: `bench e2e --out` and the tests may override the profile's.
    display = open_target(cfg.path, cfg.appliance, data_dir=cfg.data_dir)
    compositor = Compositor(display.width, display.height,
                            circular_fov=cfg.fluoroscope.detector.kind == "image_intensifier")
    display.show(compositor.compose(None, Overlay(case=cfg.case.title, operator=cfg.appliance.operator,
                                                  fluoroscope=cfg.fluoroscope.name,
                                                  warnings=["starting: preparing the patient and the X-ray renderer"])))
    renderer = make_renderer(cfg)
    timeline = open_timeline(cfg, renderer)
    try:
        took = warm_up(cfg, renderer, timeline)
        log.info("renderer warm on %s in %.1f s", device_label(renderer), took)
        camera = open_camera(cfg, console_clock)
        now = console_clock()
        if isinstance(camera, SyntheticCamera):
            camera.t0 = now             # its path keeps time with the scripted console and the case
        keypad, pedal = open_inputs(cfg, now)
        return Parts(
            camera=camera,
            tracker=open_tracker(cfg),
            renderer=renderer,
            timeline=timeline,
            console=Console(cfg.fluoroscope, cfg.keymap, t0=now),
            keypad=keypad, pedal=pedal, badge=open_badge_reader(cfg, now),
            compositor=compositor,
            display=display,
            alarm=AlarmSound(),
            t0=now,
        )
    except BaseException:
        timeline.close()
        display.close()
        raise


__all__ = ["Parts", "device_label", "make_renderer", "open_parts", "open_timeline", "patient_phases",
           "rendered_fluoroscope"]
