"""Positioner angles of saved images from the pose of the C-arm to the patient, against views
whose angles follow from the anatomy by hand: the patient's LPS frame has +x to the left,
+y posterior, +z to the head; the beam runs from the focal spot to the detector."""

from __future__ import annotations

import math

import numpy as np
import pydicom
import pytest
from dicom_session import record_session
from teaching_script import pose
from test_rdsr_content import children, number

from appliance.geometry import rotation_about
from appliance.records.positioner import positioner_angles

C30, S30 = math.sqrt(3) / 2, 0.5
C20, S20 = math.cos(math.radians(20)), math.sin(math.radians(20))


@pytest.mark.parametrize("view, beam, angles", [
    ("AP: detector over the chest", (0, -1, 0), (0.0, 0.0)),
    ("PA: detector under the table", (0, 1, 0), (180.0, 0.0)),
    ("left lateral: detector at the patient's left", (1, 0, 0), (90.0, 0.0)),
    ("right lateral", (-1, 0, 0), (-90.0, 0.0)),
    ("LAO 45", (1, -1, 0), (45.0, 0.0)),
    ("RAO 30", (-S30, -C30, 0), (-30.0, 0.0)),
    ("cranial 30: detector tilted toward the head", (0, -C30, S30), (0.0, 30.0)),
    ("caudal 30", (0, -C30, -S30), (0.0, -30.0)),
    ("LAO 30 CRA 20", (S30 * C20, -C30 * C20, S20), (30.0, 20.0)),
])
def test_angles_of_known_views(view, beam, angles):
    T = pose(beam, (12.0, -40.0, 250.0))      # through any point: the angles are the direction's
    assert positioner_angles(T) == pytest.approx(angles, abs=1e-9), view


def test_rolling_the_detector_about_the_beam_changes_nothing():
    T = pose((S30 * C20, -C30 * C20, S20), (0, 0, 0))
    roll = np.eye(4)
    roll[:3, :3] = rotation_about([0, 0, 1], math.radians(70))   # about the xray frame's beam axis
    assert positioner_angles(roll @ T) == pytest.approx((30.0, 20.0), abs=1e-9)


def test_the_saved_image_carries_the_angles_of_its_pose(tmp_path):
    # dicom_session saves its images at LAO 30 CRA 20 (its POSE).
    session = record_session(tmp_path / "var")
    for path in session.images:
        ds = pydicom.dcmread(path)
        assert (float(ds.PositionerPrimaryAngle), float(ds.PositionerSecondaryAngle)) == (30.0, 20.0)


def test_the_dose_reports_events_carry_the_angles_of_their_runs(tmp_path):
    from teaching_script import II, Session

    from appliance.records import rdsr
    from appliance.records.ledger import Ledger

    with Ledger(tmp_path / "ledger.sqlite") as ledger:
        sid = ledger.start_session("trainee", "child", II.name, 1.7e9, t_monotonic=0.0)
        s = Session(ledger)
        s.expose(1.0, 2.0, pose((S30 * C20, -C30 * C20, S20), (0, 0, 0)))     # LAO 30 CRA 20
        s.expose(3.0, 4.0, pose((-1, -1, 0), (0, 0, 50)))                     # RAO 45
        s.advance(5.0)
        ledger.record(s.console.end(5.0))
        ledger.end_session(1.7e9 + 5.0)
        ds = rdsr.session_report(*ledger.session_rows(sid))

    def meaning(item):
        return item.ConceptNameCodeSequence[0].CodeMeaning

    events = [i for i in ds.ContentSequence if meaning(i) == "Irradiation Event X-Ray Data"]
    got = [tuple(float(c.MeasuredValueSequence[0].NumericValue) for c in e.ContentSequence
                 if meaning(c) in ("Positioner Primary Angle", "Positioner Secondary Angle")) for e in events]
    assert got == [(30.0, 20.0), (-45.0, 0.0)]
    mechanical = next(i for i in ds.ContentSequence if meaning(i) == "X-Ray Mechanical Data Available")
    assert mechanical.ConceptCodeSequence[0].CodeMeaning == "Yes"


def test_the_dose_reports_angles_are_rows_of_the_event_in_degrees_to_a_tenth(tmp_path):
    # A beam at LAO 12.345 CAU 7.891 (the module docstring's d from the two angles): the report
    # gives each to a tenth of a degree, 12.3 and -7.9, as NUM rows the event CONTAINS, beside
    # its dose rows (TID 10003 with 10003C).
    from teaching_script import II, Session

    from appliance.records import rdsr
    from appliance.records.ledger import Ledger

    p, s = math.radians(12.345), math.radians(-7.891)
    beam = (math.sin(p) * math.cos(s), -math.cos(p) * math.cos(s), math.sin(s))
    with Ledger(tmp_path / "ledger.sqlite") as ledger:
        sid = ledger.start_session("trainee", "child", II.name, 1.7e9, t_monotonic=0.0)
        session = Session(ledger)
        session.expose(1.0, 2.0, pose(beam, (0, 0, 0)))
        session.advance(3.0)
        ledger.record(session.console.end(3.0))
        ledger.end_session(1.7e9 + 3.0)
        (event,) = children(rdsr.session_report(*ledger.session_rows(sid)))["Irradiation Event X-Ray Data"]
    rows = children(event)
    for concept, expected in (("Positioner Primary Angle", 12.3), ("Positioner Secondary Angle", -7.9)):
        (row,) = rows[concept]
        assert (row.RelationshipType, row.ValueType) == ("CONTAINS", "NUM")      # TID 10003C, as PS3.16 has it
        assert number(row) == (pytest.approx(expected, abs=1e-12), "deg")
    assert {"Irradiation Event UID", "DateTime Started", "Dose Area Product", "Dose (RP)", "Fluoro Mode",
            "Irradiation Duration"} <= set(rows)
