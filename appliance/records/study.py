"""One study per session: the UIDs, times and patient, study and equipment attributes that a
session's dose report and its saved images share.

Every UID is derived (RFC 4122 version 5, as a 2.25 UID) from the hash of the session's
`session_start` ledger event. That event records the appliance's Device Observer UID, which
is random per appliance, and the session's wall-clock start, so the UIDs are globally unique,
yet rebuilding a report or retrying a send from the ledger gives the same UIDs every time.

A session's study starts when the session starts: Study Date/Time and the saved images'
Series Date/Time are the session's start for every object, so they agree across the series.
Each saved image references the Irradiation Event UID of the fluoroscopy run that made it,
the same UID the dose report gives that run.
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass

from pydicom.dataset import Dataset
from pydicom.sequence import Sequence

from .. import __version__
from ..config.case import Patient
from .dicom import set_simulated_patient, uid

# The training procedure, coded where importers read it (Procedure Code Sequence of the
# General Study module, which OpenREM reads as the study's procedure).
LOCAL_SCHEME = "99FLUOROSIM"
TRAINING_PROCEDURE = ("TRAINING", LOCAL_SCHEME, "Simulated fluoroscopy training session")
STUDY_DESCRIPTION = "Fluoroscopy training (simulated)"


def code(c: tuple[str, str, str]) -> Dataset:
    ds = Dataset()
    ds.CodeValue, ds.CodingSchemeDesignator, ds.CodeMeaning = c
    return ds


def person_name(operator: str) -> str:
    """An operator as a DICOM Person Name, Family^Given: 'Jane Doe' and 'Doe, Jane' give
    'Doe^Jane'; a single word (a login such as 'trainee') is the family name alone."""
    text = " ".join(operator.split())
    if "^" in text:
        return text[:64]
    if "," in text:
        family, _, given = text.partition(",")
        return f"{family.strip()}^{given.strip()}".rstrip("^")[:64]
    words = text.split(" ")
    if len(words) == 1:
        return text[:64]
    return f"{words[-1]}^{' '.join(words[:-1])}"[:64]


def runs_of(events: list[dict]) -> list[tuple[dict, dict, dict]]:
    """(fluoro_on row, fluoro_off row, fluoro_off detail) of each finished run, in order."""
    out = []
    on = None
    for e in events:
        if e["kind"] == "fluoro_on":
            on = e
        elif e["kind"] == "fluoro_off" and on is not None:
            out.append((on, e, json.loads(e["detail"])))
            on = None
    return out


@dataclass(frozen=True)
class SessionStudy:
    """What every DICOM object of one session has in common. Built by `session_study`."""

    session_id: int
    start_hash: str
    started: dt.datetime
    operator: str
    case_title: str
    equipment: dict
    patient: Patient
    fluoroscope: str

    @property
    def study_uid(self) -> str:
        return uid("study", self.start_hash)

    @property
    def report_series_uid(self) -> str:
        return uid("series", self.start_hash)

    @property
    def report_uid(self) -> str:
        return uid("rdsr", self.start_hash, self.session_id)

    @property
    def image_series_uid(self) -> str:
        return uid("saved images series", self.start_hash)

    def image_uid(self, number: int) -> str:
        return uid("saved image", self.start_hash, number)

    @property
    def procedure_step_uid(self) -> str:
        """The session as a performed procedure step, which the report and the images reference.

        No MPPS N-CREATE/N-SET is sent for it, by choice: a training session is no ordered
        procedure (no worklist entry, a virtual patient), so an MPPS would put an unscheduled
        procedure for a patient who does not exist into the RIS, and the dose registry and
        PACS that take the objects do not need one. The reference stays because IHE REM makes
        it Type 1 in the dose report (dciodvfy -profile IHEREM refuses it empty or absent), and
        PS3.17 Annex J.2.2 describes exactly this: a modality that cannot N-CREATE generates the
        MPPS SOP Instance UID and puts it in its objects, and a system that later N-CREATEs the
        step (J.5) uses that UID, with the step's ID and start date and time from the images."""
        return uid("performed procedure step", self.start_hash)

    @staticmethod
    def event_uid(fluoro_on_hash: str) -> str:
        """The Irradiation Event UID of the run that began with this fluoro_on event."""
        return uid("irradiation event", fluoro_on_hash)

    @property
    def device_uid(self) -> str:
        # Sessions recorded before appliances had an identity of their own.
        return self.equipment.get("device_uid") or uid("device", self.manufacturer, self.model, self.serial)

    @property
    def manufacturer(self) -> str:
        return self.equipment.get("manufacturer") or "fluorosim"

    @property
    def model(self) -> str:
        return self.equipment.get("model") or self.fluoroscope

    @property
    def serial(self) -> str:
        return self.equipment.get("serial") or self.fluoroscope

    @property
    def patient_id(self) -> str:
        return f"SIM-{self.session_id}"


def session_study(session: dict, events: list[dict]) -> SessionStudy:
    """The study of a session from its ledger rows (the sessions row and its events in order)."""
    start = next(e for e in events if e["kind"] == "session_start")
    detail = json.loads(start["detail"])
    patient = Patient(**{k: v for k, v in (detail.get("patient") or {}).items() if k in Patient.model_fields})
    return SessionStudy(session_id=session["id"], start_hash=start["hash"],
                        started=dt.datetime.fromtimestamp(session["started_wall"], tz=dt.UTC),
                        operator=session["operator"], case_title=session["case_title"],
                        equipment=detail.get("equipment") or {}, patient=patient, fluoroscope=session["fluoroscope"])


def run_before(events: list[dict], event_id: int) -> dict | None:
    """The fluoro_on row of the last run begun before event `event_id` (the run a save shows)."""
    on = None
    for e in events:
        if e["id"] >= event_id:
            break
        if e["kind"] == "fluoro_on":
            on = e
    return on


def saved_image_context(session: dict, events: list[dict], save_number: int) -> tuple[SessionStudy, str | None]:
    """The study of a session and the Irradiation Event UID of the run that saved image
    `save_number` shows (None if no run came before it)."""
    study = session_study(session, events)
    saves = [e for e in events if e["kind"] == "save" and json.loads(e["detail"]).get("n") == save_number]
    on = run_before(events, saves[-1]["id"] if saves else events[-1]["id"] + 1)
    return study, None if on is None else study.event_uid(on["hash"])


MPPS_SOP_CLASS = "1.2.840.10008.3.1.2.3.3"


def procedure_step_reference(study: SessionStudy) -> Sequence:
    ref = Dataset()
    ref.ReferencedSOPClassUID = MPPS_SOP_CLASS
    ref.ReferencedSOPInstanceUID = study.procedure_step_uid
    return Sequence([ref])


def apply_common(ds: Dataset, study: SessionStudy) -> None:
    """Patient, study and equipment attributes, the same in every object of the session (so a
    PACS files them as one patient and one study, and dcentvfy finds them consistent)."""
    eq = study.equipment
    ds.SpecificCharacterSet = "ISO_IR 192"
    ds.TimezoneOffsetFromUTC = "+0000"
    # Patient: a virtual patient per session; the ID is unique per appliance, so its issuer is
    # qualified by the Device Observer UID and a registry never adds two sessions' doses.
    set_simulated_patient(ds, study.patient.model_dump(), study.session_id)
    ds.IssuerOfPatientID = (eq.get("patient_id_issuer") or "FLUOROSIM")[:64]
    issuer = Dataset()
    issuer.UniversalEntityID = study.device_uid
    issuer.UniversalEntityIDType = "ISO"
    ds.IssuerOfPatientIDQualifiersSequence = Sequence([issuer])
    # Study.
    ds.StudyInstanceUID = study.study_uid
    ds.StudyDate = study.started.strftime("%Y%m%d")
    ds.StudyTime = study.started.strftime("%H%M%S.%f")
    ds.StudyID = str(study.session_id)[:16]
    ds.AccessionNumber = ""
    ds.ReferringPhysicianName = ""
    ds.StudyDescription = STUDY_DESCRIPTION
    ds.ProcedureCodeSequence = Sequence([code(TRAINING_PROCEDURE)])
    case_title = study.case_title
    ds.AdmittingDiagnosesDescription = f"Training case: {case_title}"[:64]
    ds.AdmittingDiagnosesCodeSequence = Sequence([code((f"CASE-{uid('case', case_title)[-10:]}", LOCAL_SCHEME,
                                                        case_title[:64] or "training case"))])
    # Equipment: this appliance.
    ds.Manufacturer = study.manufacturer[:64]
    ds.ManufacturerModelName = study.model[:64]
    ds.DeviceSerialNumber = study.serial[:64]
    ds.SoftwareVersions = f"fluorosim {__version__}"
    ds.InstitutionName = (eq.get("institution") or "fluorosim training appliance")[:64]
    if eq.get("department"):
        ds.InstitutionalDepartmentName = eq["department"][:64]
    if eq.get("station_name"):
        ds.StationName = eq["station_name"][:16]
