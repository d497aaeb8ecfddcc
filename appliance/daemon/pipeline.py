"""The running appliance: camera, tracker, patient timeline, renderer, console and ledger
wired into supervised workers.

    capture   camera.latest() -> tracker.track() -> poses          (LatestValue)
    phases    clock -> timeline.at(t) -> phase                     (LatestValue)
    render    newest pose + phase + console state -> renderer -> compositor -> display
    input     keypad/pedal events -> console -> console state      (LatestValue)
                                              -> console events    (bounded queue)
    records   console events -> ledger (SQLite); saves -> PNG + DICOM

A frame is `T_xray_from_ct = T_xray_from_webcam @ T_webcam_from_phantom @ T_phantom_from_ct`.
Only console events travel through a queue (each is a dose record and none may be lost);
everything else is the newest value, so a slow renderer skips stale poses.

Clocks: the camera, the patient timeline and latency use the wall-clock monotonic time;
the console and its scripted input use the appliance clock (`daemon.clock_rate`), which
the demo runs faster so five minutes of fluoroscopy fit in a short session.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..config import ApplianceConfig
from ..errors import FluorosimError
from ..records.ledger import Ledger
from ..records.identity import device_uid, equipment_of, identity_path
from ..records.rdsr import patient_of
from ..records.saved_images import save_image
from ..records.study import saved_image_context
from .clock import SimClock
from .frame_stats import FrameStats
from .handoff import LatestValue
from .health import (CameraState, DiskSpace, InputDeviceState, TrackingState, profile_reload_check, records_check,
                     renderer_fault_check)
from .notify import Notifier
from .parts import Parts, is_cpu, make_overlay, make_view, open_parts, patient_phases, rendered_fluoroscope
from .reload import ProfileKeeper
from .supervisor import Supervisor
from .worker import Worker

log = logging.getLogger(__name__)

#: Console events waiting for the ledger. Events are rare (key presses, dose ticks), so a
#: full queue means the ledger is stuck; the input worker then waits (and stops beating)
#: rather than drop a dose record, and the watchdog takes over.
EVENT_QUEUE = 10_000
#: How long the saved-image flash stays on screen (s, wall clock).
SAVED_FLASH_S = 1.0
#: How often the input worker polls the keypad and pedal and advances the console (s).
INPUT_PERIOD_S = 0.005
#: How often the phase worker looks up the patient's phase (s).
PHASE_PERIOD_S = 0.02
#: SIGTERM to exit within 2 s: the workers get this long to stop (the ledger's flush among them),
#: then the devices this long to close (s).
SHUTDOWN_S = 1.2
CLOSE_DEVICES_S = 0.4
#: How long the records worker waits before writing again after the disk refused (s).
RECORDS_RETRY_S = 1.0
#: How long start-up waits for the camera's first frame before supervising anyway (s).
CAMERA_START_S = 3.0


@dataclass(frozen=True)
class TrackedPose:
    pose: Any                 # appliance.tracking.tracker.Pose
    t_frame: float            # camera frame timestamp (time.monotonic, s)
    seq: int                  # camera frame sequence number


@dataclass(frozen=True)
class PhaseValue:
    prepared_a: Any
    prepared_b: Any
    weight: float
    generation: int           # which renderer prepared it: values of a replaced renderer are not drawn


@dataclass
class ShownFrame:
    """What the display shows now; handed to observers (the demo's snapshots) after each write."""

    rgb_source: Callable[[], np.ndarray]   # reads the framebuffer back
    image: np.ndarray | None               # the rendered image in [0, 1] (last-image-hold keeps it)
    state: Any                             # console state
    pose: TrackedPose | None
    live: bool                             # a new image was rendered for this write
    t_wall: float
    latency_s: float | None
    banners: list[str]
    saved_flash: bool


class Appliance:
    """The appliance as a set of supervised workers around one `ApplianceConfig`."""

    def __init__(self, keeper: ProfileKeeper, notifier: Notifier | None = None, *,
                 on_shown: Callable[[ShownFrame], None] | None = None):
        self.keeper = keeper
        cfg = keeper.current
        self.config: ApplianceConfig = cfg
        daemon = cfg.appliance.daemon
        self.clock = SimClock(daemon.clock_rate)
        self.stats = FrameStats()
        self.on_shown = on_shown
        try:
            cfg.data_dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise FluorosimError(f"{cfg.data_dir}: cannot create the data folder ({e.strerror or e}); "
                                 f"check data_dir in {cfg.path}") from None

        # The ledger first: if another process holds it, nothing else is opened.
        self.ledger = Ledger(cfg.data_dir / "ledger.sqlite")
        try:
            self.parts: Parts = open_parts(cfg, self.clock)
        except BaseException:
            self.ledger.close()
            raise
        self.poses: LatestValue[TrackedPose] = LatestValue("poses")
        self.phases: LatestValue[PhaseValue] = LatestValue("phases")
        self.console_state: LatestValue[Any] = LatestValue("console")
        self.shown: LatestValue[np.ndarray] = LatestValue("shown")
        self.events: queue.Queue = queue.Queue(maxsize=EVENT_QUEUE)
        self._new_fluoroscope: LatestValue[Any] = LatestValue("fluoroscope")
        self._fluoroscope_seq = 0
        # Tube output the automatic brightness control set for the latest image, for the dose.
        self.exposure_factor: LatestValue[float] = LatestValue("exposure factor")
        self._exposure_seq = 0
        self._factor_sent = 1.0
        self.renderer_fault: str | None = None
        self.records_problem: str | None = None
        self._unwritten: list[tuple[Any, Any]] = []
        self.saved: list[tuple[Path, Path]] = []
        self.session_id: int | None = None
        self.case_t0 = time.monotonic()

        self._renderer_generation = 0
        self._frame_seq = -1
        self._last_pose_seq = 0
        self._last_image: np.ndarray | None = None
        self._last_compose = 0.0
        self._last_pulse = -1e9
        self._saved_flash_until = 0.0
        self._hold_t: float | None = None
        self._pose_ok: bool | None = None

        self.workers = [
            Worker("capture", self._capture_step),
            Worker("phases", self._phases_step),
            Worker("render", self._render_step, idle_s=0.0),
            Worker("input", self._input_step, teardown=self._input_teardown, idle_s=0.0),
            Worker("records", self._records_step, setup=self._records_setup, teardown=self._records_teardown,
                   idle_s=0.0),
        ]
        self.supervisor = Supervisor(
            self.workers, notifier,
            stall_timeout_s=daemon.stall_timeout_s, restart_limit=daemon.restart_limit,
            restart_window_s=daemon.restart_window_s, health_period_s=daemon.health_period_s,
            status_period_s=daemon.status_period_s, status=self.status_text,
            health_checks=[
                DiskSpace(cfg.data_dir, daemon.disk_min_free_mb),
                CameraState(lambda: self.parts.camera),
                TrackingState(lambda: self._pose_ok if self.parts.camera.state == "ok" else None),
                InputDeviceState("keypad", lambda: self.parts.keypad),
                InputDeviceState("pedal", lambda: self.parts.pedal),
                renderer_fault_check(lambda: self.renderer_fault),
                profile_reload_check(lambda: self.keeper.problem),
                records_check(lambda: self.records_problem),
            ])

    # --- running -----------------------------------------------------------------------------
    def run(self, until: Callable[[], bool] | None = None, signals: bool = True) -> int:
        """Run until SIGTERM/SIGINT (or `until()`); ends the session and closes the devices."""
        self.parts.camera.start()
        # A moment for the first camera frame, so the screen does not open on "camera starting".
        self.parts.camera.wait(timeout_s=CAMERA_START_S)
        try:
            return self.supervisor.run(on_reload=self.reload, until=until, shutdown_s=SHUTDOWN_S, signals=signals)
        finally:
            self.ledger.close()
            # Devices and the phase loader may each take seconds to let go (a frame being
            # grabbed, a phase being prepared); the 2 s promise of SIGTERM does not wait for them.
            closer = threading.Thread(target=self.parts.close, name="fluorosim-close", daemon=True)
            closer.start()
            closer.join(CLOSE_DEVICES_S)
            if closer.is_alive():
                log.warning("devices still closing at exit")

    def status_text(self) -> str:
        fps = self.stats.fps(time.monotonic())
        return (f"{fps:.1f} fps; camera {self.parts.camera.state}; keypad {self.parts.keypad.state}; "
                f"pedal {self.parts.pedal.state}; renderer {self.parts.renderer_device}")

    def reload(self) -> None:
        """SIGHUP: take up edited fluoroscope and case profiles; a bad edit keeps the last good set."""
        old = self.config
        new, changed = self.keeper.reload()
        if not changed:
            return
        self.config = new
        if new.fluoroscope != old.fluoroscope:
            self.parts.renderer.set_fluoroscope(rendered_fluoroscope(new, fallback=self.renderer_fault is not None))
            # The console belongs to the input worker's thread: it switches there.
            self._new_fluoroscope.put(new.fluoroscope)
            log.info("fluoroscope profile now %s", new.fluoroscope.name)
        if new.case != old.case or new.case_path != old.case_path:
            from ..patient.timeline import PhaseTimeline
            old_timeline = self.parts.timeline
            self.parts.timeline = PhaseTimeline(patient_phases(new), self.parts.renderer, at_end=new.case.at_end)
            self._renderer_generation += 1
            self.case_t0 = time.monotonic()
            old_timeline.close()
            log.info("case now %s", new.case.title)
        if new.appliance.devices != old.appliance.devices or new.data_dir != old.data_dir:
            log.warning("device or data_dir settings changed in %s; they take effect when the service restarts",
                        new.path)

    # --- capture + tracking --------------------------------------------------------------------
    def _capture_step(self, w: Worker) -> bool:
        frame = self.parts.camera.latest(after_seq=self._frame_seq)
        if frame is None:
            w.sleep(0.002)  # latest() never blocks; poll well above the camera's frame rate
            return False
        self._frame_seq = frame.seq
        pose = self.parts.tracker.track(frame.image, frame.t_monotonic)
        self._pose_ok = bool(pose.ok)
        self.poses.put(TrackedPose(pose, frame.t_monotonic, frame.seq))
        return True

    # --- 4D phase loader -----------------------------------------------------------------------
    def _phases_step(self, w: Worker) -> bool:
        """The phase (pair) for now; the timeline's own thread loads and prepares them."""
        state, _ = self.console_state.get()
        t = time.monotonic() - self.case_t0
        if state is not None and state.breath_hold:
            # A breath hold freezes the patient where it is.
            if self._hold_t is None:
                self._hold_t = t
            t = self._hold_t
        elif self._hold_t is not None:
            self.case_t0 += t - self._hold_t  # breathing resumes where the hold began
            t = self._hold_t
            self._hold_t = None
        generation = self._renderer_generation
        try:
            a, b, weight = self.parts.timeline.at(t)
        except FluorosimError:
            w.sleep(0.1)  # no phase prepared yet
            return False
        self.phases.put(PhaseValue(a, b, float(weight), generation))
        w.sleep(PHASE_PERIOD_S)
        return True

    # --- render + display ------------------------------------------------------------------------
    def _render_step(self, w: Worker) -> bool:
        state, _ = self.console_state.get()
        if state is None:
            self.console_state.wait_newer(0, 0.1)
            return False
        # Each pose is looked at once: drawn if the beam is on, else skipped for the next one.
        got_pose = self.poses.newer(self._last_pose_seq)
        tracked = None
        if got_pose is not None:
            tracked, self._last_pose_seq = got_pose
        phase, _ = self.phases.get()
        now = time.monotonic()
        live = False
        if (state.fluoro_on and tracked is not None and tracked.pose.ok and phase is not None
                and phase.generation == self._renderer_generation and self._pulse_due(state)):
            image = self._render(tracked, phase, state, w)
            if image is not None:
                self._last_image = image
                live = True
                factor = self.parts.renderer.exposure_factor
                if factor != self._factor_sent:
                    self._factor_sent = factor
                    self.exposure_factor.put(factor)
        hold_period = 1.0 / self.config.appliance.daemon.hold_refresh_hz
        if not live and now - self._last_compose < hold_period:
            # Nothing new to draw: wait for the next pose rather than spin.
            self.poses.wait_newer(self._last_pose_seq, min(hold_period, 0.02))
            return False
        banners = self.supervisor.banners()
        saved_flash = now < self._saved_flash_until
        overlay = make_overlay(self.config, state, live=live, saved_flash=saved_flash, warnings=banners,
                               fps=self.stats.fps(now))
        rgb = self.parts.compositor.compose(self._last_image, overlay)
        self.parts.display.show(rgb)
        t_shown = time.monotonic()
        self._last_compose = t_shown
        latency = None
        if live:
            latency = t_shown - tracked.t_frame
            self.stats.add(t_shown, latency)
            self.shown.put(self._last_image)
        self.supervisor.first_frame.set()
        if self.on_shown is not None:
            self.on_shown(ShownFrame(self.parts.display.read_back, self._last_image, state, tracked if live else None,
                                     live, t_shown, latency, banners, saved_flash))
        return True

    def _pulse_due(self, state) -> bool:
        """In a pulsed mode a new image comes only at the pulse rate, as on the real unit."""
        rate = state.pulse_rate_per_s
        if not rate:
            return True
        now = self.clock()
        if now - self._last_pulse >= 1.0 / rate:
            self._last_pulse = now
            return True
        return False

    def _render(self, tracked: TrackedPose, phase: PhaseValue, state, w: Worker) -> np.ndarray | None:
        cfg = self.config
        T_xray_from_ct = (cfg.fluoroscope.T_xray_from_webcam() @ tracked.pose.T_webcam_from_phantom
                          @ np.asarray(cfg.case.T_phantom_from_ct, dtype=np.float64))
        view = make_view(cfg, state)
        blend = (phase.prepared_b, phase.weight) if phase.prepared_b is not None else None
        try:
            # The first frames build kernels and tables: seconds on a CPU device, not a hang.
            with w.grace(60.0 if self.stats.frames < 3 else cfg.appliance.daemon.stall_timeout_s):
                return self.parts.renderer.render(phase.prepared_a, T_xray_from_ct, view, blend=blend)
        except FluorosimError:
            raise
        except Exception as e:  # noqa: BLE001 - an OpenCL fault must not end the appliance
            if is_cpu(self.parts.renderer):
                raise
            self.renderer_fault = f"{type(e).__name__}: {e}"[:120]
            log.error("renderer failed on %s (%s); falling back to the CPU device", self.parts.renderer_device, e)
            self.parts.fall_back_to_cpu(cfg)
            self._renderer_generation += 1
            return None

    # --- input ---------------------------------------------------------------------------------
    def _input_step(self, w: Worker) -> bool:
        now = self.clock()
        console = self.parts.console
        out: list[tuple[Any, Any]] = []
        switched = self._new_fluoroscope.newer(self._fluoroscope_seq)
        if switched is not None:
            fluoroscope, self._fluoroscope_seq = switched
            out += [(ce, None) for ce in console.set_fluoroscope(fluoroscope)]
        exposure = self.exposure_factor.newer(self._exposure_seq)
        if exposure is not None:
            factor, self._exposure_seq = exposure
            out += [(ce, None) for ce in console.set_exposure_factor(factor, now)]
        events = self.parts.keypad.poll(now) + self.parts.pedal.poll(now)
        for e in events:
            for ce in console.handle(e):
                # A save is written with the console's state at that press (its count names the file).
                out.append((ce, console.snapshot() if ce.kind == "save" else None))
        out += [(ce, None) for ce in console.tick(now)]
        for item in out:
            self.events.put(item)  # blocks only if the ledger is stuck (see EVENT_QUEUE)
        snapshot = console.snapshot()
        self.parts.alarm.update(snapshot.alarm_sounding)
        self.console_state.put(snapshot)
        w.sleep(INPUT_PERIOD_S)
        return bool(events or out)

    def _input_teardown(self, w: Worker) -> None:
        if not w.stopping:
            return  # crashed: the supervisor restarts this worker with the same console
        # An exposure in progress ends now, so its time and dose reach the ledger.
        for ce in self.parts.console.end(self.clock()):
            self.events.put((ce, None))
        self.console_state.put(self.parts.console.snapshot())

    # --- records -------------------------------------------------------------------------------
    def _records_setup(self, w: Worker) -> None:
        if self.session_id is None:
            cfg = self.config
            fl = cfg.fluoroscope
            self.session_id = self.ledger.start_session(
                cfg.appliance.operator, cfg.case.title, fl.name, time.time(), t_monotonic=self.clock(),
                equipment=equipment_of(fl, cfg.appliance.dicom, device_uid(identity_path(cfg.path, cfg.data_dir,
                                                                                         cfg.appliance.dicom))),
                patient=patient_of(cfg.case))
            log.info("session %s started: operator %s, case %s, fluoroscope %s",
                     self.session_id, cfg.appliance.operator, cfg.case.title, fl.name)

    def _records_step(self, w: Worker) -> bool:
        if self._unwritten:
            # The disk refused the last batch: try again a little later, keeping everything.
            if w.sleep(RECORDS_RETRY_S):
                return False
            return self._record([])
        try:
            batch = [self.events.get(timeout=0.05)]
        except queue.Empty:
            return False
        while len(batch) < 256:
            try:
                batch.append(self.events.get_nowait())
            except queue.Empty:
                break
        return self._record(batch)

    def _record(self, batch: list[tuple[Any, Any]]) -> bool:
        """Write events (and their saved images); on a disk error keep them for the next try."""
        batch = self._unwritten + batch
        try:
            self.ledger.record([ce for ce, _ in batch])
        except FluorosimError as e:
            if not self._unwritten:
                log.error("ledger write failed, %d event(s) kept in memory: %s", len(batch), e)
            self._unwritten = batch
            self.records_problem = str(e)
            return False
        self._unwritten = []
        self.records_problem = None
        for ce, state in batch:
            if ce.kind == "save" and state is not None:
                try:
                    self._save_image(state)
                except FluorosimError as e:
                    # The save itself is in the ledger; only the picture is missing.
                    log.error("image not saved: %s", e)
                    self.records_problem = str(e)
        return True

    def _save_image(self, state) -> None:
        image, _ = self.shown.get()
        if image is None:
            log.warning("save pressed before any image was shown; nothing saved")
            return
        cfg = self.config
        # The fluoroscope as rendered: the DICOM pixel spacing is that of the saved matrix.
        # The image joins its session's study and names the run it shows (records.study).
        study, event_uid = saved_image_context(*self.ledger.session_rows(self.session_id), state.save_count)
        paths = save_image(image, state, self.parts.renderer.fluoroscope, cfg.data_dir / "images", t_wall=time.time(),
                           study=study, event_uid=event_uid)
        self.saved.append(paths)
        self._saved_flash_until = time.monotonic() + SAVED_FLASH_S
        log.info("saved %s and %s", *paths)

    def _records_teardown(self, w: Worker) -> None:
        # The input worker has stopped before this one: what is queued is all there is.
        batch = []
        while True:
            try:
                batch.append(self.events.get_nowait())
            except queue.Empty:
                break
        if batch or self._unwritten:
            self._record(batch)
        if not w.stopping:
            return  # crashed: the supervisor restarts this worker and the session goes on
        if self._unwritten:
            log.error("%d console event(s) could not be written at shutdown: %s", len(self._unwritten),
                      self.records_problem)
        try:
            self.ledger.end_session(time.time())
        except FluorosimError as e:
            # The next start's crash recovery closes the session at its last written event.
            log.error("session %s not closed: %s", self.session_id, e)
            return
        log.info("session %s ended; ledger flushed", self.session_id)
