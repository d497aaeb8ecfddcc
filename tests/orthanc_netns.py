"""Run a real Orthanc and `fluorosim dicom send` against it, inside a network namespace of
their own whose only interface is loopback (start with `unshare --net`), as a test host would.

    unshare --net python tests/orthanc_netns.py PROFILE WORK_DIR SESSION

Prints one JSON object: the send's exit status and stderr, the echo's, and what Orthanc
stored as read back over its REST API (studies, their series and instances).
"""

import contextlib
import io
import json
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

DICOM_PORT, HTTP_PORT = 4242, 8042
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def rest(path: str):
    with urllib.request.urlopen(f"http://127.0.0.1:{HTTP_PORT}{path}", timeout=5) as answer:
        return json.load(answer)


def fluorosim(*args) -> dict:
    """The `fluorosim` command, run in this process (inside the namespace): exit status and output."""
    from appliance.cli import main
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(list(args))
    return {"rc": rc, "out": out.getvalue(), "err": err.getvalue()}


def main() -> None:
    profile, work, session = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    config = {"Name": "fluorosim-test", "StorageDirectory": str(work / "storage"), "IndexDirectory": str(work / "storage"),
              "DicomAet": "ORTHANC", "DicomPort": DICOM_PORT, "HttpPort": HTTP_PORT, "DicomCheckCalledAet": True,
              "RemoteAccessAllowed": False, "AuthenticationEnabled": False, "Plugins": [], "ConcurrentJobs": 1,
              "DicomAlwaysAllowStore": True, "DicomAlwaysAllowEcho": True}
    (work / "orthanc.json").write_text(json.dumps(config))
    log = open(work / "orthanc.log", "w")
    orthanc = subprocess.Popen(["Orthanc", str(work / "orthanc.json")], stdout=log, stderr=subprocess.STDOUT)
    result: dict = {}
    try:
        started = time.monotonic()
        while True:
            try:
                result["orthanc_version"] = rest("/system")["Version"]
                break
            except OSError:
                if orthanc.poll() is not None or time.monotonic() - started > 60:
                    raise SystemExit(f"Orthanc did not start: see {work / 'orthanc.log'}") from None
                time.sleep(0.1)
        result["startup_s"] = round(time.monotonic() - started, 2)
        result["echo"] = fluorosim("dicom", "echo", "--config", str(profile))
        result["send"] = fluorosim("dicom", "send", "--config", str(profile), "--session", session)
        studies = []
        for study in rest("/studies?expand"):
            series = []
            for s in study["Series"]:
                info = rest(f"/series/{s}")
                series.append({"Modality": info["MainDicomTags"].get("Modality"),
                               "SeriesInstanceUID": info["MainDicomTags"]["SeriesInstanceUID"],
                               "instances": sorted(rest(f"/instances/{i}")["MainDicomTags"]["SOPInstanceUID"]
                                                   for i in info["Instances"])})
            studies.append({"StudyInstanceUID": study["MainDicomTags"]["StudyInstanceUID"],
                            "PatientID": study["PatientMainDicomTags"]["PatientID"], "series": series})
        result["studies"] = studies
    finally:
        orthanc.terminate()
        orthanc.wait(timeout=10)
        log.close()
    print(json.dumps(result))


if __name__ == "__main__":
    main()
