"""Open the appliance's parts from its profiles: camera, tracker, patient timeline, renderer,
console, input devices, compositor and display.

This is the one place that knows how each area's objects are built, so the workers in
`pipeline` only call the agreed interfaces. Devices that are absent at start (camera,
keypad, pedal) open in a "lost"/"unplugged" state and reattach by themselves; only a
display that cannot be opened, or profiles that cannot be used, stop the start.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from drivers.framebuffer import open_display

from ..config import ApplianceConfig, resolve
from ..config.base import matrix
from ..console.alarm_sound import AlarmSound
from ..console.inputs import open_inputs
from ..console.state import Console
from ..display.compositor import Compositor, Overlay
from ..errors import FluorosimError
from ..patient.timeline import PhaseTimeline
from ..xray.renderer import Renderer, View, at_resolution

log = logging.getLogger(__name__)


def data_path(cfg: ApplianceConfig, written: str) -> Path:
    """A path written in the appliance profile's devices section, relative to data_dir."""
    p = Path(written).expanduser()
    return p if p.is_absolute() else cfg.data_dir / p


def patient_phases(cfg: ApplianceConfig, progress: Callable[[str], None] | None = None) -> list[tuple[float, Any]]:
    """(time stamp s, loader) for each phase of the active case; builds the built-in patient once."""
    case = cfg.case
    if case.builtin is not None:
        from ..patient.builtin import builtin_phases
        return builtin_phases(case.builtin, cfg.data_dir / "cache", progress=progress)
    from ..patient.volume_io import load_volume
    return [(ph.time_s, (lambda p=resolve(cfg.case_path, ph.volume): load_volume(p))) for ph in case.phases]


def rendered_fluoroscope(cfg: ApplianceConfig, fallback: bool = False):
    """The fluoroscope as rendered: read out at `daemon.render_matrix_px` when the profile sets it,
    and at no more than `daemon.cpu_fallback_matrix_px` once rendering fell back to the CPU."""
    d = cfg.appliance.daemon
    n = d.render_matrix_px or cfg.fluoroscope.detector.columns
    if fallback:
        n = min(n, d.cpu_fallback_matrix_px)
    if n == cfg.fluoroscope.detector.columns == cfg.fluoroscope.detector.rows:
        return cfg.fluoroscope
    return at_resolution(cfg.fluoroscope, n, n)


def make_renderer(cfg: ApplianceConfig, device: str = "auto") -> Renderer:
    return Renderer(rendered_fluoroscope(cfg, fallback=device == "cpu"), cfg.case.materials,
                    contrast=cfg.case.contrast, device=device)


def device_label(renderer: Renderer) -> str:
    d = renderer.device
    return f"{d.name.strip()} ({'CPU' if is_cpu(renderer) else 'GPU'})"


def is_cpu(renderer: Renderer) -> bool:
    import pyopencl as cl
    return bool(renderer.device.type & cl.device_type.CPU)


def open_camera(cfg: ApplianceConfig):
    from ..tracking.sources import open_camera as open_source
    return open_source(cfg)


def open_tracker(cfg: ApplianceConfig):
    from ..tracking.sources import tracker_for
    return tracker_for(cfg)


def make_view(cfg: ApplianceConfig, state) -> View:
    fov = state.fov_mm
    c = state.collimation_mm
    collimation = None if c is None or (c[0] >= fov and c[1] >= fov) else tuple(c)
    # Live frames run through the recursive filter, so moving the C-arm leaves its trail.
    return View(zoom=state.zoom, collimation_mm=collimation, invert=state.invert, noise=cfg.fluoroscope.display.noise,
                temporal="live", mode=state.mode)


def make_overlay(cfg: ApplianceConfig, state, *, live: bool, saved_flash: bool, warnings: list[str],
                 fps: float | None) -> Overlay:
    fov = state.fov_mm
    c = state.collimation_mm
    return Overlay(live=live, zoom=state.zoom, fov_mm=fov,
                   collimation_mm=None if c is None or (c[0] >= fov and c[1] >= fov) else tuple(c),
                   fluoro_time_s=state.fluoro_time_s, air_kerma_mgy=state.air_kerma_mgy,
                   air_kerma_rate_mgy_per_min=state.air_kerma_rate_mgy_per_min,
                   dap_gy_cm2=state.dap_gy_cm2, mode=state.mode, alarm=state.alarm_sounding,
                   saved_flash=saved_flash, invert=state.invert, breath_hold=state.breath_hold,
                   case=cfg.case.title, operator=cfg.appliance.operator, fluoroscope=cfg.fluoroscope.name,
                   warnings=list(warnings), fps=fps)


@dataclass
class Parts:
    camera: Any
    tracker: Any
    renderer: Renderer
    timeline: PhaseTimeline
    console: Console
    keypad: Any
    pedal: Any
    compositor: Compositor
    display: Any
    alarm: AlarmSound
    closed: bool = False

    @property
    def renderer_device(self) -> str:
        return device_label(self.renderer)

    def fall_back_to_cpu(self, cfg: ApplianceConfig) -> None:
        """Replace a failed OpenCL device by PoCL's CPU device; phases are prepared again there."""
        old = self.timeline
        self.renderer = make_renderer(cfg, device="cpu")
        self.timeline = PhaseTimeline(patient_phases(cfg), self.renderer, at_end=cfg.case.at_end)
        old.close()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for name, close in (("camera", self.camera.stop), ("keypad", self.keypad.close), ("pedal", self.pedal.close), ("alarm", self.alarm.stop),
                            ("phase loader", self.timeline.close), ("display", self.display.close)):
            try:
                close()
            except Exception as e:  # noqa: BLE001 - closing one part must not leave the others open
                log.warning("closing the %s: %s", name, e)


#: How long start-up waits for the first phase of the case to be loaded and prepared (s).
FIRST_PHASE_TIMEOUT_S = 300.0


def warm_up(cfg: ApplianceConfig, renderer: Renderer, timeline: PhaseTimeline) -> float:
    """Render two throw-away frames (plain and blended) so kernels and ray tables are built
    before the session starts; returns the seconds it took."""
    import time

    from ..tracking.trajectory import pose_from_angles

    t0 = time.monotonic()
    timeline.wait_ready(FIRST_PHASE_TIMEOUT_S)
    a, _, _ = timeline.at(0.0)
    # The box straight under the webcam: any pose that puts the patient in the beam will do.
    T = cfg.fluoroscope.T_xray_from_webcam() @ pose_from_angles([0.0, 0.0, 550.0]) @ matrix(cfg.case.T_phantom_from_ct)
    renderer.render(a, T, View())
    renderer.render(a, T, View(), blend=(a, 0.5))
    return time.monotonic() - t0


def open_parts(cfg: ApplianceConfig, console_clock: Callable[[], float]) -> Parts:
    """Every part the workers need, opened from the active profiles.

    The display comes first and shows that the appliance is starting; the console and its
    inputs come last, after the renderer is warm, so a scripted session starts on time.
    """
    d = cfg.appliance.devices.display
    display_path = str(data_path(cfg, d.path)) if d.target == "file" else None
    try:
        if display_path:
            Path(display_path).parent.mkdir(parents=True, exist_ok=True)
        display = open_display(d.target, path=display_path, width=d.width, height=d.height, bpp=d.bpp)
    except OSError as e:
        # The driver's message names the device or file and what is wrong with it.
        raise FluorosimError(f"display: {e}; check devices.display in {cfg.path}") from None
    compositor = Compositor(display.width, display.height,
                            circular_fov=cfg.fluoroscope.detector.kind == "image_intensifier")
    display.show(compositor.compose(None, Overlay(case=cfg.case.title, operator=cfg.appliance.operator,
                                                  fluoroscope=cfg.fluoroscope.name,
                                                  warnings=["starting: preparing the patient and the X-ray renderer"])))
    renderer = make_renderer(cfg)
    timeline = PhaseTimeline(patient_phases(cfg), renderer, at_end=cfg.case.at_end)
    try:
        took = warm_up(cfg, renderer, timeline)
        log.info("renderer warm on %s in %.1f s", device_label(renderer), took)
        camera = open_camera(cfg)
        now = console_clock()
        keypad, pedal = open_inputs(cfg, now)
        return Parts(
            camera=camera,
            tracker=open_tracker(cfg),
            renderer=renderer,
            timeline=timeline,
            console=Console(cfg.fluoroscope, cfg.keymap, t0=now),
            keypad=keypad, pedal=pedal,
            compositor=compositor,
            display=display,
            alarm=AlarmSound(),
        )
    except BaseException:
        timeline.close()
        display.close()
        raise


__all__ = ["Parts", "data_path", "device_label", "make_overlay", "make_renderer", "make_view",
           "open_parts", "patient_phases", "rendered_fluoroscope"]
