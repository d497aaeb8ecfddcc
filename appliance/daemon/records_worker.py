"""The records worker: console events -> the ledger (SQLite); save presses -> PNG + DICOM images."""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..console.state import ConsoleState
from ..errors import FluorosimError
from ..records.ledger import Ledger
from ..records.rdsr import equipment_of, patient_of
from ..records.saved_images import save_image
from .handoff import LatestValue, Recorded, SavedImage
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

    def __init__(self, ledger: Ledger, keeper: ProfileKeeper, parts: Parts, clock: Callable[[], float], *,
                 events: queue.Queue[Recorded], shown: LatestValue[np.ndarray], saves: LatestValue[SavedImage]):
        super().__init__("records", idle_s=0.0)
        self.ledger, self.keeper, self.parts, self.console_clock = ledger, keeper, parts, clock
        self.events, self.shown, self.saves = events, shown, saves
        self.session_id: int | None = None
        #: Why the last write failed (None while records are written), for the records health check.
        self.problem: str | None = None
        #: (png, dicom) of every image saved this session.
        self.saved: list[tuple[Path, Path]] = []
        self._unwritten: list[Recorded] = []

    def setup(self) -> None:
        if self.session_id is not None:
            return  # restarted after a crash: the session goes on
        cfg = self.keeper.current
        fl = cfg.fluoroscope
        self.session_id = self.ledger.start_session(
            cfg.appliance.operator, cfg.case.title, fl.name, time.time(), t_monotonic=self.console_clock(),
            equipment=equipment_of(fl), patient=patient_of(cfg.case))
        log.info("session %s started: operator %s, case %s, fluoroscope %s",
                 self.session_id, cfg.appliance.operator, cfg.case.title, fl.name)

    def step(self) -> bool:
        if self._unwritten:
            # The disk refused the last batch: try again a little later, keeping everything.
            if self.sleep(RECORDS_RETRY_S):
                return False
            return self._record([])
        try:
            batch = [self.events.get(timeout=EVENT_WAIT_S)]
        except queue.Empty:
            return False
        while len(batch) < BATCH_EVENTS:
            try:
                batch.append(self.events.get_nowait())
            except queue.Empty:
                break
        return self._record(batch)

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
        for item in batch:
            if item.event.kind == "save" and item.save_state is not None:
                try:
                    self._save_image(item.save_state)
                except FluorosimError as e:
                    # The save itself is in the ledger; only the picture is missing.
                    log.error("image not saved: %s", e)
                    self.problem = str(e)
        return True

    def _save_image(self, state: ConsoleState) -> None:
        image, _ = self.shown.get()
        if image is None:
            log.warning("save pressed before any image was shown; nothing saved")
            return
        cfg = self.keeper.current
        # The fluoroscope as rendered: the DICOM pixel spacing is that of the saved matrix.
        png, dicom = save_image(image, state, self.parts.renderer.fluoroscope, cfg.data_dir / "images",
                                t_wall=time.time(), session_id=self.session_id or 0, operator=cfg.appliance.operator,
                                case_title=cfg.case.title, patient=patient_of(cfg.case))
        self.saved.append((png, dicom))
        self.saves.put(SavedImage(png, dicom, time.monotonic()))
        log.info("saved %s and %s", png, dicom)

    def teardown(self) -> None:
        # The input worker has stopped before this one: what is queued is all there is.
        batch = []
        while True:
            try:
                batch.append(self.events.get_nowait())
            except queue.Empty:
                break
        if batch or self._unwritten:
            self._record(batch)
        if not self.stopping:
            return  # crashed: the supervisor restarts this worker and the session goes on
        if self._unwritten:
            log.error("%d console event(s) could not be written at shutdown: %s", len(self._unwritten), self.problem)
        try:
            self.ledger.end_session(time.time())
        except FluorosimError as e:
            # The next start's crash recovery closes the session at its last written event.
            log.error("session %s not closed: %s", self.session_id, e)
            return
        log.info("session %s ended; ledger flushed", self.session_id)
