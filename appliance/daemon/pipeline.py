"""The running appliance: camera, tracker, patient timeline, renderer, console and ledger
wired into supervised workers, one class each, handing each other typed values.

    capture  CaptureWorker  camera.latest() -> Tracker.track()            -> poses          (LatestValue)
    phases   PhaseWorker    case clock -> PhaseTimeline.at()              -> phases         (LatestValue)
    input    InputWorker    keypad/pedal -> Console.handle()/tick()       -> console_state  (LatestValue)
                                                                          -> events         (bounded queue)
    render   RenderWorker   poses + phases + console_state -> Renderer.render
                            -> Compositor.compose -> Display.show         -> shown, exposure_factor
    records  RecordsWorker  events -> Ledger.record(); saves -> PNG + DICOM -> saves
                            saved images, ended sessions' dose reports    -> DICOM send queue (ledger file)
    send     SendWorker     send queue -> C-STORE to the PACS and the dose registry,
                            xAPI statements to the LRS

Teaching rides on two of them: the render worker hands each live image's geometry to the
input worker (`views`), whose LiveTeaching records it through the console and sends the shot
counter and task line back (`teaching_status`).

Each worker owns its state; this module only opens the parts, makes the slots between the
workers and hands them out. Only console events travel through a queue (each is a dose
record and none may be lost); everything else is the newest value, so a slow renderer
skips stale poses. The path of one frame reads top to bottom in `RenderWorker.step`.

Clocks: the console, its scripted input, the synthetic camera's path and the patient
timeline all run on the appliance clock (`daemon.clock_rate`, 1 on a real appliance), which
the demo runs faster so five minutes of fluoroscopy fit in a short session; one clock, so
an exercise's phase window means the same second to the console, the camera and the case.
Frame stamps and latency stay on the wall-clock monotonic time.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path

from drivers.camera import CaptureState

from ..config import ApplianceConfig
from ..config.fluoroscope import FluoroscopeProfile
from ..console.state import ConsoleState
from ..errors import FluorosimError
from ..patient.heap import keep_large_blocks_apart
from ..records.deferred_ledger import open_ledger
from ..teaching.live import TeachingStatus, live_teaching_for
from .capture_worker import CaptureWorker
from .clock import SimClock
from .frame_stats import fps_text
from .handoff import LatestValue, PhaseValue, Recorded, SavedImage, ShownFrame, ShownImage, Technique, TrackedPose
from .health import (
    CameraState,
    DiskSpace,
    InputDeviceState,
    TrackingState,
    profile_reload_check,
    records_check,
    renderer_fault_check,
)
from .input_worker import InputWorker
from .notify import Notifier
from .parts import Parts, is_cpu, open_parts, rendered_fluoroscope
from .phase_worker import PhaseWorker
from .pose_demand import PoseDemand
from .records_worker import RecordsWorker
from .reload import ProfileKeeper
from .render_worker import RenderWorker
from .send_worker import SendWorker, dicom_send_check, xapi_send_check
from .supervisor import Supervisor

log = logging.getLogger(__name__)

#: Console events waiting for the ledger. Events are rare (key presses, dose ticks), so a
#: full queue means the ledger is stuck; the input worker then waits (and stops beating)
#: rather than drop a dose record, and the watchdog takes over.
EVENT_QUEUE = 10_000
#: SIGTERM to exit within 2 s: the workers get this long to stop (the ledger's flush among them),
#: then the devices this long to close (s).
SHUTDOWN_S = 1.2
CLOSE_DEVICES_S = 0.4
#: A records worker still flushing after SHUTDOWN_S (a machine so loaded that 1.2 s of wall time
#: was not enough CPU) gets this much longer before its ledger is closed: a dose record outranks
#: the 2 s promise, and the unit's TimeoutStopSec (10 s) still covers it (s).
RECORDS_GRACE_S = 5.0
#: How long start-up waits for the camera's first frame before supervising anyway (s).
CAMERA_START_S = 3.0

__all__ = ["Appliance", "ShownFrame"]


class Appliance:
    """The appliance as a set of supervised workers around one `ProfileKeeper`'s profiles."""

    def __init__(self, keeper: ProfileKeeper, notifier: Notifier | None = None, *,
                 on_shown: Callable[[ShownFrame], None] | None = None):
        self.keeper = keeper
        cfg = keeper.current
        daemon = cfg.appliance.daemon
        # Before the renderer's first buffers: its per-frame blocks then never fragment the heap.
        keep_large_blocks_apart()
        self.clock = SimClock(daemon.clock_rate, pace_s=daemon.clock_pace_s)
        try:
            cfg.data_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise FluorosimError(f"{cfg.data_dir}: cannot create the data folder ({e.strerror or e}); "
                                 f"check data_dir in {cfg.path}") from None

        # The ledger first: if another process holds it, nothing else is opened. On a full disk
        # it opens later, when it can (records/deferred_ledger.py).
        self.ledger = open_ledger(cfg.data_dir / "ledger.sqlite")
        try:
            self.parts: Parts = open_parts(cfg, self.clock)
        except BaseException:
            self.ledger.close()
            raise
        parts = self.parts
        carried = self.ledger.carry_over()
        if carried:
            # A crash ended the last session: its timer and alarm count go on until a person resets them.
            parts.console.carry_over(carried["fluoro_time_s"], carried["alarms"])
            log.warning("continuing the fluoroscopy timer of session %s after a crash: %.0f s, %d alarm(s)",
                        carried["from_session"], carried["fluoro_time_s"], carried["alarms"])

        # The slots between the workers: who writes each is the one worker named beside it.
        self.poses: LatestValue[TrackedPose] = LatestValue("poses")                       # capture
        self.phases: LatestValue[PhaseValue] = LatestValue("phases")                      # phases
        self.console_state: LatestValue[ConsoleState] = LatestValue("console")            # input
        self.events: queue.Queue[Recorded] = queue.Queue(maxsize=EVENT_QUEUE)             # input
        self.shown: LatestValue[ShownImage] = LatestValue("shown")                        # render
        exposure_factor: LatestValue[Technique] = LatestValue("technique")              # render
        saves: LatestValue[SavedImage] = LatestValue("saves")                             # records
        self._new_fluoroscope: LatestValue[FluoroscopeProfile] = LatestValue("fluoroscope")  # reload
        views: LatestValue[tuple[float, dict]] = LatestValue("views")                     # render
        self.teaching_status: LatestValue[TeachingStatus] = LatestValue("teaching")       # input
        self.teaching = live_teaching_for(cfg)

        # Poses the renderer would never draw are neither tracked nor, by the synthetic webcam, drawn.
        self.pose_demand = PoseDemand(1.0 / cfg.appliance.devices.camera.fps)
        if hasattr(parts.camera, "wanted"):
            parts.camera.wanted = self.pose_demand.wanted
        self.capture = CaptureWorker(parts.camera, parts.tracker, self.poses, self.pose_demand)
        self.phase = PhaseWorker(parts, self.console_state, self.phases, self.clock)
        self.render = RenderWorker(parts, keeper, poses=self.poses, phases=self.phases,
                                   console_state=self.console_state, saves=saves, shown=self.shown,
                                   exposure_factor=exposure_factor, banners=lambda: self.supervisor.banners(),
                                   on_first_frame=lambda: self.supervisor.first_frame.set(),
                                   on_shown=lambda frame: self._shown(frame, on_shown),
                                   views=views, teaching=self.teaching_status, demand=self.pose_demand)
        self.input = InputWorker(parts.console, [parts.keypad, parts.pedal], parts.alarm, self.clock,
                                 console_state=self.console_state, events=self.events,
                                 fluoroscope=self._new_fluoroscope, exposure_factor=exposure_factor,
                                 teaching=self.teaching, views=views, teaching_status=self.teaching_status,
                                 badge=parts.badge)
        self.records = RecordsWorker(self.ledger, keeper, parts, self.clock, events=self.events, shown=self.shown,
                                     saves=saves, native=self.render.native_image)
        self.sender = SendWorker(self.ledger.path, keeper)
        self.stats = self.render.stats
        self.supervisor = Supervisor(
            # In this order: at shutdown the input worker ends its exposure before records flushes,
            # and the ledger's writer, last, gets whatever time the others leave.
            [self.capture, self.phase, self.render, self.input, self.sender, self.records], notifier,
            stall_timeout_s=daemon.stall_timeout_s, restart_limit=daemon.restart_limit,
            restart_window_s=daemon.restart_window_s, health_period_s=daemon.health_period_s,
            status_period_s=daemon.status_period_s, status=self.status_text,
            health_checks=[
                DiskSpace(cfg.data_dir, daemon.disk_min_free_mb),
                CameraState(lambda: parts.camera),
                TrackingState(lambda: self.capture.pose_ok if parts.camera.state == CaptureState.OK else None),
                InputDeviceState("keypad", lambda: parts.keypad),
                InputDeviceState("pedal", lambda: parts.pedal),
                renderer_fault_check(lambda: self.render.fault),
                profile_reload_check(lambda: self.keeper.problem),
                records_check(lambda: self.records.problem),
                dicom_send_check(lambda: self.sender.problem),
                xapi_send_check(lambda: self.sender.xapi_problem),
            ])

    def _shown(self, frame: ShownFrame, then: Callable[[ShownFrame], None] | None) -> None:
        self.clock.shown()          # a paced clock runs on from each image on screen
        if then is not None:
            then(frame)

    # --- what the demo, the benchmarks and the tests read --------------------------------------
    @property
    def config(self) -> ApplianceConfig:
        return self.keeper.current

    @property
    def renderer_fault(self) -> str | None:
        return self.render.fault

    @property
    def session_id(self) -> int | None:
        return self.records.session_id

    @property
    def saved(self) -> list[tuple[Path, Path]]:
        return self.records.saved

    # --- running -----------------------------------------------------------------------------
    def run(self, until: Callable[[], bool] | None = None, signals: bool = True) -> int:
        """Run until SIGTERM/SIGINT (or `until()`); ends the session and closes the devices."""
        self.parts.camera.start()
        # A moment for the first camera frame, so the screen does not open on "camera starting".
        self.parts.camera.wait(timeout_s=CAMERA_START_S)
        try:
            return self.supervisor.run(on_reload=self.reload, until=until, shutdown_s=SHUTDOWN_S, signals=signals)
        finally:
            if self.records.alive and not self.records.join(RECORDS_GRACE_S):
                log.error("the records worker is still writing at exit; the ledger is left to SQLite's journal")
            else:
                self.ledger.close()
            # Devices and the phase loader may each take seconds to let go (a frame being
            # grabbed, a phase being prepared); the 2 s promise of SIGTERM does not wait for them.
            closer = threading.Thread(target=self.parts.close, name="fluorosim-close", daemon=True)
            closer.start()
            closer.join(CLOSE_DEVICES_S)
            if closer.is_alive():
                log.warning("devices still closing at exit")

    def status_text(self) -> str:
        fps = fps_text(self.stats.fps(time.monotonic())).strip()
        return (f"{fps}; camera {self.parts.camera.state}; keypad {self.parts.keypad.state}; "
                f"pedal {self.parts.pedal.state}; renderer {self.parts.renderer_device} at "
                f"{self.parts.renderer.shape[1]} px")

    def reload(self) -> None:
        """SIGHUP: take up edited fluoroscope and case profiles; a bad edit keeps the last good set."""
        old = self.keeper.current
        new, changed = self.keeper.reload()
        if not changed:
            return
        if new.fluoroscope != old.fluoroscope:
            self.parts.renderer.set_fluoroscope(rendered_fluoroscope(new, fallback=self.render.fault is not None,
                                                                     cpu=is_cpu(self.parts.renderer)))
            # The console belongs to the input worker's thread: it switches there.
            self._new_fluoroscope.put(new.fluoroscope)
            log.info("fluoroscope profile now %s", new.fluoroscope.name)
        if new.case != old.case or new.case_path != old.case_path:
            self.parts.switch_case(new)
            self.phase.restart_case()
            log.info("case now %s", new.case.title)
        if new.appliance.devices != old.appliance.devices or new.data_dir != old.data_dir:
            log.warning("device or data_dir settings changed in %s; they take effect when the service restarts",
                        new.path)
