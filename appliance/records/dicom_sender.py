"""The DICOM send queue: what to send where, and one round of sending it.

Saved images go to the destinations that take images, each session's dose report to those
that take dose reports, through the outbox (records.outbox, kind "dicom", keyed by SOP
Instance UID). A round sends, per destination, what is due in one association and records
each confirmation as it arrives, so a kill between two objects resends neither of the
confirmed ones. A destination that fails `retry.warn_after_failures` rounds in a row counts
as failing: `problems()` gives the banner line and one warning goes to the log; the line
clears, and an info line is logged, when it answers again.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import pydicom

from ..config.dicom import Destination, Dicom
from . import dicom_network
from .dicom_network import DestinationError, StoreResult
from .outbox import FailureStreaks, Item, Outbox, RoundReport

log = logging.getLogger(__name__)

KIND = "dicom"
BATCH = 32        # objects per association per round


def queue_object(outbox: Outbox, dicom: Dicom, data: bytes, what: str, label: str, session_id: int | None) -> list[str]:
    """Queue one Part 10 object (`what` is "image" or "dose_report") for the destinations that
    take it; returns the names it was newly queued for (none if it was already queued there:
    queueing one object twice changes nothing)."""
    names = [d.name for d in dicom.destinations if d.takes(what)]  # type: ignore[arg-type]
    if not names:
        return []
    return names if outbox.put(sop_instance_uid(data), label, data, names, session_id=session_id) else []


def sop_instance_uid(data: bytes) -> str:
    """The key an object is queued under."""
    return str(pydicom.dcmread(io.BytesIO(data), stop_before_pixels=True).SOPInstanceUID)


class DicomSender:
    """Sends what the outbox holds for the destinations of `dicom`; `base` is the profile's folder."""

    def __init__(self, outbox: Outbox, dicom: Dicom, base: Path, *, failures: dict[str, tuple[int, str]] | None = None):
        self.outbox = outbox
        self.dicom = dicom
        self.base = base
        self.streaks = FailureStreaks("DICOM", dicom.retry.warn_after_failures, log, failures)
        #: Destination -> (failed rounds in a row, the last error's short reason); kept across a reload.
        self.failures = self.streaks.counts

    def run_round(self, *, ignore_backoff: bool = False, key: str | None = None) -> RoundReport:
        """Send what is due (or only the object `key`) to each destination, one association each."""
        report = RoundReport()
        retry = self.dicom.retry
        for dest in self.dicom.destinations:
            items = self.outbox.claim(dest.name, lease_s=self.dicom.timeout_s * (BATCH + 3), limit=BATCH,
                                      ignore_backoff=ignore_backoff, key=key)
            if not items:
                continue
            by_key = {i.key: i for i in items}
            done: set[str] = set()

            def heard(result: StoreResult, by_key: dict[str, Item] = by_key, done: set[str] = done,
                      dest: Destination = dest) -> None:
                item = by_key[result.key]
                done.add(result.key)
                if result.ok:
                    self.outbox.delivered(item)
                    report.sent[dest.name] = report.sent.get(dest.name, 0) + 1
                else:
                    self.outbox.failed(item, result.message, first_delay_s=retry.first_delay_s,
                                       max_delay_s=retry.max_delay_s)
                    report.errors.append(f"{item.label}: {result.message}")
            try:
                dicom_network.store(self.dicom, dest, self.base, [(i.key, i.payload) for i in items], heard)
            except DestinationError as e:
                message = str(e)
                for item in items:
                    if item.key not in done:
                        self.outbox.failed(item, message, first_delay_s=retry.first_delay_s, max_delay_s=retry.max_delay_s)
                report.errors.append(message)
                self.streaks.failed(dest.name, message, e.short)
                continue
            self.streaks.answered(dest.name)
        return report

    def problems(self) -> list[str]:
        """A few words per destination that keeps failing, for the on-screen banner; they stay
        the same while it keeps failing the same way (the log has the full line once)."""
        return self.streaks.problems()
