"""DICOM X-Ray Radiation Dose SR (TID 10001) of one ledger session, as dose registries import it.

Structure (PS3.16): the root "X-Ray Radiation Dose Report" container names the procedure
(Projection X-Ray), the acquisition device type (Fluoroscopy-Guided Projection Radiography
System, which importers such as OpenREM use to file the report as fluoroscopy), the device
observer, the scope of accumulation (the study); one "Accumulated X-Ray Dose Data" container
(TID 10002 with TID 10004 and TID 10007 rows); one "Irradiation Event X-Ray Data" container
(TID 10003 with its X-ray source rows) per fluoroscopy run; and the source of the
dose information. Code meanings are the standard's, verbatim: importers match them as text.

Units in the report: Gy.m2 for dose-area products, Gy for reference-point doses, s, kV, mA,
ms, mm, m2. The ledger records mGy and Gy cm^2; they are converted here.
"""

from __future__ import annotations

import datetime as dt
import json

import numpy as np
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence

from ..config.case import CaseProfile
from ..config.fluoroscope import FluoroscopeProfile
from . import rdsr_anchor
from .dicom import ds_number
from .positioner import positioner_angles
from .study import (
    LOCAL_SCHEME,
    TRAINING_PROCEDURE,
    SessionStudy,
    apply_common,
    code,
    person_name,
    procedure_step_reference,
    runs_of,
    session_study,
)

XRAY_RADIATION_DOSE_SR = "1.2.840.10008.5.1.4.1.1.88.67"

# (value, scheme, meaning) exactly as PS3.16 spells them.
REPORT = ("113701", "DCM", "X-Ray Radiation Dose Report")
PROCEDURE_REPORTED = ("121058", "DCM", "Procedure reported")
PROJECTION_XRAY = ("113704", "DCM", "Projection X-Ray")
HAS_INTENT = ("363703001", "SCT", "Has Intent")
DIAGNOSTIC_INTENT = ("261004008", "SCT", "Diagnostic Intent")
ACQUISITION_DEVICE_TYPE = ("122142", "DCM", "Acquisition Device Type")
FLUORO_GUIDED_SYSTEM = ("113957", "DCM", "Fluoroscopy-Guided Projection Radiography System")
OBSERVER_TYPE = ("121005", "DCM", "Observer Type")
DEVICE = ("121007", "DCM", "Device")
DEVICE_OBSERVER_UID = ("121012", "DCM", "Device Observer UID")
DEVICE_OBSERVER_NAME = ("121013", "DCM", "Device Observer Name")
DEVICE_OBSERVER_MANUFACTURER = ("121014", "DCM", "Device Observer Manufacturer")
DEVICE_OBSERVER_MODEL = ("121015", "DCM", "Device Observer Model Name")
DEVICE_OBSERVER_SERIAL = ("121016", "DCM", "Device Observer Serial Number")
SCOPE_OF_ACCUMULATION = ("113705", "DCM", "Scope of Accumulation")
STUDY = ("113014", "DCM", "Study")
STUDY_INSTANCE_UID = ("110180", "DCM", "Study Instance UID")
DETECTOR_DATA_AVAILABLE = ("113945", "DCM", "X-Ray Detector Data Available")
SOURCE_DATA_AVAILABLE = ("113943", "DCM", "X-Ray Source Data Available")
MECHANICAL_DATA_AVAILABLE = ("113944", "DCM", "X-Ray Mechanical Data Available")
YES = ("373066001", "SCT", "Yes")
NO = ("373067005", "SCT", "No")
ACCUMULATED = ("113702", "DCM", "Accumulated X-Ray Dose Data")
ACQUISITION_PLANE = ("113764", "DCM", "Acquisition Plane")
SINGLE_PLANE = ("113622", "DCM", "Single Plane")
FLUORO_DAP_TOTAL = ("113726", "DCM", "Fluoro Dose Area Product Total")
FLUORO_DOSE_RP_TOTAL = ("113728", "DCM", "Fluoro Dose (RP) Total")
TOTAL_FLUORO_TIME = ("113730", "DCM", "Total Fluoro Time")
ACQUISITION_DAP_TOTAL = ("113727", "DCM", "Acquisition Dose Area Product Total")
ACQUISITION_DOSE_RP_TOTAL = ("113729", "DCM", "Acquisition Dose (RP) Total")
TOTAL_ACQUISITION_TIME = ("113855", "DCM", "Total Acquisition Time")
DAP_TOTAL = ("113722", "DCM", "Dose Area Product Total")
DOSE_RP_TOTAL = ("113725", "DCM", "Dose (RP) Total")
RADIOGRAPHIC_FRAMES = ("113731", "DCM", "Total Number of Radiographic Frames")
DISTANCE_SOURCE_TO_RP = ("113737", "DCM", "Distance Source to Reference Point")
POSITIONER_PRIMARY_ANGLE = ("112011", "DCM", "Positioner Primary Angle")
POSITIONER_SECONDARY_ANGLE = ("112012", "DCM", "Positioner Secondary Angle")
REFERENCE_POINT_DEFINITION = ("113780", "DCM", "Reference Point Definition")
RP_15CM_FROM_ISOCENTER = ("113860", "DCM", "15cm from Isocenter toward Source")
IRRADIATION_EVENT = ("113706", "DCM", "Irradiation Event X-Ray Data")
IRRADIATION_EVENT_UID = ("113769", "DCM", "Irradiation Event UID")
DATETIME_STARTED = ("111526", "DCM", "DateTime Started")
IRRADIATION_EVENT_TYPE = ("113721", "DCM", "Irradiation Event Type")
FLUOROSCOPY = ("44491008", "SCT", "Fluoroscopy")
ACQUISITION_PROTOCOL = ("125203", "DCM", "Acquisition Protocol")
DAP = ("122130", "DCM", "Dose Area Product")
DOSE_RP = ("113738", "DCM", "Dose (RP)")
FLUORO_MODE = ("113732", "DCM", "Fluoro Mode")
PULSED = ("113631", "DCM", "Pulsed")
CONTINUOUS = ("113630", "DCM", "Continuous")
PULSE_RATE = ("113791", "DCM", "Pulse Rate")
NUMBER_OF_PULSES = ("113768", "DCM", "Number of Pulses")
IRRADIATION_DURATION = ("113742", "DCM", "Irradiation Duration")
KVP = ("113733", "DCM", "KVP")
TUBE_CURRENT = ("113734", "DCM", "X-Ray Tube Current")
PULSE_WIDTH = ("113793", "DCM", "Pulse Width")
FOCAL_SPOT_SIZE = ("113766", "DCM", "Focal Spot Size")
COLLIMATED_FIELD_AREA = ("113790", "DCM", "Collimated Field Area")
COMMENT = ("121106", "DCM", "Comment")
# TID 1020 Person Participant: the trainee at the pedal is the one administering the irradiation.
PERSON_NAME = ("113870", "DCM", "Person Name")
PERSON_ROLE_IN_PROCEDURE = ("113875", "DCM", "Person Role in Procedure")
IRRADIATION_ADMINISTERING = ("113851", "DCM", "Irradiation Administering")
ORGANIZATION_NAME = ("113873", "DCM", "Organization Name")
# Local codes (a "99" scheme, as PS3.16 8.2 allows): a training session has no real diagnosis
# or requested procedure, but IHE REM requires both to be coded (see records.study).
SOURCE_OF_DOSE_INFORMATION = ("113854", "DCM", "Source of Dose Information")
AUTOMATED_DATA_COLLECTION = ("113856", "DCM", "Automated Data Collection")

# UCUM units, meanings as the templates give them.
U_GY_M2 = ("Gy.m2", "UCUM", "Gy.m2")
U_GY = ("Gy", "UCUM", "Gy")
U_S = ("s", "UCUM", "s")
U_KV = ("kV", "UCUM", "kV")
U_MA = ("mA", "UCUM", "mA")
U_MS = ("ms", "UCUM", "ms")
U_MM = ("mm", "UCUM", "mm")
U_M2 = ("m2", "UCUM", "m2")
U_PULSE_RATE = ("{pulse}/s", "UCUM", "pulse/s")
U_PULSES = ("{pulses}", "UCUM", "pulses")
U_NONE = ("1", "UCUM", "no units")
U_DEG = ("deg", "UCUM", "deg")


def _item(relationship: str | None, value_type: str, concept: tuple) -> Dataset:
    ds = Dataset()
    if relationship:
        ds.RelationshipType = relationship
    ds.ValueType = value_type
    ds.ConceptNameCodeSequence = Sequence([code(concept)])
    return ds


def container(relationship: str | None, concept: tuple, children: list[Dataset], template: str | None = None) -> Dataset:
    ds = _item(relationship, "CONTAINER", concept)
    ds.ContinuityOfContent = "SEPARATE"
    if template:
        t = Dataset()
        t.MappingResource = "DCMR"
        t.TemplateIdentifier = template
        ds.ContentTemplateSequence = Sequence([t])
    ds.ContentSequence = Sequence(children)
    return ds


def code_item(relationship: str, concept: tuple, value: tuple, children: list[Dataset] | None = None) -> Dataset:
    ds = _item(relationship, "CODE", concept)
    ds.ConceptCodeSequence = Sequence([code(value)])
    if children:
        ds.ContentSequence = Sequence(children)
    return ds


def num_item(relationship: str, concept: tuple, value: float, unit: tuple) -> Dataset:
    ds = _item(relationship, "NUM", concept)
    measured = Dataset()
    measured.NumericValue = ds_number(value)
    measured.FloatingPointValue = float(value)
    measured.MeasurementUnitsCodeSequence = Sequence([code(unit)])
    ds.MeasuredValueSequence = Sequence([measured])
    return ds


def text_item(relationship: str, concept: tuple, text: str) -> Dataset:
    ds = _item(relationship, "TEXT", concept)
    ds.TextValue = text
    return ds


def _with_children(ds: Dataset, children: list[Dataset] | None) -> Dataset:
    if children:
        ds.ContentSequence = Sequence(children)
    return ds


def uid_item(relationship: str, concept: tuple, uid: str, children: list[Dataset] | None = None) -> Dataset:
    ds = _item(relationship, "UIDREF", concept)
    ds.UID = uid
    return _with_children(ds, children)


def datetime_item(relationship: str, concept: tuple, when: dt.datetime) -> Dataset:
    ds = _item(relationship, "DATETIME", concept)
    ds.DateTime = dicom_datetime(when)
    return ds


def pname_item(relationship: str, concept: tuple, name: str, children: list[Dataset] | None = None) -> Dataset:
    ds = _item(relationship, "PNAME", concept)
    ds.PersonName = name
    return _with_children(ds, children)


def utc(t_wall: float) -> dt.datetime:
    return dt.datetime.fromtimestamp(t_wall, tz=dt.UTC)


def dicom_datetime(when: dt.datetime) -> str:
    """DT without an offset: the header's Timezone Offset From UTC applies (and DCMTK refuses
    an offset in a content item's DateTime)."""
    return when.strftime("%Y%m%d%H%M%S.%f")


def _observer(study: SessionStudy) -> list[Dataset]:
    name = study.equipment.get("station_name") or study.fluoroscope or "fluorosim"
    return [
        code_item("HAS OBS CONTEXT", OBSERVER_TYPE, DEVICE),
        uid_item("HAS OBS CONTEXT", DEVICE_OBSERVER_UID, study.device_uid),
        text_item("HAS OBS CONTEXT", DEVICE_OBSERVER_NAME, name[:64]),
        text_item("HAS OBS CONTEXT", DEVICE_OBSERVER_MANUFACTURER, study.manufacturer[:64]),
        text_item("HAS OBS CONTEXT", DEVICE_OBSERVER_MODEL, study.model[:64]),
        text_item("HAS OBS CONTEXT", DEVICE_OBSERVER_SERIAL, study.serial[:64]),
    ]


def _person_participant(study: SessionStudy) -> Dataset:
    properties = [code_item("HAS PROPERTIES", PERSON_ROLE_IN_PROCEDURE, IRRADIATION_ADMINISTERING)]
    institution = study.equipment.get("institution")
    if institution:
        properties.append(text_item("HAS PROPERTIES", ORGANIZATION_NAME, institution[:64]))
    return pname_item("CONTAINS", PERSON_NAME, person_name(study.operator), properties)


def run_angles(events: list[dict], on: dict, off: dict) -> tuple[float, float] | None:
    """Positioner angles (deg) of a run: of its first recorded image's pose (the ledger's `view`
    records, which teaching writes for the first image of every exposure); None without one."""
    for e in events:
        if on["id"] < e["id"] < off["id"] and e["kind"] == "view":
            T = json.loads(e["detail"]).get("T_xray_from_ct")
            if T is not None:
                return positioner_angles(np.asarray(T, dtype=np.float64))
    return None


def _irradiation_event(run: dict, event_uid: str, study: SessionStudy,
                       angles: tuple[float, float] | None = None) -> Dataset:
    pulsed = run.get("pulse_rate_per_s") is not None
    kerma_gy = run["air_kerma_mgy"] / 1000.0
    children = [
        code_item("HAS CONCEPT MOD", ACQUISITION_PLANE, SINGLE_PLANE),
        uid_item("CONTAINS", IRRADIATION_EVENT_UID, event_uid),
        datetime_item("CONTAINS", DATETIME_STARTED, utc(run["start_wall"])),
        code_item("CONTAINS", IRRADIATION_EVENT_TYPE, FLUOROSCOPY),
    ]
    if run.get("mode"):
        children.append(text_item("CONTAINS", ACQUISITION_PROTOCOL, f"{run['mode']}, zoom {run.get('zoom')}"))
    children += [
        num_item("CONTAINS", DAP, run["dap_gy_cm2"] / 1e4, U_GY_M2),
        num_item("CONTAINS", DOSE_RP, kerma_gy, U_GY),
        code_item("CONTAINS", REFERENCE_POINT_DEFINITION, RP_15CM_FROM_ISOCENTER),
    ]
    # OpenREM and TID 10003 read the distance per irradiation event.
    if run.get("source_to_reference_mm"):
        children.append(num_item("CONTAINS", DISTANCE_SOURCE_TO_RP, run["source_to_reference_mm"], U_MM))
    if angles is not None:
        # TID 10003C, at the run's start (the C-arm may move during the run; the images carry their own).
        children += [num_item("CONTAINS", POSITIONER_PRIMARY_ANGLE, round(angles[0], 1), U_DEG),
                     num_item("CONTAINS", POSITIONER_SECONDARY_ANGLE, round(angles[1], 1), U_DEG)]
    children.append(code_item("CONTAINS", FLUORO_MODE, PULSED if pulsed else CONTINUOUS))
    if pulsed:
        children += [num_item("CONTAINS", PULSE_RATE, run["pulse_rate_per_s"], U_PULSE_RATE),
                     num_item("CONTAINS", NUMBER_OF_PULSES, run.get("pulses", 0), U_PULSES)]
    children.append(num_item("CONTAINS", IRRADIATION_DURATION, run["duration_s"], U_S))
    if run.get("kvp") is not None:
        children.append(num_item("CONTAINS", KVP, run["kvp"], U_KV))
    if run.get("ma") is not None:
        children.append(num_item("CONTAINS", TUBE_CURRENT, run["ma"], U_MA))
    if pulsed and run.get("pulse_width_ms") is not None:
        children.append(num_item("CONTAINS", PULSE_WIDTH, run["pulse_width_ms"], U_MS))
    if run.get("focal_spot_mm") is not None:
        children.append(num_item("CONTAINS", FOCAL_SPOT_SIZE, run["focal_spot_mm"], U_MM))
    if run.get("field_area_cm2") is not None:
        children.append(num_item("CONTAINS", COLLIMATED_FIELD_AREA, run["field_area_cm2"] / 1e4, U_M2))
    if run.get("reason") == "recovered":
        children.append(text_item("CONTAINS", COMMENT, "Run cut off by a power loss or crash; "
                                                       "values cover the exposure recorded before it."))
    children.append(_person_participant(study))
    return container("CONTAINS", IRRADIATION_EVENT, children, "10003")


def session_report(session: dict, events: list[dict]) -> Dataset:
    """The RDSR dataset of one ended session; `session` and `events` are ledger rows."""
    study = session_study(session, events)
    runs = runs_of(events)
    angles = [run_angles(events, on, off) for on, off, _ in runs]
    started, ended = utc(session["started_wall"]), utc(session["ended_wall"] or session["started_wall"])
    dap_gy_m2 = session["dap_gy_cm2"] / 1e4
    kerma_gy = session["air_kerma_mgy"] / 1000.0

    accumulated = [
        code_item("HAS CONCEPT MOD", ACQUISITION_PLANE, SINGLE_PLANE),
        # TID 10004: fluoroscopy and acquisition totals (a simulator acquires no radiographs).
        num_item("CONTAINS", FLUORO_DAP_TOTAL, dap_gy_m2, U_GY_M2),
        num_item("CONTAINS", FLUORO_DOSE_RP_TOTAL, kerma_gy, U_GY),
        num_item("CONTAINS", TOTAL_FLUORO_TIME, session["fluoro_time_s"], U_S),
        num_item("CONTAINS", ACQUISITION_DAP_TOTAL, 0.0, U_GY_M2),
        num_item("CONTAINS", ACQUISITION_DOSE_RP_TOTAL, 0.0, U_GY),
        num_item("CONTAINS", TOTAL_ACQUISITION_TIME, 0.0, U_S),
        # TID 10007: the totals over everything.
        num_item("CONTAINS", DAP_TOTAL, dap_gy_m2, U_GY_M2),
        num_item("CONTAINS", DOSE_RP_TOTAL, kerma_gy, U_GY),
        num_item("CONTAINS", RADIOGRAPHIC_FRAMES, 0, U_NONE),
        code_item("CONTAINS", REFERENCE_POINT_DEFINITION, RP_15CM_FROM_ISOCENTER),
    ]

    content = [
        code_item("HAS CONCEPT MOD", PROCEDURE_REPORTED, PROJECTION_XRAY,
                  [code_item("HAS CONCEPT MOD", HAS_INTENT, DIAGNOSTIC_INTENT)]),
        code_item("CONTAINS", ACQUISITION_DEVICE_TYPE, FLUORO_GUIDED_SYSTEM),
        *_observer(study),
        code_item("HAS OBS CONTEXT", SCOPE_OF_ACCUMULATION, STUDY,
                  [uid_item("HAS PROPERTIES", STUDY_INSTANCE_UID, study.study_uid)]),
        code_item("CONTAINS", DETECTOR_DATA_AVAILABLE, NO),
        code_item("CONTAINS", SOURCE_DATA_AVAILABLE, YES),
        # Positioner angles (TID 10003C) where the ledger holds a run's pose; no table positions.
        # The fixed source to reference point distance is given with each irradiation event.
        code_item("CONTAINS", MECHANICAL_DATA_AVAILABLE, YES if any(a is not None for a in angles) else NO),
        container("CONTAINS", ACCUMULATED, accumulated, "10002"),
        *[_irradiation_event(detail, study.event_uid(on["hash"]), study, a) for (on, _, detail), a in zip(runs, angles)],
        text_item("CONTAINS", COMMENT, f"Simulated fluoroscopy (fluorosim training session {session['id']}, "
                                       f"case '{session['case_title']}'); no patient was exposed."),
        code_item("CONTAINS", SOURCE_OF_DOSE_INFORMATION, AUTOMATED_DATA_COLLECTION),
    ]

    ds = Dataset()
    apply_common(ds, study)
    scheme = Dataset()
    scheme.CodingSchemeDesignator = LOCAL_SCHEME
    scheme.CodingSchemeName = "fluorosim local codes"
    scheme.CodingSchemeResponsibleOrganization = "fluorosim"
    ds.CodingSchemeIdentificationSequence = Sequence([scheme])
    ds.SOPClassUID = XRAY_RADIATION_DOSE_SR
    ds.SOPInstanceUID = study.report_uid
    ds.InstanceCreationDate, ds.InstanceCreationTime = ended.strftime("%Y%m%d"), ended.strftime("%H%M%S.%f")
    ds.SeriesDate, ds.SeriesTime = started.strftime("%Y%m%d"), started.strftime("%H%M%S.%f")
    ds.ContentDate, ds.ContentTime = ended.strftime("%Y%m%d"), ended.strftime("%H%M%S.%f")
    ds.Modality = "SR"
    ds.SeriesDescription = "Radiation Dose Information"
    ds.OperatorsName = person_name(study.operator)
    ds.SeriesInstanceUID = study.report_series_uid
    ds.SeriesNumber = 999
    ds.InstanceNumber = 1
    ds.ReferencedPerformedProcedureStepSequence = procedure_step_reference(study)
    ds.PerformedProcedureCodeSequence = Sequence([code(TRAINING_PROCEDURE)])
    ds.CompletionFlag = "COMPLETE"
    ds.VerificationFlag = "UNVERIFIED"
    ds.ValueType = "CONTAINER"
    ds.ConceptNameCodeSequence = Sequence([code(REPORT)])
    ds.ContinuityOfContent = "SEPARATE"
    template = Dataset()
    template.MappingResource = "DCMR"
    template.TemplateIdentifier = "10001"
    ds.ContentTemplateSequence = Sequence([template])
    ds.ContentSequence = Sequence(content)
    # The ledger's entry that ends the session, kept outside the ledger with the report (records.rdsr_anchor).
    rdsr_anchor.stamp(ds, events)
    return ds


def patient_of(case: CaseProfile) -> dict:
    """What a session records about its virtual patient (CaseProfile -> dict) for the reports."""
    return dict(case.patient.model_dump())


def equipment_of(fluoroscope: FluoroscopeProfile) -> dict:
    """The machine alone, for a session without an appliance profile (tests, benchmarks); the
    appliance records its identity too (records.identity.equipment_of)."""
    return {"manufacturer": fluoroscope.manufacturer, "model": fluoroscope.model, "serial": fluoroscope.name}
