"""The dose report's content tree, item by item, against PS3.16's templates as written: TID 10001
(the report), 1002 (the device observer), 10002/10004/10007 (accumulated dose), 10003 (each
irradiation event) and 1020 (the person administering). The values come from the hand-worked
session of test_export (three runs on the flat-panel profile); the relationship and value type
of every row are the standard's, not read from the writer."""

from __future__ import annotations

import datetime as dt
import json

import pytest
from test_export import DAY1, FLAT, RUNS, make_ledger, name

from appliance.records import rdsr
from appliance.records.ledger import Ledger

#: Concept name -> (relationship to its parent, value type), as the templates have them.
TEMPLATE_ROWS = {
    "Procedure reported": ("HAS CONCEPT MOD", "CODE"),
    "Has Intent": ("HAS CONCEPT MOD", "CODE"),
    "Observer Type": ("HAS OBS CONTEXT", "CODE"),
    "Device Observer UID": ("HAS OBS CONTEXT", "UIDREF"),
    "Device Observer Name": ("HAS OBS CONTEXT", "TEXT"),
    "Device Observer Manufacturer": ("HAS OBS CONTEXT", "TEXT"),
    "Device Observer Model Name": ("HAS OBS CONTEXT", "TEXT"),
    "Device Observer Serial Number": ("HAS OBS CONTEXT", "TEXT"),
    "Scope of Accumulation": ("HAS OBS CONTEXT", "CODE"),
    "Study Instance UID": ("HAS PROPERTIES", "UIDREF"),
    "X-Ray Detector Data Available": ("CONTAINS", "CODE"),
    "X-Ray Source Data Available": ("CONTAINS", "CODE"),
    "X-Ray Mechanical Data Available": ("CONTAINS", "CODE"),
    "Accumulated X-Ray Dose Data": ("CONTAINS", "CONTAINER"),
    "Acquisition Plane": ("HAS CONCEPT MOD", "CODE"),
    "Fluoro Dose Area Product Total": ("CONTAINS", "NUM"),
    "Fluoro Dose (RP) Total": ("CONTAINS", "NUM"),
    "Total Fluoro Time": ("CONTAINS", "NUM"),
    "Acquisition Dose Area Product Total": ("CONTAINS", "NUM"),
    "Acquisition Dose (RP) Total": ("CONTAINS", "NUM"),
    "Total Acquisition Time": ("CONTAINS", "NUM"),
    "Dose Area Product Total": ("CONTAINS", "NUM"),
    "Dose (RP) Total": ("CONTAINS", "NUM"),
    "Total Number of Radiographic Frames": ("CONTAINS", "NUM"),
    "Reference Point Definition": ("CONTAINS", "CODE"),
    "Irradiation Event X-Ray Data": ("CONTAINS", "CONTAINER"),
    "Irradiation Event UID": ("CONTAINS", "UIDREF"),
    "DateTime Started": ("CONTAINS", "DATETIME"),
    "Irradiation Event Type": ("CONTAINS", "CODE"),
    "Acquisition Protocol": ("CONTAINS", "TEXT"),
    "Dose Area Product": ("CONTAINS", "NUM"),
    "Dose (RP)": ("CONTAINS", "NUM"),
    "Distance Source to Reference Point": ("CONTAINS", "NUM"),
    "Fluoro Mode": ("CONTAINS", "CODE"),
    "Pulse Rate": ("CONTAINS", "NUM"),
    "Number of Pulses": ("CONTAINS", "NUM"),
    "Irradiation Duration": ("CONTAINS", "NUM"),
    "KVP": ("CONTAINS", "NUM"),
    "X-Ray Tube Current": ("CONTAINS", "NUM"),
    "Pulse Width": ("CONTAINS", "NUM"),
    "Focal Spot Size": ("CONTAINS", "NUM"),
    "Collimated Field Area": ("CONTAINS", "NUM"),
    "Person Name": ("CONTAINS", "PNAME"),
    "Person Role in Procedure": ("HAS PROPERTIES", "CODE"),
    "Organization Name": ("HAS PROPERTIES", "TEXT"),
    "Comment": ("CONTAINS", "TEXT"),
    "Source of Dose Information": ("CONTAINS", "CODE"),
    # The device type row (OpenREM files the report as fluoroscopy from its value); its relationship
    # is the one dciodvfy -profile IHEREM accepts in test_export.
    "Acquisition Device Type": ("CONTAINS", "CODE"),
}
#: Templates of the containers (TID numbers).
CONTAINER_TEMPLATES = {"Accumulated X-Ray Dose Data": "10002", "Irradiation Event X-Ray Data": "10003"}


@pytest.fixture(scope="module")
def rows(tmp_path_factory):
    path = tmp_path_factory.mktemp("rdsr") / "ledger.sqlite"
    make_ledger(path)
    with Ledger(path) as ledger:
        return ledger.session_rows(1)


def walk(items):
    for item in items:
        yield item
        yield from walk(item.get("ContentSequence", []))


def children(item) -> dict:
    out: dict = {}
    for c in item.ContentSequence:
        out.setdefault(name(c), []).append(c)
    return out


def number(item) -> tuple[float, str]:
    m = item.MeasuredValueSequence[0]
    # The decimal string and the binary value say the same, to the decimal's precision.
    assert float(m.NumericValue) == pytest.approx(float(m.FloatingPointValue), rel=1e-11, abs=1e-15)
    assert len(str(m.NumericValue)) <= 16
    unit = m.MeasurementUnitsCodeSequence[0]
    assert unit.CodingSchemeDesignator == "UCUM"
    return float(m.FloatingPointValue), unit.CodeValue


def test_every_row_has_the_templates_relationship_and_value_type(rows):
    ds = rdsr.session_report(*rows)
    seen = set()
    for item in walk(ds.ContentSequence):
        concept = name(item)
        assert concept in TEMPLATE_ROWS, concept
        assert (item.RelationshipType, item.ValueType) == TEMPLATE_ROWS[concept], concept
        code = item.ConceptNameCodeSequence[0]
        assert len(item.ConceptNameCodeSequence) == 1 and code.CodeValue and code.CodingSchemeDesignator
        if item.ValueType == "CONTAINER":
            assert item.ContinuityOfContent == "SEPARATE"
            (template,) = item.ContentTemplateSequence
            assert (template.MappingResource, template.TemplateIdentifier) == ("DCMR", CONTAINER_TEMPLATES[concept])
        if item.ValueType == "CODE":
            assert len(item.ConceptCodeSequence) == 1 and item.ConceptCodeSequence[0].CodeMeaning
        if item.ValueType == "NUM":
            number(item)
        seen.add(concept)
    assert seen == set(TEMPLATE_ROWS) - {"Organization Name"}      # no institution in this session's equipment


def test_root_header_and_flags(rows):
    session, events = rows
    ds = rdsr.session_report(session, events)
    assert (ds.ValueType, ds.ContinuityOfContent, ds.CompletionFlag, ds.VerificationFlag) == \
        ("CONTAINER", "SEPARATE", "COMPLETE", "UNVERIFIED")
    assert name(ds) == "X-Ray Radiation Dose Report" and ds.ConceptNameCodeSequence[0].CodeValue == "113701"
    (template,) = ds.ContentTemplateSequence
    assert (template.MappingResource, template.TemplateIdentifier) == ("DCMR", "10001")
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.88.67" and ds.Modality == "SR"
    assert ds.SeriesDescription == "Radiation Dose Information"
    # Started at DAY1 = 2023-11-14 22:13:20 UTC, ended 60 s later; times as DICOM TM in UTC.
    assert (ds.SeriesDate, ds.SeriesTime) == ("20231114", "221320.000000")
    assert (ds.ContentDate, ds.ContentTime) == ("20231114", "221420.000000")
    assert (ds.InstanceCreationDate, ds.InstanceCreationTime) == ("20231114", "221420.000000")
    assert str(ds.OperatorsName) == "Trainee^Dr"
    assert ds.PerformedProcedureCodeSequence[0].CodeMeaning and ds.ReferencedPerformedProcedureStepSequence
    (scheme,) = ds.CodingSchemeIdentificationSequence
    assert scheme.CodingSchemeDesignator == rdsr.LOCAL_SCHEME and scheme.CodingSchemeName == "fluorosim local codes"
    assert scheme.CodingSchemeResponsibleOrganization == "fluorosim"
    # The report's own series, numbered after the images' (series 1, records.saved_images), as
    # viewers list the dose report last; it is that series' one instance.
    assert (ds.SeriesNumber, ds.InstanceNumber) == (999, 1)
    top = children(ds)
    assert [c.ConceptCodeSequence[0].CodeMeaning for c in top["X-Ray Detector Data Available"]] == ["No"]
    assert [c.ConceptCodeSequence[0].CodeMeaning for c in top["X-Ray Source Data Available"]] == ["Yes"]
    assert [c.ConceptCodeSequence[0].CodeMeaning for c in top["X-Ray Mechanical Data Available"]] == ["No"]
    assert top["Source of Dose Information"][0].ConceptCodeSequence[0].CodeMeaning == "Automated Data Collection"
    (comment,) = top["Comment"]
    assert comment.TextValue == ("Simulated fluoroscopy (fluorosim training session 1, case 'Child torso'); "
                                 "no patient was exposed.")
    (scope,) = top["Scope of Accumulation"]
    assert scope.ConceptCodeSequence[0].CodeMeaning == "Study"
    assert children(scope)["Study Instance UID"][0].UID == ds.StudyInstanceUID
    (procedure,) = top["Procedure reported"]
    assert children(procedure)["Has Intent"][0].ConceptCodeSequence[0].CodeMeaning == "Diagnostic Intent"


def test_device_observer_names_the_machine_and_cuts_long_names(rows):
    session, events = rows
    top = children(rdsr.session_report(session, events))
    assert top["Observer Type"][0].ConceptCodeSequence[0].CodeMeaning == "Device"
    assert top["Device Observer Name"][0].TextValue == FLAT.name           # no station name: the fluoroscope
    assert top["Device Observer Manufacturer"][0].TextValue == FLAT.manufacturer
    assert top["Device Observer Model Name"][0].TextValue == FLAT.model
    assert top["Device Observer Serial Number"][0].TextValue == "SN-1"
    assert top["Device Observer UID"][0].UID
    equipment = {"manufacturer": "M" * 70, "model": "m" * 65, "serial": "S" * 80, "station_name": "X" * 66,
                 "institution": "I" * 90}
    start = next(e for e in events if e["kind"] == "session_start")
    detail = json.loads(start["detail"]) if isinstance(start["detail"], str) else dict(start["detail"])
    detail["equipment"] = equipment
    changed = [dict(e, detail=json.dumps(detail)) if e is start else e for e in events]
    top = children(rdsr.session_report(session, changed))
    assert [top[k][0].TextValue for k in ("Device Observer Name", "Device Observer Manufacturer",
                                          "Device Observer Model Name", "Device Observer Serial Number")] == \
        ["X" * 64, "M" * 64, "m" * 64, "S" * 64]
    person = top["Irradiation Event X-Ray Data"][0]
    (who,) = children(person)["Person Name"]
    properties = children(who)
    (organization,) = properties["Organization Name"]
    assert organization.TextValue == "I" * 64
    assert (organization.RelationshipType, organization.ValueType) == TEMPLATE_ROWS["Organization Name"]
    assert properties["Person Role in Procedure"][0].ConceptCodeSequence[0].CodeMeaning == "Irradiation Administering"


def test_events_carry_their_run_in_the_reports_units(rows):
    session, events = rows
    top = children(rdsr.session_report(session, events))
    runs = top["Irradiation Event X-Ray Data"]
    assert len(runs) == len(RUNS)
    starts = [1.0, 20.0, 50.0]           # pedal down in make_ledger (s after the session's start)
    for event, (duration, kerma, area), start in zip(runs, RUNS, starts):
        rows_ = children(event)
        assert rows_["Acquisition Plane"][0].ConceptCodeSequence[0].CodeMeaning == "Single Plane"
        when = dt.datetime.fromtimestamp(DAY1 + start, tz=dt.UTC).strftime("%Y%m%d%H%M%S.%f")
        assert rows_["DateTime Started"][0].DateTime == when
        assert number(rows_["Irradiation Duration"][0]) == (pytest.approx(duration), "s")
        assert number(rows_["Dose (RP)"][0]) == (pytest.approx(kerma / 1000, rel=1e-9), "Gy")
        assert number(rows_["Dose Area Product"][0]) == (pytest.approx(kerma / 1000 * area / 1e4, rel=1e-9), "Gy.m2")
        assert number(rows_["Collimated Field Area"][0]) == (pytest.approx(area / 1e4, rel=1e-9), "m2")
        assert number(rows_["Distance Source to Reference Point"][0]) == (pytest.approx(600.0), "mm")
        assert rows_["Reference Point Definition"][0].ConceptCodeSequence[0].CodeMeaning == \
            "15cm from Isocenter toward Source"
        (who,) = rows_["Person Name"]
        assert str(who.PersonName) == "Trainee^Dr"
    protocols = [children(e)["Acquisition Protocol"][0].TextValue for e in runs]
    assert protocols[0].endswith("zoom 1") and protocols[1].endswith("zoom 2") and protocols[2].startswith("pulsed")
    pulsed = children(runs[2])
    assert number(pulsed["Number of Pulses"][0]) == (45.0, "{pulses}")
    assert number(pulsed["Pulse Rate"][0]) == (pytest.approx(15.0), "{pulse}/s")
    assert pulsed["Fluoro Mode"][0].ConceptCodeSequence[0].CodeMeaning == "Pulsed"
    assert children(runs[0])["Fluoro Mode"][0].ConceptCodeSequence[0].CodeMeaning == "Continuous"
    acc = children(top["Accumulated X-Ray Dose Data"][0])
    assert number(acc["Total Number of Radiographic Frames"][0]) == (0.0, "1")
    for row in ("Acquisition Dose Area Product Total", "Acquisition Dose (RP) Total", "Total Acquisition Time"):
        assert number(acc[row][0])[0] == 0.0
    assert number(acc["Dose (RP) Total"][0]) == (pytest.approx(sum(r[1] for r in RUNS) / 1000, rel=1e-9), "Gy")


def test_times_are_utc_whatever_the_machines_zone(rows, monkeypatch):
    import time

    session, events = rows
    monkeypatch.setenv("TZ", "Pacific/Auckland")        # +13:00 in November: a local time would read 11:13
    time.tzset()
    try:
        ds = rdsr.session_report(session, events)
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()
    assert (ds.SeriesDate, ds.SeriesTime) == ("20231114", "221320.000000")
    first = children(children(ds)["Irradiation Event X-Ray Data"][0])
    assert first["DateTime Started"][0].DateTime == "20231114221321.000000"


def test_device_observer_name_falls_back_to_the_product(rows):
    session, events = rows
    nameless = dict(session, fluoroscope="")
    assert children(rdsr.session_report(nameless, events))["Device Observer Name"][0].TextValue == "fluorosim"


def test_identity_of_a_case_and_a_machine():
    from appliance.config.case import CaseProfile

    case = CaseProfile(title="t", phases=[{"volume": "ct.mha", "time_s": 0}],
                       patient={"sex": "F", "age_years": 6, "weight_kg": 21.0, "height_m": 1.16})
    assert rdsr.patient_of(case) == {"sex": "F", "age_years": 6, "weight_kg": 21.0, "height_m": 1.16}
    assert rdsr.equipment_of(FLAT) == {"manufacturer": FLAT.manufacturer, "model": FLAT.model, "serial": FLAT.name}


def test_a_pulsed_run_recorded_without_its_pulse_count_reports_none(rows):
    # A ledger row from before runs counted their pulses: the report says 0 pulses, not a guess.
    session, events = rows
    offs = [e for e in events if e["kind"] == "fluoro_off"]
    detail = json.loads(offs[2]["detail"])
    assert detail["pulse_rate_per_s"] and detail.pop("pulses") == 45
    older = [dict(e, detail=json.dumps(detail)) if e is offs[2] else e for e in events]
    pulsed = children(children(rdsr.session_report(session, older))["Irradiation Event X-Ray Data"][2])
    assert number(pulsed["Number of Pulses"][0]) == (0.0, "{pulses}")


def with_run_detail(events, index, **changes):
    offs = [e for e in events if e["kind"] == "fluoro_off"]
    detail = {**json.loads(offs[index]["detail"]), **changes}
    return [dict(e, detail=json.dumps(detail)) if e is offs[index] else e for e in events]


def test_a_run_cut_off_by_a_crash_says_so_and_continuous_runs_carry_no_pulse_width(rows):
    session, events = rows
    changed = with_run_detail(events, 0, reason="recovered", pulse_width_ms=8.0)
    first = children(children(rdsr.session_report(session, changed))["Irradiation Event X-Ray Data"][0])
    (comment,) = first["Comment"]
    assert comment.TextValue == ("Run cut off by a power loss or crash; values cover the exposure recorded before it.")
    assert (comment.RelationshipType, comment.ValueType) == TEMPLATE_ROWS["Comment"]
    assert "Pulse Width" not in first              # a continuous run has no pulses, whatever the record holds
    plain = children(children(rdsr.session_report(session, events))["Irradiation Event X-Ray Data"][0])
    assert "Comment" not in plain


def test_a_session_never_ended_dates_its_report_at_its_start(rows):
    session, events = rows
    ds = rdsr.session_report(dict(session, ended_wall=None), events)
    assert (ds.ContentDate, ds.ContentTime) == ("20231114", "221320.000000")
    assert (ds.InstanceCreationDate, ds.InstanceCreationTime) == ("20231114", "221320.000000")


def test_the_report_carries_the_ledger_entry_that_ended_its_session(rows):
    # records.rdsr_anchor: the count and hash of the session's last ledger row, as the ledger holds them.
    from appliance.records import rdsr_anchor

    session, events = rows
    last = events[-1]
    assert last["kind"] == "session_end"
    assert rdsr_anchor.read(rdsr.session_report(session, events)) == {"count": last["id"], "hash": last["hash"]}
