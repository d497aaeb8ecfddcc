"""The DICOM send worker: what the records worker queued goes to the PACS and the dose registry.

Every `dicom.retry.poll_period_s` it runs one round of records.dicom_sender over the
destinations of the current profile (a reload that changes them takes effect at the next
round). A destination that keeps failing shows as a banner through `dicom_send_check`; the
objects stay in the queue, in the ledger's file, until they are confirmed.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..records.dicom_sender import KIND, DicomSender
from ..records.outbox import Outbox
from .health import Level, Reported
from .reload import ProfileKeeper
from .worker import Worker

log = logging.getLogger(__name__)


class DicomSendWorker(Worker):
    def __init__(self, ledger_path: Path, keeper: ProfileKeeper):
        super().__init__("dicom-send", idle_s=0.0)
        self.ledger_path, self.keeper = ledger_path, keeper
        self._outbox: Outbox | None = None
        self._sender: DicomSender | None = None

    def setup(self) -> None:
        if self._outbox is None:
            self._outbox = Outbox(self.ledger_path, KIND)

    def step(self) -> bool:
        cfg = self.keeper.current
        dicom = cfg.appliance.dicom
        assert self._outbox is not None
        if self._sender is None or self._sender.dicom is not dicom:
            failures = self._sender.failures if self._sender is not None else {}
            self._sender = DicomSender(self._outbox, dicom, cfg.path.parent, failures=failures)
        sent = False
        if dicom.destinations:
            # One association can take a while (time-outs of timeout_s): say so to the supervisor.
            with self.grace(dicom.timeout_s * (len(dicom.destinations) + 1) * 2):
                report = self._sender.run_round()
            for name, n in report.sent.items():
                log.info("DICOM: %d object(s) sent to '%s'", n, name)
            sent = bool(report.sent)
        # Wait for the next round in short steps, beating, so a long poll period is not a hang.
        until = self.clock() + dicom.retry.poll_period_s
        while not self.stopping and self.clock() < until:
            self.beat()
            self.sleep(min(0.5, until - self.clock()))
        return sent

    def teardown(self) -> None:
        if self.stopping and self._outbox is not None:
            self._outbox.close()
            self._outbox = None

    @property
    def problem(self) -> str | None:
        """The destinations that keep failing, one line, None while all answer."""
        problems = self._sender.problems() if self._sender is not None else []
        return "; ".join(problems) or None


def dicom_send_check(problem) -> Reported:
    """Whether every DICOM destination takes what is sent to it (the queue keeps it meanwhile)."""
    return Reported("dicom", problem, Level.WARNING, "{}; images and dose reports stay queued")
