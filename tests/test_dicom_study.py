"""One study per session, a device identity of its own, and DCMTK/dicom3tools conformance
of a session's dose report and images together."""

import re
import shutil
import subprocess

import pydicom
import pytest
from dicom_session import IDENTITY, II, record_session

from appliance.errors import FluorosimError
from appliance.records.identity import device_uid, read_device_uid
from appliance.records.study import person_name

UID = re.compile(r"^(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))+$")
needs_dcmtk = pytest.mark.skipif(shutil.which("dsrdump") is None or shutil.which("dcentvfy") is None,
                                 reason="dsrdump/dcentvfy (Debian package dcmtk) are not installed; `make test` installs them")
needs_dciodvfy = pytest.mark.skipif(shutil.which("dciodvfy") is None,
                                    reason="dciodvfy (Debian package dicom3tools) is not installed; `make test` installs it")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return record_session(tmp_path_factory.mktemp("session"))


def name(item):
    return item.ConceptNameCodeSequence[0].CodeMeaning


def events_of(report):
    return [i for i in report.ContentSequence if name(i) == "Irradiation Event X-Ray Data"]


def child(event, meaning):
    found = [c for c in event.ContentSequence if name(c) == meaning]
    assert len(found) == 1, meaning
    return found[0]


def test_report_and_images_form_one_study(session):
    report = pydicom.dcmread(session.report)
    images = [pydicom.dcmread(p) for p in session.images]
    assert len(images) == 3
    for ds in images:
        for keyword in ("StudyInstanceUID", "StudyDate", "StudyTime", "StudyID", "PatientID", "IssuerOfPatientID",
                        "PatientName", "PatientSex", "PatientAge", "InstitutionName", "DeviceSerialNumber", "StationName"):
            assert ds[keyword].value == report[keyword].value, keyword
        assert ds.IssuerOfPatientIDQualifiersSequence[0].UniversalEntityID == \
            report.IssuerOfPatientIDQualifiersSequence[0].UniversalEntityID
        assert ds.ReferencedPerformedProcedureStepSequence[0].ReferencedSOPInstanceUID == \
            report.ReferencedPerformedProcedureStepSequence[0].ReferencedSOPInstanceUID
        # No MPPS is sent (study.procedure_step_uid): the images describe the step for a system that
        # creates it later (PS3.17 J.2.2): its ID and start, the session's.
        assert (ds.PerformedProcedureStepID, ds.PerformedProcedureStepStartDate, ds.PerformedProcedureStepStartTime) == \
            (report.StudyID, "20231114", report.StudyTime)
    # The session started at 22:13:20 UTC: the study and the image series start then.
    assert report.StudyDate == "20231114" and report.StudyTime.startswith("221320")
    assert {(ds.SeriesInstanceUID, ds.SeriesDate, ds.SeriesTime) for ds in images} == \
        {(images[0].SeriesInstanceUID, "20231114", report.StudyTime)}
    # Acquisition times are the saves' own: 2.5 s, 5 s and 14 s into the session.
    assert [ds.AcquisitionTime[:6] for ds in images] == ["221322", "221325", "221334"]
    # The scope of accumulation in the report names the same study.
    scope = next(i for i in report.ContentSequence if name(i) == "Scope of Accumulation")
    assert scope.ContentSequence[0].UID == report.StudyInstanceUID
    uids = [report.SOPInstanceUID, report.SeriesInstanceUID, report.StudyInstanceUID, images[0].SeriesInstanceUID,
            *(ds.SOPInstanceUID for ds in images)]
    assert len(set(uids)) == len(uids) and all(UID.match(u) and len(u) <= 64 for u in uids)


def test_each_image_names_the_irradiation_event_of_its_run(session):
    report = pydicom.dcmread(session.report)
    event_uids = [child(e, "Irradiation Event UID").UID for e in events_of(report)]
    assert len(event_uids) == 2 and len(set(event_uids)) == 2
    images = [pydicom.dcmread(p) for p in session.images]
    # Ground truth of the script: saves 1 (live) and 2 (held) show run 1, save 3 shows run 2.
    assert [ds.IrradiationEventUID for ds in images] == [event_uids[run] for run in session.saved_after_run]


def test_report_rows_registries_read(session):
    report = pydicom.dcmread(session.report)
    for event in events_of(report):
        # Generic II C-arm: source to isocentre 620 mm, reference point 150 mm toward the source.
        distance = child(event, "Distance Source to Reference Point").MeasuredValueSequence[0]
        assert float(distance.NumericValue) == 470.0 and distance.MeasurementUnitsCodeSequence[0].CodeValue == "mm"
        person = child(event, "Person Name")
        assert person.ValueType == "PNAME" and person.PersonName == "Trainee^Jane Q"
        role = next(c for c in person.ContentSequence if name(c) == "Person Role in Procedure")
        assert role.ConceptCodeSequence[0].CodeMeaning == "Irradiation Administering"
        started = child(event, "DateTime Started").DateTime
        assert re.fullmatch(r"\d{14}\.\d{6}", started), started       # no offset: the header's TimezoneOffsetFromUTC holds
    assert report.TimezoneOffsetFromUTC == "+0000"
    assert report.ProcedureCodeSequence[0].CodeMeaning == "Simulated fluoroscopy training session"
    assert report.OperatorsName == "Trainee^Jane Q"
    assert (report.InstitutionName, report.InstitutionalDepartmentName, report.StationName, report.DeviceSerialNumber) == \
        (IDENTITY.institution, IDENTITY.department, IDENTITY.station_name, IDENTITY.serial_number)
    observer = {name(i): i for i in report.ContentSequence if i.RelationshipType == "HAS OBS CONTEXT"}
    assert observer["Device Observer UID"].UID == read_device_uid(session.ledger.parent / "device-identity")
    assert observer["Device Observer Serial Number"].TextValue == "FS-0042"
    assert observer["Device Observer Name"].TextValue == "FLUOROSIM-3"
    assert report.IssuerOfPatientIDQualifiersSequence[0].UniversalEntityID == observer["Device Observer UID"].UID


# Attributes the standard makes Type 2 (present, may be empty) in these objects; anything else
# empty would be an empty Type 1 or Type 3.
TYPE_2 = {"PatientBirthDate", "AccessionNumber", "ReferringPhysicianName", "PatientOrientation", "ExposureTime"}


def test_no_empty_attributes_other_than_type_2(session):
    for path in [session.report, *session.images]:
        ds = pydicom.dcmread(path)
        empty = sorted({e.keyword for e in ds.iterall() if e.value in ("", None, b"") or
                        (e.VR == "SQ" and len(e.value) == 0)} - TYPE_2)
        assert not empty, (path.name, empty)
        assert "Laterality" not in ds


def test_uids_are_stable_for_a_session_and_differ_between_appliances(tmp_path, session):
    again = record_session(tmp_path / "another-appliance")
    # Another appliance (its own identity file) recording the same script at the same instant.
    assert pydicom.dcmread(again.report).StudyInstanceUID != pydicom.dcmread(session.report).StudyInstanceUID
    # Rebuilding one session's report from its ledger gives the same bytes (same UIDs on every retry).
    from appliance.records import dicom, rdsr
    from appliance.records.ledger import Ledger
    with Ledger(session.ledger) as ledger:
        rebuilt = dicom.encode(rdsr.session_report(*ledger.session_rows(session.session_id)))
    assert rebuilt == session.report_bytes


@needs_dcmtk
def test_dcmtk_reads_the_report_and_finds_the_study_consistent(session):
    dump = subprocess.run(["dsrdump", str(session.report)], capture_output=True, text=True)
    assert dump.returncode == 0 and "violates" not in dump.stderr + dump.stdout, dump.stderr
    assert "Trainee^Jane Q" in dump.stdout and "Distance Source to Reference Point" in dump.stdout
    files = [str(p) for p in [session.report, *session.images]]
    check = subprocess.run(["dcentvfy", *files], capture_output=True, text=True)
    output = check.stdout + check.stderr
    assert check.returncode == 0 and not [line for line in output.splitlines() if line.startswith("Error")], output


@needs_dciodvfy
def test_dciodvfy_finds_no_errors(session):
    for path, profile in [(session.report, ["-profile", "IHEREM"]), *((p, []) for p in session.images)]:
        result = subprocess.run(["dciodvfy", *profile, str(path)], capture_output=True, text=True)
        output = result.stdout + result.stderr
        assert not [line for line in output.splitlines() if line.startswith("Error")], (path.name, output)


def test_device_uid_is_made_once_and_kept(tmp_path):
    path = tmp_path / "etc" / "device-identity"
    first = device_uid(path)
    assert first.startswith("2.25.") and UID.match(first) and len(first) <= 64
    assert device_uid(path) == first and path.read_text().strip() == first
    assert device_uid(tmp_path / "other") != first
    path.write_text("not-a-uid\n")
    with pytest.raises(FluorosimError, match=r"device-identity: 'not-a-uid' is not a DICOM UID; restore"):
        device_uid(path)
    with pytest.raises(FluorosimError, match="run 'fluorosim dicom identity'"):
        device_uid(tmp_path / "missing", create=False)


@pytest.mark.parametrize("operator, expected", [
    ("Jane Doe", "Doe^Jane"), ("Doe, Jane", "Doe^Jane"), ("Mary Ann  Smith", "Smith^Mary Ann"),
    ("trainee", "trainee"), ("Doe^Jane", "Doe^Jane"),
])
def test_operator_as_family_given(operator, expected):
    assert person_name(operator) == expected


def test_fluoroscope_profile_is_not_the_device(session):
    # The generic profile's name must not stand in for the serial number or the device UID.
    report = pydicom.dcmread(session.report)
    assert II.name not in (report.DeviceSerialNumber, report.StationName)

