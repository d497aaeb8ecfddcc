"""DICOM over the network with pynetdicom: C-ECHO and C-STORE to one destination.

Every failure a person can fix (a wrong host, nothing listening, the wrong called AE title,
a destination that does not take dose reports) is a `DestinationError` whose one line names
the destination and says what to check. An object the destination refuses fails alone; a
destination that cannot be reached fails the whole round, and nothing is lost: the caller
keeps the objects queued.
"""

from __future__ import annotations

import io
import logging
import socket
import ssl
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pydicom
from pydicom.uid import (
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    XRayRadiofluoroscopicImageStorage,
)
from pynetdicom import AE, evt
from pynetdicom.association import Association
from pynetdicom.sop_class import Verification, XRayRadiationDoseSRStorage  # type: ignore[attr-defined]

from ..config.dicom import Destination, Dicom
from ..errors import FluorosimError

#: What the appliance sends; each is offered in the encoding it is written in and the default one.
STORAGE_CLASSES = (XRayRadiofluoroscopicImageStorage, XRayRadiationDoseSRStorage)
CLASS_NAMES = {XRayRadiofluoroscopicImageStorage: "X-Ray Radiofluoroscopic Image Storage",
               XRayRadiationDoseSRStorage: "X-Ray Radiation Dose SR Storage"}

_pynetdicom_log = logging.getLogger("pynetdicom")
# pynetdicom logs every refused connection as errors of its own; the appliance logs one line per
# destination instead, so its records are only read here for the socket's reason.
_pynetdicom_log.propagate = False
_pynetdicom_log.setLevel(logging.ERROR)


class DestinationError(FluorosimError):
    """A destination could not be reached or refused the association. `short` is the reason in
    a few words, for the on-screen banner (the message itself is for the log and the admin)."""

    def __init__(self, message: str, short: str = "no answer"):
        super().__init__(message)
        self.short = short


class _SocketReasons(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.reasons: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if message.startswith("TCP Initialisation Error: "):
            self.reasons.append(message.removeprefix("TCP Initialisation Error: "))


_reasons = _SocketReasons()
_pynetdicom_log.addHandler(_reasons)
_one_association = threading.Lock()


def _tls_context(dest: Destination, base: Path) -> tuple[ssl.SSLContext, str] | None:
    if dest.tls is None:
        return None

    def path(written: str) -> str:
        p = Path(written)
        return str(p if p.is_absolute() else base / p)
    try:
        context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=path(dest.tls.ca_file))
        if dest.tls.cert_file and dest.tls.key_file:
            context.load_cert_chain(path(dest.tls.cert_file), path(dest.tls.key_file))
    except (OSError, ssl.SSLError) as e:
        raise DestinationError(f"destination {dest.label()}: cannot load its TLS files ({e}); check dicom.destinations "
                               f"tls: in the appliance profile", "TLS files unreadable") from None
    return context, dest.tls.server_name or dest.host


@contextmanager
def association(dicom: Dicom, dest: Destination, base: Path,
                contexts: Sequence[tuple[str, Sequence[str]]]) -> Iterator[Association]:
    """An established association with `dest`, released on exit; `base` is the profile's folder."""
    ae = AE(ae_title=dicom.ae_title)
    for sop_class, syntaxes in contexts:
        ae.add_requested_context(sop_class, list(syntaxes))
    ae.connection_timeout = ae.acse_timeout = ae.dimse_timeout = ae.network_timeout = dicom.timeout_s
    tls = _tls_context(dest, base)
    try:
        socket.getaddrinfo(dest.host, dest.port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as e:
        raise DestinationError(f"destination {dest.label()}: cannot resolve host '{dest.host}' ({e}); check host in "
                               "the dicom: section and the appliance's name service", "unknown host") from None
    rejection: list = []

    def on_acse(event: evt.Event) -> None:
        primitive = getattr(event, "primitive", None)   # the A-ASSOCIATE primitive of EVT_ACSE_RECV
        if getattr(primitive, "result", None) not in (None, 0x00):
            rejection.append(primitive)

    with _one_association:
        del _reasons.reasons[:]
        assoc = ae.associate(dest.host, dest.port, ae_title=dest.ae_title, tls_args=tls,
                             evt_handlers=[(evt.EVT_ACSE_RECV, on_acse)])
        reasons = list(_reasons.reasons)
    if not assoc.is_established:
        if assoc.is_rejected and rejection:
            r = rejection[0]
            hint = {"Called AE title not recognised": "check the destination's ae_title",
                    "Calling AE title not recognised": f"ask the destination's admin to accept AE title {dicom.ae_title}"}
            reason = r.reason_str
            raise DestinationError(f"destination {dest.label()}: association rejected ({r.result_str.lower()}, "
                                   f"{reason}); {hint.get(reason, 'check ae_title with the destination admin')}",
                                   f"rejected: {reason}")
        why = reasons[0] if reasons else "no answer"
        short = "certificate not verified" if "CERTIFICATE_VERIFY_FAILED" in why else why.split("] ")[-1]
        raise DestinationError(f"destination {dest.label()}: no DICOM association ({why}); check host and port, and that "
                               "the destination's DICOM service is running and reachable", short)
    try:
        yield assoc
    finally:
        if assoc.is_established:
            assoc.release()


def echo(dicom: Dicom, dest: Destination, base: Path) -> float:
    """C-ECHO `dest`; the round trip (ms), or DestinationError."""
    started = time.monotonic()
    with association(dicom, dest, base, [(Verification, [ExplicitVRLittleEndian, ImplicitVRLittleEndian])]) as assoc:
        status = assoc.send_c_echo()
    if not status or status.Status != 0x0000:
        code = f"0x{status.Status:04X}" if status else "no response"
        raise DestinationError(f"destination {dest.label()}: C-ECHO failed ({code}); check the destination's logs",
                               "C-ECHO failed")
    return (time.monotonic() - started) * 1000.0


@dataclass(frozen=True)
class StoreResult:
    key: str
    ok: bool
    message: str


def store(dicom: Dicom, dest: Destination, base: Path, objects: list[tuple[str, bytes]],
          on_result: Callable[[StoreResult], None]) -> None:
    """C-STORE each (key, Part 10 bytes) in one association; `on_result` hears each outcome as
    soon as the destination answers (so it can be recorded before the next is sent)."""
    contexts = [(c, [ExplicitVRLittleEndian, ImplicitVRLittleEndian]) for c in STORAGE_CLASSES]
    with association(dicom, dest, base, contexts) as assoc:
        accepted = {c.abstract_syntax for c in assoc.accepted_contexts}
        for key, data in objects:
            ds = pydicom.dcmread(io.BytesIO(data))
            sop_class = str(ds.SOPClassUID)
            if sop_class not in accepted:
                on_result(StoreResult(key, False, f"destination {dest.label()} does not accept "
                                                  f"{CLASS_NAMES.get(sop_class, sop_class)}; check its objects: setting"))
                continue
            status = assoc.send_c_store(ds)
            if not assoc.is_established:
                raise DestinationError(f"destination {dest.label()}: the association was lost while storing; "
                                       "check the destination's logs", "connection lost")
            code = getattr(status, "Status", None)
            if code is None:
                raise DestinationError(f"destination {dest.label()}: no answer to C-STORE within {dicom.timeout_s:g} s; "
                                       "check the destination's load and logs", "no answer to C-STORE")
            # 0x0000 success; 0xB000, 0xB006, 0xB007 warnings (stored, with coercion or elements dropped).
            if code == 0x0000 or code in (0xB000, 0xB006, 0xB007):
                on_result(StoreResult(key, True, "stored" if code == 0 else f"stored with warning 0x{code:04X}"))
            else:
                on_result(StoreResult(key, False, f"destination {dest.label()} refused the object (C-STORE status "
                                                  f"0x{code:04X}); check the destination's logs"))
