"""Admin export: CSV/JSON totals against hand-worked sums, DICOM RDSR through dciodvfy."""

import csv
import json
import os
import resource
import shutil
import signal
import subprocess
from pathlib import Path

import pydicom
import pytest
from pydicom.sr._concepts_dict import concepts

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.console.state import Console
from appliance.errors import FluorosimError
from appliance.records import export as export_module
from appliance.records.ledger import Ledger, open_readonly
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
FLAT = load_profile(REPO / "configs/fluoroscopes/generic-flat-detector.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
DAY1 = 1_700_000_000.0          # 2023-11-14T22:13:20Z
DAY2 = DAY1 + 86400.0

# Hand-worked: flat panel, reference point at 750 - 150 = 600 mm of a 1100 mm SID, so an
# area at the detector scales by (600/1100)^2 at the reference point. Rates from the profile.
SCALE = (600.0 / 1100.0) ** 2
RUNS = [  # (duration s, kerma mGy, field area at the reference point cm^2)
    (10.0, 6.0 * 10 / 60, 30.0 * 30.0 * SCALE),          # zoom 1 (300 mm), continuous 6 mGy/min, open
    (20.0, 11.16 * 20 / 60, 20.0 * 19.0 * SCALE),        # zoom 2 (220 mm), continuous 11.16, blades 200 x 190 mm
    (3.0, 45 * 5.58 / 60 / 15, 20.0 * 19.0 * SCALE),     # pulsed-15 at zoom 2: 5.58 mGy/min, pulses at k/15 s, k = 0..44
]
TOTAL_TIME = sum(r[0] for r in RUNS)
TOTAL_KERMA = sum(r[1] for r in RUNS)
TOTAL_DAP = sum(r[1] / 1000 * r[2] for r in RUNS)


def press(console, t, key, pressed=True):
    return console.handle(InputEvent(t, "keypad", key, pressed))


def make_ledger(path: Path) -> None:
    with Ledger(path) as ledger:
        console = Console(FLAT, KEYMAP, t0=0.0)
        ledger.start_session("Dr Trainee", "Child torso", FLAT.name, t_wall=DAY1, t_monotonic=0.0,
                             equipment={"manufacturer": FLAT.manufacturer, "model": FLAT.model, "serial": "SN-1"},
                             patient={"sex": "O", "age_years": 6, "weight_kg": 21.0, "height_m": 1.16})
        ev = press(console, 1.0, "pedal") + console.tick(5.0) + press(console, 11.0, "pedal", False)
        ev += press(console, 12.0, "KEY_KP2")
        ev += press(console, 13.0, "KEY_KP9") + press(console, 13.1, "KEY_KP9")
        ev += press(console, 14.0, "KEY_KP6") + press(console, 14.1, "KEY_KP6") + press(console, 14.2, "KEY_KP6")
        ev += press(console, 20.0, "pedal") + console.tick(30.0) + press(console, 40.0, "pedal", False)
        ev += press(console, 41.0, "KEY_KP5")
        ev += press(console, 50.0, "pedal") + console.tick(51.5) + press(console, 53.0, "pedal", False)
        ev += press(console, 54.0, "KEY_KPPLUS")
        ledger.record(ev)
        ledger.end_session(DAY1 + 60.0)
        console = Console(FLAT, KEYMAP, t0=0.0)
        ledger.start_session("Dr Other", "Child torso", FLAT.name, t_wall=DAY2, t_monotonic=0.0)
        ledger.record(press(console, 1.0, "pedal") + press(console, 2.0, "pedal", False))
        ledger.end_session(DAY2 + 10.0)


@pytest.fixture(scope="module")
def ledger_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("ledger") / "ledger.sqlite"
    make_ledger(path)
    return path


def do_export(ledger_file, fmt, out, since="2023-11-14T00:00:00Z", until="2023-11-15T00:00:00Z"):
    conn = open_readonly(ledger_file)
    try:
        return export_module.export(conn, export_module.parse_when(since), export_module.parse_when(until, end=True),
                                    fmt, out)
    finally:
        conn.close()


def test_csv_totals_equal_hand_computed_sums(ledger_file, tmp_path):
    written, _ = do_export(ledger_file, "csv", tmp_path / "out")
    assert sorted(p.name for p in written) == ["events.csv", "sessions.csv"]
    with open(tmp_path / "out/sessions.csv", newline="") as f:
        sessions = list(csv.DictReader(f))
    assert len(sessions) == 1                      # the second session is the next day
    s = sessions[0]
    assert s["operator"] == "Dr Trainee" and s["end_reason"] == "ended" and s["started_utc"] == "2023-11-14T22:13:20.000Z"
    assert float(s["fluoro_time_s"]) == pytest.approx(TOTAL_TIME, abs=1e-9)
    assert float(s["fluoro_time_min"]) == pytest.approx(TOTAL_TIME / 60, abs=1e-9)
    assert float(s["air_kerma_mgy"]) == pytest.approx(TOTAL_KERMA, rel=1e-12)
    assert float(s["dap_gy_cm2"]) == pytest.approx(TOTAL_DAP, rel=1e-12)
    assert (int(s["runs"]), int(s["saves"]), int(s["alarms"])) == (3, 1, 0)
    with open(tmp_path / "out/events.csv", newline="") as f:
        events = list(csv.DictReader(f))
    assert sum(float(e["d_air_kerma_mgy"]) for e in events) == pytest.approx(TOTAL_KERMA, rel=1e-12)
    assert sum(float(e["d_dap_gy_cm2"]) for e in events) == pytest.approx(TOTAL_DAP, rel=1e-12)
    offs = [json.loads(e["detail"]) for e in events if e["kind"] == "fluoro_off"]
    assert [o["duration_s"] for o in offs] == pytest.approx([r[0] for r in RUNS])
    assert [o["air_kerma_mgy"] for o in offs] == pytest.approx([r[1] for r in RUNS])
    assert [o["pulses"] for o in offs] == [0, 0, 45]


def test_json_holds_sessions_with_their_events(ledger_file, tmp_path):
    do_export(ledger_file, "json", tmp_path / "out", since="2023-11-01", until="2023-11-30")
    doc = json.loads((tmp_path / "out/ledger.json").read_text())
    assert doc["chain"]["ok"] and len(doc["sessions"]) == 2
    first = doc["sessions"][0]
    assert first["air_kerma_mgy"] == pytest.approx(TOTAL_KERMA)
    assert first["events"][0]["kind"] == "session_start" and first["events"][-1]["kind"] == "session_end"
    assert first["events"][0]["detail"]["equipment"]["serial"] == "SN-1"


def walk(items, depth=0):
    for item in items:
        yield item, depth
        if "ContentSequence" in item:
            yield from walk(item.ContentSequence, depth + 1)


def name(item):
    return item.ConceptNameCodeSequence[0].CodeMeaning


def num(items, meaning):
    found = [i for i in items if i.ValueType == "NUM" and name(i) == meaning]
    assert len(found) == 1, meaning
    measured = found[0].MeasuredValueSequence[0]
    return float(measured.NumericValue), measured.MeasurementUnitsCodeSequence[0].CodeValue


@pytest.mark.skipif(shutil.which("dciodvfy") is None,
                    reason="dciodvfy (Debian package dicom3tools) is not installed; `make test` installs it")
def test_rdsr_passes_dciodvfy_iherem(ledger_file, tmp_path):
    written, notes = do_export(ledger_file, "rdsr", tmp_path / "out")
    assert len(written) == 1 and not notes
    result = subprocess.run(["dciodvfy", "-profile", "IHEREM", str(written[0])], capture_output=True, text=True)
    output = result.stdout + result.stderr
    errors = [line for line in output.splitlines() if line.startswith("Error")]
    assert not errors, output


def test_rdsr_carries_the_runs_worked_by_hand(ledger_file, tmp_path):
    # Read with pydicom on every machine; dciodvfy's conformance check above is an extra.
    written, notes = do_export(ledger_file, "rdsr", tmp_path / "out")
    assert len(written) == 1 and not notes
    ds = pydicom.dcmread(written[0])
    assert ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.88.67" and ds.Modality == "SR"
    assert name(ds) == "X-Ray Radiation Dose Report" and ds.ContentTemplateSequence[0].TemplateIdentifier == "10001"
    top = list(ds.ContentSequence)
    device_type = [i for i in top if name(i) == "Acquisition Device Type"]
    assert "Fluoroscopy-Guided" in device_type[0].ConceptCodeSequence[0].CodeMeaning
    assert [i.ConceptCodeSequence[0].CodeMeaning for i in top if name(i) == "Procedure reported"] == ["Projection X-Ray"]
    accumulated = [i for i in top if name(i) == "Accumulated X-Ray Dose Data"]
    assert len(accumulated) == 1
    acc = list(accumulated[0].ContentSequence)
    assert num(acc, "Total Fluoro Time") == (pytest.approx(TOTAL_TIME), "s")
    assert num(acc, "Fluoro Dose Area Product Total") == (pytest.approx(TOTAL_DAP / 1e4, rel=1e-9), "Gy.m2")
    assert num(acc, "Dose Area Product Total")[0] == pytest.approx(TOTAL_DAP / 1e4, rel=1e-9)
    assert num(acc, "Fluoro Dose (RP) Total") == (pytest.approx(TOTAL_KERMA / 1000, rel=1e-9), "Gy")
    events = [i for i in top if name(i) == "Irradiation Event X-Ray Data"]
    assert len(events) == len(RUNS)
    uids = [next(c.UID for c in e.ContentSequence if name(c) == "Irradiation Event UID") for e in events]
    assert len(set(uids)) == len(RUNS)
    for event, (duration, kerma, area) in zip(events, RUNS):
        items = list(event.ContentSequence)
        assert [c.ConceptCodeSequence[0].CodeMeaning for c in items if name(c) == "Irradiation Event Type"] == ["Fluoroscopy"]
        assert num(items, "Irradiation Duration")[0] == pytest.approx(duration)
        assert num(items, "Dose (RP)")[0] == pytest.approx(kerma / 1000, rel=1e-9)
        assert num(items, "Dose Area Product")[0] == pytest.approx(kerma / 1000 * area / 1e4, rel=1e-9)
        assert num(items, "Collimated Field Area") == (pytest.approx(area / 1e4, rel=1e-9), "m2")
    assert num(list(events[2].ContentSequence), "Number of Pulses")[0] == 45
    # The technique of each run, as the flat-panel profile states it (70 kV, 3.0 mA, 0.4 mm
    # focal spot, 8 ms pulses at 15 per second), with the units a registry reads.
    for event in events:
        items = list(event.ContentSequence)
        assert num(items, "KVP") == (pytest.approx(70.0), "kV")
        assert num(items, "X-Ray Tube Current") == (pytest.approx(3.0), "mA")
        assert num(items, "Focal Spot Size") == (pytest.approx(0.4), "mm")
    pulsed = list(events[2].ContentSequence)
    assert num(pulsed, "Pulse Rate") == (pytest.approx(15.0), "{pulse}/s")
    assert num(pulsed, "Pulse Width") == (pytest.approx(8.0), "ms")
    for event in events[:2]:
        assert not [c for c in event.ContentSequence if name(c) in ("Pulse Rate", "Pulse Width", "Number of Pulses")]
    # Focal spot to the reference point: 750 mm to the isocentre less the 150 mm of IEC 60601-2-43.
    distances = [float(i.MeasuredValueSequence[0].NumericValue) for i, _ in walk(ds.ContentSequence)
                 if i.get("ValueType") == "NUM" and name(i) == "Distance Source to Reference Point"]
    assert distances and distances == [pytest.approx(600.0)] * len(distances)
    assert [c.ConceptCodeSequence[0].CodeMeaning for c in events[2].ContentSequence if name(c) == "Fluoro Mode"] == ["Pulsed"]
    # Every DCM code carries the standard's meaning verbatim (pydicom's copy of PS3.16 as the reference).
    dcm = {code: meaning for group in concepts["DCM"].values() for code, (meaning, _) in group.items()}
    checked = 0
    for item, _ in walk(ds.ContentSequence):
        for seq in ("ConceptNameCodeSequence", "ConceptCodeSequence"):
            for c in item.get(seq, []):
                if c.CodingSchemeDesignator == "DCM":
                    assert c.CodeMeaning == dcm[c.CodeValue], c
                    checked += 1
    assert checked > 50
    # Re-exporting gives the same UIDs: a registry sees the same report, not a new one.
    again, _ = do_export(ledger_file, "rdsr", tmp_path / "again")
    assert pydicom.dcmread(again[0]).SOPInstanceUID == ds.SOPInstanceUID


def test_export_refuses_to_overwrite(ledger_file, tmp_path):
    do_export(ledger_file, "csv", tmp_path / "out")
    before = (tmp_path / "out/sessions.csv").read_bytes()
    with pytest.raises(FluorosimError, match="refusing to overwrite"):
        do_export(ledger_file, "csv", tmp_path / "out")
    assert (tmp_path / "out/sessions.csv").read_bytes() == before


def _export_in_child(ledger_file, out: Path, limit_bytes=None, as_nobody=False) -> tuple[int, str]:
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 3
        try:
            os.close(r)
            conn = open_readonly(ledger_file)
            if limit_bytes is not None:
                # The kernel then fails writes past this size with EFBIG, as a full disk fails them with ENOSPC.
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
                resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))
            if as_nobody:
                os.setgid(65534)
                os.setuid(65534)
            try:
                export_module.export(conn, None, None, "json", out)
                code = 0
            except FluorosimError as e:
                os.write(w, str(e).encode())
                code = 2
        finally:
            os._exit(code)
    os.close(w)
    with os.fdopen(r) as f:
        message = f.read()
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status), message


def test_full_disk_leaves_no_partial_file(ledger_file, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    code, message = _export_in_child(ledger_file, out, limit_bytes=4096)
    assert code == 2 and "cannot write" in message and "ledger.json" in message
    assert list(out.iterdir()) == []


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to drop to another user for an unwritable folder")
def test_unwritable_target_gives_one_clear_error(ledger_file, tmp_path):
    out = tmp_path / "locked"
    out.mkdir(mode=0o555)
    code, message = _export_in_child(ledger_file, out, as_nobody=True)
    assert code == 2 and "writable" in message and str(out) in message
    assert list(out.iterdir()) == []


def cli(capsys, *args):
    """The same command line in this process (argument parsing, error handling, exit status)."""
    from appliance.cli import main
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_cli_verify_export_and_bad_input(ledger_file, tmp_path, capsys):
    code, stdout, _ = cli(capsys, "logs", "verify", "--ledger", str(ledger_file))
    assert code == 0 and "chain intact" in stdout
    out = tmp_path / "cli"
    code, stdout, err = cli(capsys, "logs", "export", "--ledger", str(ledger_file), "--since", "2023-11-14T00:00Z",
                            "--until", "2023-11-16T00:00Z", "--format", "csv", "--out", str(out))
    assert code == 0, err
    assert len(list(csv.DictReader(open(out / "sessions.csv")))) == 2
    code, _, err = cli(capsys, "logs", "export", "--ledger", str(ledger_file), "--format", "csv", "--out", str(out))
    assert code == 2 and err.count("\n") == 1 and "refusing to overwrite" in err
    code, _, err = cli(capsys, "logs", "export", "--ledger", str(ledger_file), "--since", "last week", "--format", "csv",
                       "--out", str(out))
    assert code == 2 and "is not a date" in err and "Traceback" not in err
    code, stdout, _ = cli(capsys, "logs", "list", "--ledger", str(ledger_file), "--since", "2023-11-14T00:00Z",
                          "--until", "2023-11-15T00:00Z")
    rows = stdout.splitlines()[1:]
    assert code == 0 and len(rows) == 1 and rows[0].split()[0] == "1"
    assert float(rows[0].split()[-6]) == pytest.approx(TOTAL_TIME / 60, abs=0.05)
    code, _, err = cli(capsys, "logs", "verify", "--ledger", str(tmp_path / "nope.sqlite"))
    assert code == 2 and "no ledger there" in err
    # Tampering shows up as the first broken link, exit 1.
    copy = tmp_path / "tampered.sqlite"
    shutil.copy(ledger_file, copy)
    import sqlite3
    conn = sqlite3.connect(copy)
    conn.execute("UPDATE events SET d_fluoro_time_s = 0 WHERE id = 5")
    conn.commit()
    conn.close()
    code, _, err = cli(capsys, "logs", "verify", "--ledger", str(copy))
    assert code == 1 and "first broken link at event 5" in err


def test_ledger_found_through_the_appliance_profile(tmp_path, capsys):
    config = tmp_path / "configs"
    shutil.copytree(REPO / "configs", config)
    data = tmp_path / "var"
    data.mkdir()
    make_ledger(data / "ledger.sqlite")
    code, stdout, _ = cli(capsys, "logs", "verify", "--config", str(config / "appliance.yaml"))
    assert code == 0 and str(data / "ledger.sqlite") in stdout.replace("configs/../", "")


@pytest.mark.skipif(shutil.which("dciodvfy") is None,
                    reason="dciodvfy (Debian package dicom3tools) is not installed; `make test` installs it")
def test_rdsr_of_a_session_cut_off_mid_run(tmp_path):
    path = tmp_path / "ledger.sqlite"
    ledger = Ledger(path)
    console = Console(FLAT, KEYMAP, t0=0.0)
    ledger.start_session("Dr Trainee", "Child torso", FLAT.name, t_wall=DAY1, t_monotonic=0.0)
    ledger.record(press(console, 1.0, "pedal") + console.tick(4.0) + console.tick(7.5))
    ledger.close()                    # no end_session: as after a power cut, the run still open
    with Ledger(path) as reopened:
        assert reopened.recovered == [1]
    written, _ = do_export(path, "rdsr", tmp_path / "out")
    result = subprocess.run(["dciodvfy", "-profile", "IHEREM", str(written[0])], capture_output=True, text=True)
    assert not [l for l in (result.stdout + result.stderr).splitlines() if l.startswith("Error")]
    ds = pydicom.dcmread(written[0])
    events = [i for i in ds.ContentSequence if name(i) == "Irradiation Event X-Ray Data"]
    assert len(events) == 1
    items = list(events[0].ContentSequence)
    # Continuous at 6 mGy/min: the last committed progress record is at 7.0 s, 6 s after pedal-down.
    assert num(items, "Irradiation Duration")[0] == pytest.approx(6.0)
    assert num(items, "Dose (RP)")[0] == pytest.approx(6.0 * 6.0 / 60 / 1000)
    assert any(name(i) == "Comment" and "cut off" in i.TextValue for i in items)
