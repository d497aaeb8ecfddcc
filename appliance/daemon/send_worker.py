"""The send worker: what the records worker queued goes off the appliance.

Images and dose reports go to the PACS and the dose registry (records.dicom_sender), the
ended sessions' xAPI statements to the Learning Record Store (teaching.xapi), both from the
one persistent queue in the ledger's file. Every poll period (the shorter of the DICOM and
the LRS retry's `poll_period_s`) it runs one round of each over the current profile (a
reload that changes a destination takes effect at the next round). A destination that keeps
failing shows as a banner (`dicom_send_check`, `xapi_send_check`); what it was to take stays
queued until it is confirmed.
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..errors import FluorosimError
from ..records.dicom_sender import KIND, DicomSender
from ..records.outbox import Outbox
from ..teaching import xapi
from .health import Level, Reported
from .reload import ProfileKeeper
from .worker import Worker

log = logging.getLogger(__name__)


class SendWorker(Worker):
    def __init__(self, ledger_path: Path, keeper: ProfileKeeper):
        super().__init__("send", idle_s=0.0)
        self.ledger_path, self.keeper = ledger_path, keeper
        self._outbox: Outbox | None = None
        self._xapi_outbox: Outbox | None = None
        self._sender: DicomSender | None = None
        self._xapi: xapi.XapiSender | None = None
        self._unopened: str | None = None

    def _open(self) -> bool:
        """Open the queue; on a disk that was full at start the ledger's file may not be there yet:
        say so once and try again next round (nothing can have been queued meanwhile)."""
        if self._outbox is None:
            try:
                outbox = Outbox(self.ledger_path, KIND)
            except FluorosimError as e:
                if self._unopened is None:
                    log.warning("send queue not open yet, trying again: %s", e)
                self._unopened = str(e)
                return False
            self._outbox, self._xapi_outbox, self._unopened = outbox, Outbox(self.ledger_path, xapi.KIND), None
        return True

    def step(self) -> bool:
        cfg = self.keeper.current
        dicom, lrs = cfg.appliance.dicom, cfg.appliance.teaching.lrs
        if not self._open():
            self._wait(dicom.retry.poll_period_s)
            return False
        assert self._outbox is not None and self._xapi_outbox is not None
        if self._sender is None or self._sender.dicom is not dicom:
            failures = self._sender.failures if self._sender is not None else {}
            self._sender = DicomSender(self._outbox, dicom, cfg.path.parent, failures=failures)
        if lrs is None:
            self._xapi = None
        elif self._xapi is None or self._xapi.lrs is not lrs:
            failures = self._xapi.failures if self._xapi is not None else {}
            self._xapi = xapi.XapiSender(self._xapi_outbox, lrs, cfg.path, failures=failures)
        sent = False
        if dicom.destinations:
            # One association can take a while (time-outs of timeout_s): say so to the supervisor.
            with self.grace(dicom.timeout_s * (len(dicom.destinations) + 1) * 2):
                report = self._sender.run_round()
            for name, n in report.sent.items():
                log.info("DICOM: %d object(s) sent to '%s'", n, name)
            sent = bool(report.sent)
        if self._xapi is not None and lrs is not None:
            with self.grace(lrs.timeout_s * 4):
                report = self._xapi.run_round()
            for n in report.sent.values():
                log.info("xAPI: %d statement(s) sent to %s", n, lrs.endpoint)
            sent = sent or bool(report.sent)
        self._wait(min([dicom.retry.poll_period_s] + ([lrs.retry.poll_period_s] if lrs is not None else [])))
        return sent

    def _wait(self, period_s: float) -> None:
        # Wait for the next round in short steps, beating, so a long poll period is not a hang.
        until = self.clock() + period_s
        while not self.stopping and self.clock() < until:
            self.beat()
            self.sleep(min(0.5, until - self.clock()))

    def teardown(self) -> None:
        if self.stopping and self._outbox is not None and self._xapi_outbox is not None:
            self._outbox.close()
            self._xapi_outbox.close()
            self._outbox = self._xapi_outbox = None

    @property
    def problem(self) -> str | None:
        """The DICOM destinations that keep failing, one line, None while all answer."""
        problems = self._sender.problems() if self._sender is not None else []
        return "; ".join(problems) or None

    @property
    def xapi_problem(self) -> str | None:
        """The LRS, while it keeps failing; None while it answers (or none is configured)."""
        problems = self._xapi.problems() if self._xapi is not None else []
        return "; ".join(problems) or None


def dicom_send_check(problem) -> Reported:
    """Whether every DICOM destination takes what is sent to it (the queue keeps it meanwhile)."""
    return Reported("dicom", problem, Level.WARNING, "{}; images and dose reports stay queued")


def xapi_send_check(problem) -> Reported:
    """Whether the LRS takes the trainees' results (the queue keeps them meanwhile)."""
    return Reported("xapi", problem, Level.WARNING, "{}; trainees' results stay queued")
