"""Sending to real receivers in their own processes: pynetdicom storage SCPs on loopback.

The objects of a recorded session go through `fluorosim dicom send` to a PACS (images and
dose reports) and a dose registry (dose reports only); what each receiver wrote to disk is
compared with what the appliance queued. Bad host, nothing listening and a wrong called AE
each give one line naming the destination and lose nothing; a sender killed mid-queue
resends nothing already confirmed and loses nothing."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pydicom
import pytest
from dicom_session import record_session
from ruamel.yaml import YAML

from appliance.cli import main
from appliance.records.outbox import Outbox

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


class Receiver:
    def __init__(self, out: Path, ae_title: str, hold: tuple[int, float] = (0, 0.0), tls: tuple[Path, Path] | None = None):
        self.out = out
        self.ae_title = ae_title
        self.proc = subprocess.Popen([sys.executable, str(HERE / "dicom_receiver.py"), ae_title, str(out),
                                      "--hold", *map(str, hold), *(["--tls", *map(str, tls)] if tls else [])],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        assert line.startswith("listening "), line
        self.port = int(line.split()[1])

    def received(self) -> list[str]:
        path = self.out / "received.txt"
        return path.read_text().split() if path.exists() else []

    def stop(self) -> None:
        self.proc.stdin.close()
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stdout.close()


@pytest.fixture
def receivers(tmp_path):
    started = []

    def start(name: str, ae_title: str, hold: tuple[int, float] = (0, 0.0),
              tls: tuple[Path, Path] | None = None) -> Receiver:
        r = Receiver(tmp_path / f"received-{name}", ae_title, hold, tls)
        started.append(r)
        return r
    yield start
    for r in started:
        r.stop()


def free_port() -> int:
    """A loopback port nobody listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_profile(config_copy: Path, destinations: list[dict], timeout_s: float = 3.0) -> Path:
    """The copied appliance profile with its dicom: section set for the test."""
    path = config_copy / "appliance.yaml"
    yaml = YAML(typ="rt")
    data = yaml.load(path.read_text())
    data["dicom"] = {"ae_title": "FLUOROSIM3", "institution": "St Elsewhere Teaching Hospital",
                     "station_name": "FLUOROSIM-3", "serial_number": "FS-0042", "timeout_s": timeout_s,
                     "retry": {"first_delay_s": 30, "max_delay_s": 600, "warn_after_failures": 2},
                     "destinations": destinations}
    with open(path, "w") as f:
        yaml.dump(data, f)
    return path


def cli(capsys, *args) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def uids_of(paths) -> list[str]:
    return [str(pydicom.dcmread(p, stop_before_pixels=True).SOPInstanceUID) for p in paths]


def test_a_session_reaches_the_pacs_and_the_registry_once(config_copy, receivers, capsys):
    pacs, registry = receivers("pacs", "PACS"), receivers("registry", "DOSEREG")
    profile = write_profile(config_copy, [
        {"name": "pacs", "ae_title": "PACS", "host": "127.0.0.1", "port": pacs.port, "objects": "both"},
        {"name": "registry", "ae_title": "DOSEREG", "host": "localhost", "port": registry.port, "objects": "dose_reports"},
    ])
    session = record_session(config_copy.parent / "var")
    assert cli(capsys, "dicom", "echo", "--config", str(profile))[0] == 0
    code, out, err = cli(capsys, "dicom", "send", "--config", str(profile), "--session", str(session.session_id))
    assert code == 0, err
    assert "session 1: 4 object(s) queued" in out and "'pacs': 4 object(s) sent" in out and "'registry': 1 object(s)" in out
    images, report = uids_of(session.images), uids_of([session.report])
    assert sorted(pacs.received()) == sorted(images + report)
    assert registry.received() == report
    # What arrived is what was written: the same bytes of pixel data, the same study.
    for path in session.images:
        sent = pydicom.dcmread(path)
        got = pydicom.dcmread(pacs.out / f"{sent.SOPInstanceUID}.dcm")
        assert got.PixelData == sent.PixelData and got.StudyInstanceUID == sent.StudyInstanceUID
        assert got.IrradiationEventUID == sent.IrradiationEventUID
    got_report = pydicom.dcmread(registry.out / f"{report[0]}.dcm")
    assert got_report.StudyInstanceUID == pydicom.dcmread(session.images[0]).StudyInstanceUID
    # Sending or queueing the session again sends nothing twice.
    assert cli(capsys, "dicom", "send", "--config", str(profile))[1].strip() == "nothing queued; nothing sent"
    assert cli(capsys, "dicom", "send", "--config", str(profile), "--session", "1")[0] == 0
    assert len(pacs.received()) == 4 and len(registry.received()) == 1
    assert cli(capsys, "dicom", "queue", "--config", str(profile))[1].strip() == "nothing queued"


def test_unreachable_destinations_give_one_line_each_and_lose_nothing(config_copy, receivers, capsys):
    pacs = receivers("pacs", "PACS")
    closed = free_port()
    profile = write_profile(config_copy, [
        {"name": "nohost", "ae_title": "PACS", "host": "no-such-host.invalid", "port": 104},
        {"name": "refused", "ae_title": "PACS", "host": "127.0.0.1", "port": closed},
        {"name": "wrongae", "ae_title": "NOTPACS", "host": "127.0.0.1", "port": pacs.port},
    ], timeout_s=2.0)
    session = record_session(config_copy.parent / "var")
    code, out, err = cli(capsys, "dicom", "echo", "--config", str(profile))
    lines = err.strip().splitlines()
    assert code == 1 and out == "" and len(lines) == 3, err
    assert lines[0].startswith("fluorosim: destination 'nohost' (PACS@no-such-host.invalid:104): cannot resolve host")
    assert lines[1].startswith(f"fluorosim: destination 'refused' (PACS@127.0.0.1:{closed}): no DICOM association (")
    assert "Connection refused" in lines[1]
    assert lines[2].startswith(f"fluorosim: destination 'wrongae' (NOTPACS@127.0.0.1:{pacs.port}): association rejected")
    assert "Called AE title not recognised" in lines[2] and "check the destination's ae_title" in lines[2]
    code, out, err = cli(capsys, "dicom", "send", "--config", str(profile), "--session", "1")
    assert code == 1 and "Traceback" not in err
    assert [line for line in err.splitlines() if line.startswith("fluorosim: destination")] == lines
    assert pacs.received() == []
    # All 4 objects stay queued for each of the 3 destinations, with the reason.
    code, out, _ = cli(capsys, "dicom", "queue", "--config", str(profile))
    rows = out.strip().splitlines()[1:]
    assert code == 0 and len(rows) == 12
    assert sum("association rejected" in r for r in rows) == 4 and sum("cannot resolve" in r for r in rows) == 4
    # The admin corrects the AE title: the queued objects go, once.
    fixed = profile.read_text().replace("ae_title: NOTPACS", "ae_title: PACS")
    profile.write_text(fixed)
    cli(capsys, "dicom", "send", "--config", str(profile))
    assert sorted(pacs.received()) == sorted(uids_of(session.images + [session.report]))


def test_a_destination_that_keeps_failing_is_reported_once_and_recovers(config_copy, receivers, caplog):
    from appliance.config import ApplianceProfile, load_profile
    from appliance.records.dicom_sender import DicomSender, queue_object

    port = free_port()
    profile = write_profile(config_copy, [{"name": "pacs", "ae_title": "PACS", "host": "127.0.0.1", "port": port}],
                            timeout_s=1.0)
    dicom = load_profile(profile, ApplianceProfile).dicom
    session = record_session(config_copy.parent / "var")
    with Outbox(config_copy.parent / "var/ledger.sqlite", "dicom") as box:
        assert queue_object(box, dicom, session.report_bytes, "dose_report", "dose report of session 1", 1) == ["pacs"]
        sender = DicomSender(box, dicom, profile.parent)
        with caplog.at_level("INFO", logger="appliance.records.dicom_sender"):
            for attempt in range(1, 4):
                report = sender.run_round(ignore_backoff=True)
                assert report.sent == {} and len(report.errors) == 1
                # warn_after_failures is 2: a banner from the second failure on, one warning in the log.
                assert len(sender.problems()) == (attempt >= 2)
            assert sender.problems() == ["DICOM send to 'pacs' failing (Connection refused)"]
            assert len([r for r in caplog.records if r.levelname == "WARNING"]) == 1
            # Backoff: without ignoring it, nothing is due again yet (first delay 30 s).
            assert sender.run_round().errors == []
            # The PACS comes up on that port.
            receiver_out = config_copy.parent / "received"
            proc = subprocess.Popen([sys.executable, str(HERE / "dicom_receiver.py"), "PACS", str(receiver_out),
                                     "--port", str(port)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            try:
                assert proc.stdout.readline().startswith("listening")
                assert sender.run_round(ignore_backoff=True).sent == {"pacs": 1}
                assert sender.problems() == []
                assert "answers again" in caplog.text
            finally:
                proc.stdin.close()
                proc.wait(timeout=5)
                proc.stdout.close()
    assert (receiver_out / "received.txt").read_text().split() == uids_of([session.report])


def test_killing_the_sender_mid_queue_loses_and_repeats_nothing_confirmed(config_copy, receivers, capsys):
    pacs = receivers("pacs", "PACS", hold=(3, 5.0))    # the answer to the third object waits 5 s
    profile = write_profile(config_copy, [
        {"name": "pacs", "ae_title": "PACS", "host": "127.0.0.1", "port": pacs.port, "objects": "both"}])
    first = record_session(config_copy.parent / "var")
    ledger = config_copy.parent / "var/ledger.sqlite"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    # `fluorosim dicom send --session 1` in a process of its own (without the whole CLI's imports).
    send = ("import sys, types; from appliance.records.dicom_commands import run_send; "
            "run_send(types.SimpleNamespace(config=sys.argv[1], session=int(sys.argv[2])))")
    sender = subprocess.Popen([sys.executable, "-c", send, str(profile), str(first.session_id)], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    while len(pacs.received()) < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    # The third object has arrived and its answer is held back: kill the sender now.
    os.kill(sender.pid, signal.SIGKILL)
    sender.wait()
    sender.stderr.close()
    with Outbox(ledger, "dicom") as box:
        confirmed = box.sent_keys("pacs")
        left = {p.key for p in box.pending()}
    assert len(confirmed) == 2 and len(left) == 2, (confirmed, left)   # 4 objects: 2 confirmed, 1 in flight, 1 not begun
    received_before = pacs.received()
    assert received_before[:2] == confirmed
    code, _, err = cli(capsys, "dicom", "send", "--config", str(profile))
    assert code == 0, err
    everything = uids_of(first.images + [first.report])
    received = pacs.received()
    assert sorted(set(received)) == sorted(everything)                  # nothing lost
    assert all(received.count(k) == 1 for k in confirmed)               # nothing confirmed sent twice
    # Only the object in flight at the kill (arrived, unconfirmed) came again, under its own UID.
    assert [k for k in set(received) if received.count(k) > 1] == [received_before[2]]
    assert len(received) == len(everything) + 1


def _can_unshare_network() -> bool:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return False
    return subprocess.run(["unshare", "--net", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(shutil.which("Orthanc") is None, reason="Orthanc (Debian package orthanc) is not installed; "
                                                          "`make test` installs it")
@pytest.mark.skipif(not _can_unshare_network(), reason="needs unshare --net (root or user namespaces) and ip (iproute2) "
                                                       "to give Orthanc a loopback-only network of its own")
def test_orthanc_stores_the_session_as_one_study(config_copy, tmp_path):
    profile = write_profile(config_copy, [
        {"name": "orthanc", "ae_title": "ORTHANC", "host": "127.0.0.1", "port": 4242, "objects": "both"}])
    session = record_session(config_copy.parent / "var")
    work = tmp_path / "orthanc"
    work.mkdir()
    run = subprocess.run(["unshare", "--net", sys.executable, str(HERE / "orthanc_netns.py"), str(profile), str(work),
                          str(session.session_id)], capture_output=True, text=True, timeout=240)
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["echo"]["rc"] == 0 and "answered C-ECHO" in result["echo"]["out"], result["echo"]
    assert result["send"]["rc"] == 0, result["send"]
    images = [pydicom.dcmread(p, stop_before_pixels=True) for p in session.images]
    report = pydicom.dcmread(session.report, stop_before_pixels=True)
    # Read back over Orthanc's REST API: one study, with the images' series and the report's.
    (study,) = result["studies"]
    assert study["StudyInstanceUID"] == report.StudyInstanceUID and study["PatientID"] == report.PatientID
    series = {s["Modality"]: s for s in study["series"]}
    assert sorted(series) == ["RF", "SR"]
    assert series["RF"]["SeriesInstanceUID"] == images[0].SeriesInstanceUID
    assert series["RF"]["instances"] == sorted(str(ds.SOPInstanceUID) for ds in images)
    assert series["SR"]["instances"] == [str(report.SOPInstanceUID)]


def self_signed(folder: Path, name: str) -> tuple[Path, Path]:
    """A certificate for 127.0.0.1 and localhost, and its key (PEM), made with openssl."""
    cert, key = folder / f"{name}-cert.pem", folder / f"{name}-key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                    "-keyout", str(key), "-out", str(cert), "-days", "2", "-subj", f"/CN={name}",
                    "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"], check=True, capture_output=True)
    return cert, key


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl (Debian package openssl) makes the test certificates")
def test_dicom_over_tls_checks_the_destinations_certificate(config_copy, receivers, capsys, tmp_path):
    cert, key = self_signed(tmp_path, "pacs")
    other, _ = self_signed(tmp_path, "someone-else")
    pacs = receivers("pacs", "PACS", tls=(cert, key))
    profile = write_profile(config_copy, [
        {"name": "pacs", "ae_title": "PACS", "host": "127.0.0.1", "port": pacs.port, "tls": {"ca_file": str(cert)}},
        {"name": "impostor", "ae_title": "PACS", "host": "127.0.0.1", "port": pacs.port, "tls": {"ca_file": str(other)},
         "objects": "dose_reports"},
    ])
    session = record_session(config_copy.parent / "var")
    code, out, err = cli(capsys, "dicom", "echo", "--config", str(profile))
    assert code == 1 and "destination 'pacs'" in out and "answered C-ECHO" in out, err
    (line,) = err.strip().splitlines()
    assert line.startswith("fluorosim: destination 'impostor'") and "CERTIFICATE_VERIFY_FAILED" in line
    code, out, err = cli(capsys, "dicom", "send", "--config", str(profile), "--session", "1")
    assert code == 1 and "'pacs': 4 object(s) sent" in out
    assert sorted(pacs.received()) == sorted(uids_of(session.images + [session.report]))
    # The report stays queued for the destination whose certificate did not verify.
    code, out, _ = cli(capsys, "dicom", "queue", "--config", str(profile))
    (row,) = out.strip().splitlines()[1:]
    assert "impostor" in row and "CERTIFICATE_VERIFY_FAILED" in row
