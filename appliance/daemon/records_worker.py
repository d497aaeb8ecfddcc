"""The records worker: console events -> the ledger (SQLite); save presses -> PNG + DICOM images;
each saved image, and the session's dose report and xAPI statements when it ends, into the send
queue (records.outbox, in the ledger's file)."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..config.fluoroscope import FluoroscopeProfile
from ..console.state import ConsoleState
from ..errors import FluorosimError
from ..records import rdsr
from ..records.deferred_ledger import DeferredLedger
from ..records.dicom import encode as encode_dicom
from ..records.dicom_sender import KIND, DicomSender, queue_object, sop_instance_uid
from ..records.disk_reserve import check_reserve
from ..records.identity import device_uid, equipment_of, identity_path
from ..records.ledger import Ledger, open_readonly
from ..records.outbox import Outbox
from ..records.rdsr import patient_of
from ..records.saved_images import save_image
from ..records.study import saved_image_context
from ..teaching import xapi
from .handoff import LatestValue, Recorded, SavedImage, ShownImage
from .health import IMAGE_NOT_SAVED
from .parts import Parts
from .reload import ProfileKeeper
from .worker import Worker

log = logging.getLogger(__name__)

#: How long the worker waits before writing again after the disk refused (s).
RECORDS_RETRY_S = 1.0
#: How long it waits for an event before looking again (s); short, so a stop is seen at once.
EVENT_WAIT_S = 0.05
#: At most this many events go into one ledger transaction.
BATCH_EVENTS = 256


class RecordsWorker(Worker):
    """`events` -> Ledger.record() in batches, then save_image() for each save press.

    The one writer to the ledger. Opens the session at start and closes it at shutdown; an
    event the disk refused is kept in memory and written again, never dropped.
    """

    def __init__(self, ledger: Ledger | DeferredLedger, keeper: ProfileKeeper, parts: Parts, clock: Callable[[], float],
                 *, events: queue.Queue[Recorded], shown: LatestValue[ShownImage], saves: LatestValue[SavedImage],
                 native: Callable[[Callable[[], bool]], tuple[np.ndarray, FluoroscopeProfile] | None] | None = None):
        super().__init__("records", idle_s=0.0)
        self.ledger, self.keeper, self.parts, self.console_clock = ledger, keeper, parts, clock
        self.events, self.shown, self.saves = events, shown, saves
        # The saved image re-rendered at the detector's native matrix (None: save what is shown).
        self.native = native
        self.session_id: int | None = None
        #: Why the last write failed (None while records are written), for the records health check.
        self.problem: str | None = None
        #: (png, dicom) of every image saved this session.
        self.saved: list[tuple[Path, Path]] = []
        self._unwritten: list[Recorded] = []
        self._saves_due: list[ConsoleState] = []     # save presses recorded, their images not yet written
        self._saving = False                         # an image is being saved (its re-render records events)
        self._outbox: Outbox | None = None
        self._xapi_outbox: Outbox | None = None
        self._last_report: bytes | None = None
        self._session_start: tuple[float, float] | None = None

    def setup(self) -> None:
        self._open_send_queue()
        if self.session_id is not None:
            return  # restarted after a crash: the session goes on
        if self._session_start is None:
            # When the session began, even if the disk lets it be written only later.
            self._session_start = (time.time(), self.console_clock())
        self._start_session()

    def _open_send_queue(self) -> None:
        """Open the send queue once the ledger is open: at start, or, on a disk that was full at
        start, when the ledger opens. Its own connections to the ledger's file: the send queue is
        outside the event chain."""
        if self._outbox is not None or (isinstance(self.ledger, DeferredLedger) and not self.ledger.opened):
            return
        try:
            self._outbox = Outbox(self.ledger.path, KIND)
            self._xapi_outbox = Outbox(self.ledger.path, xapi.KIND)
        except FluorosimError as e:
            log.error("send queue not opened, nothing is queued to send until it opens: %s", e)
            if self._outbox is not None:
                self._outbox.close()
            self._outbox = None
            return
        # Sessions a crash or power loss left open were closed when the ledger opened, and the
        # last run may have been cut off before it queued its report: queue what is missing.
        for sid in sorted(set(self.ledger.recovered) | set(self._last_ended())):
            self._queue_report(sid)
            self._queue_statements(sid)

    def _start_session(self) -> bool:
        """Open the session in the ledger; on a full disk say so and try again later, never crash."""
        cfg = self.keeper.current
        fl = cfg.fluoroscope
        dicom = cfg.appliance.dicom
        try:
            identity = device_uid(identity_path(cfg.path, cfg.data_dir, dicom))
        except FluorosimError as e:
            # Training goes on; the session's objects then name the device by its profile only.
            log.error("no Device Observer UID: %s", e)
            identity = ""
        assert self._session_start is not None
        try:
            self.session_id = self.ledger.start_session(
                cfg.appliance.operator, cfg.case.title, fl.name, self._session_start[0],
                t_monotonic=self._session_start[1], equipment=equipment_of(fl, dicom, identity),
                patient=patient_of(cfg.case))
        except FluorosimError as e:
            if self.problem is None:
                log.error("session not opened in the ledger, events kept in memory: %s", e)
            self.problem = str(e)
            return False
        self.problem = None
        log.info("session %s started: operator %s, case %s, fluoroscope %s",
                 self.session_id, cfg.appliance.operator, cfg.case.title, fl.name)
        self._open_send_queue()    # a ledger that opened late, after a full disk at start
        return True

    def step(self) -> bool:
        if self.session_id is None:
            # No session yet (the disk refused it): hold what comes in memory, and try again.
            self._hold_queued()
            if self.sleep(RECORDS_RETRY_S) or not self._start_session():
                return False
            return self._record([])
        if self._unwritten:
            # The disk refused the last batch: try again a little later, keeping everything.
            if self.sleep(RECORDS_RETRY_S):
                return False
            return self._record([])
        try:
            batch = [self.events.get(timeout=EVENT_WAIT_S)]
        except queue.Empty:
            return False
        return self._record(batch + self._queued(BATCH_EVENTS - 1))

    def _queued(self, most: int | None = None) -> list[Recorded]:
        """The events waiting in the queue now, at most `most` of them (all without)."""
        out: list[Recorded] = []
        while most is None or len(out) < most:
            try:
                out.append(self.events.get_nowait())
            except queue.Empty:
                break
        return out

    def _hold_queued(self) -> None:
        self._unwritten += self._queued()

    def _record(self, batch: list[Recorded]) -> bool:
        """Write events (and their saved images); on a disk error keep them for the next try."""
        batch = self._unwritten + batch
        try:
            self.ledger.record([item.event for item in batch])
        except FluorosimError as e:
            if not self._unwritten:
                log.error("ledger write failed, %d event(s) kept in memory: %s", len(batch), e)
            self._unwritten = batch
            self.problem = str(e)
            return False
        self._unwritten = []
        self.problem = None
        self._saves_due += [item.save_state for item in batch if item.event.kind == "save" and item.save_state is not None]
        if self._saving:
            return True     # recorded between the bands of an image being saved: its turn comes after
        self._saving = True
        try:
            while self._saves_due:
                try:
                    self._save_image(self._saves_due.pop(0))
                except FluorosimError as e:
                    # The save itself is in the ledger; only the picture is missing.
                    log.error("image not saved: %s", e)
                    self.problem = f"{IMAGE_NOT_SAVED}{e}"
        finally:
            self._saving = False
        return True

    def _save_image(self, state: ConsoleState) -> None:
        cfg = self.keeper.current
        check_reserve(cfg.data_dir, cfg.appliance.daemon.records_reserve_mb, "the picture was")
        shown, _ = self.shown.get()
        if shown is None:
            log.warning("save pressed before any image was shown; nothing saved")
            return
        image = shown.image
        assert self.session_id is not None   # setup() opened it before any event is recorded
        # The image joins its session's study and names the run it shows (records.study).
        study, event_uid = saved_image_context(*self.ledger.session_rows(self.session_id), state.save_count)
        # The fluoroscope as rendered: the DICOM pixel spacing is that of the saved matrix.
        fluoroscope = self.parts.renderer.fluoroscope
        if self.native is not None:
            try:
                # Between the cast's bands the worker beats (a native cast on a CPU takes seconds,
                # and is not a hang) and, stopping, saves what is on screen instead of waiting.
                native = self.native(self._beat_unless_stopping)
            except Exception as e:  # noqa: BLE001 - the image on screen is saved instead
                log.warning("saving the live matrix: the native re-render failed or was cut short (%s)", e)
                native = None
            if native is not None:
                image, fluoroscope = native
        png, dicom = save_image(image, state, fluoroscope, cfg.data_dir / "images",
                                t_wall=time.time(), study=study, event_uid=event_uid, T_xray_from_ct=shown.T_xray_from_ct)
        self.saved.append((png, dicom))
        self.saves.put(SavedImage(png, dicom, time.monotonic()))
        log.info("saved %s and %s", png, dicom)
        if self._outbox is not None and any(d.takes("image") for d in cfg.appliance.dicom.destinations):
            try:
                data = dicom.read_bytes()
            except OSError as e:
                raise FluorosimError(f"{dicom}: cannot read the saved image back to queue it ({e.strerror or e})") from None
            queue_object(self._outbox, cfg.appliance.dicom, data, "image",
                         f"image {state.save_count} of session {self.session_id}", self.session_id)

    def _beat_unless_stopping(self) -> bool:
        """Asked between the bands of a native re-render (and while it is paced): beat, and write
        the events that came in meanwhile, so the dose ledger never waits for a saved image."""
        self.beat()
        if self.session_id is not None and not self._unwritten:
            waiting = self._queued(BATCH_EVENTS)
            if waiting:
                self._record(waiting)
        return self.stopping

    def _send_now(self, report: bytes | None, statements: int) -> None:
        """At shutdown (the send worker has stopped), try to send the session's dose report within
        dicom.send_at_shutdown_s and its xAPI statements within teaching.lrs.send_at_shutdown_s,
        side by side; what does not go in time stays queued for the next start."""
        cfg = self.keeper.current
        dicom, lrs = cfg.appliance.dicom, cfg.appliance.teaching.lrs
        jobs: list[tuple[str, float, Callable[[], dict[str, int]]]] = []
        if report is not None and dicom.send_at_shutdown_s > 0 and any(d.takes("dose_report") for d in dicom.destinations):
            key, quick = sop_instance_uid(report), dicom.model_copy(update={"timeout_s": dicom.send_at_shutdown_s})

            def send_report() -> dict[str, int]:
                with Outbox(self.ledger.path, KIND) as box:
                    return DicomSender(box, quick, cfg.path.parent).run_round(ignore_backoff=True, key=key).sent
            jobs.append(("dose report", dicom.send_at_shutdown_s, send_report))
        if statements and lrs is not None and lrs.send_at_shutdown_s > 0:
            fast = lrs.model_copy(update={"timeout_s": lrs.send_at_shutdown_s})

            def send_statements() -> dict[str, int]:
                with Outbox(self.ledger.path, xapi.KIND) as box:
                    return xapi.XapiSender(box, fast, cfg.path).run_round(ignore_backoff=True).sent
            jobs.append(("xAPI statements", lrs.send_at_shutdown_s, send_statements))
        threads = []
        for what, budget, send in jobs:
            done: dict[str, int] = {}
            # Its own connection: if the time runs out, this thread is left behind at exit.
            thread = threading.Thread(target=lambda send=send, done=done: done.update(send()),
                                      name=f"fluorosim-send-{what.split()[0]}", daemon=True)
            thread.start()
            threads.append((what, budget, thread, done))
        started = time.monotonic()
        for what, budget, thread, done in threads:
            thread.join(max(0.0, budget - (time.monotonic() - started)))
            for name in done:
                log.info("%s of session %s sent to '%s'", what, self.session_id, name)
            if thread.is_alive() or not done:
                log.warning("%s of session %s not confirmed within %.1f s of shutdown; left in the send queue "
                            "for the next start",
                            what, self.session_id, budget)

    def _queue_statements(self, session_id: int) -> int:
        """Queue an ended session's xAPI statements for the LRS; returns how many were new."""
        lrs = self.keeper.current.appliance.teaching.lrs
        if self._xapi_outbox is None or lrs is None:
            return 0
        conn = open_readonly(self.ledger.path)
        try:
            new = xapi.queue_session(self._xapi_outbox, conn, session_id, lrs)
        except FluorosimError as e:
            log.error("xAPI statements of session %s not queued: %s; 'fluorosim lrs send' queues them", session_id, e)
            return 0
        finally:
            conn.close()
        if new:
            log.info("%d xAPI statement(s) of session %s queued for %s", new, session_id, lrs.endpoint)
        return new

    def _last_ended(self) -> list[int]:
        conn = open_readonly(self.ledger.path)
        try:
            last = conn.execute("SELECT max(id) FROM sessions WHERE ended_wall IS NOT NULL").fetchone()[0]
        finally:
            conn.close()
        return [] if last is None else [last]

    def _queue_report(self, session_id: int) -> None:
        """Queue an ended session's dose report for the destinations that take dose reports."""
        dicom = self.keeper.current.appliance.dicom
        if self._outbox is None or not any(d.takes("dose_report") for d in dicom.destinations):
            return
        try:
            report = encode_dicom(rdsr.session_report(*self.ledger.session_rows(session_id)))
            names = queue_object(self._outbox, dicom, report, "dose_report",
                                 f"dose report of session {session_id}", session_id)
            self._last_report = report
        except FluorosimError as e:
            log.error("dose report of session %s not queued: %s; 'fluorosim dicom send --session %s' queues it",
                      session_id, e, session_id)
            return
        if names:
            log.info("dose report of session %s queued for %s", session_id, ", ".join(names))

    def teardown(self) -> None:
        # The input worker has stopped before this one: what is queued is all there is.
        batch = self._queued()
        if self.session_id is None:
            self._unwritten += batch
            batch = []
            if self.stopping:
                self._start_session()
        if (batch or self._unwritten) and self.session_id is not None:
            self._record(batch)
        if not self.stopping:
            return  # crashed: the supervisor restarts this worker and the session goes on
        if self._unwritten:
            # The journal is then the only record: give the session's totals as the console had them.
            last = self._unwritten[-1].event
            log.error("%d console event(s) could not be written at shutdown (session totals then: fluoroscopy %.1f s, "
                      "air kerma %.3f mGy, DAP %.4f Gy cm2): %s", len(self._unwritten), last.fluoro_time_s,
                      last.air_kerma_mgy, last.dap_gy_cm2, self.problem)
        try:
            self.ledger.end_session(time.time())
        except FluorosimError as e:
            # The next start's crash recovery closes the session at its last written event.
            log.error("session %s not closed: %s", self.session_id, e)
            return
        log.info("session %s ended; ledger flushed", self.session_id)
        if self.session_id is not None:
            self._last_report = None
            self._open_send_queue()
            self._queue_report(self.session_id)
            statements = self._queue_statements(self.session_id)
            self._send_now(self._last_report, statements)
        for box in (self._outbox, self._xapi_outbox):
            if box is not None:
                box.close()
        self._outbox = self._xapi_outbox = None
