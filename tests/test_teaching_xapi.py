"""xAPI to a real Learning Record Store: ralph-malph's LRS with its file-system backend, started
on loopback by the test. Statements are read back through the LRS's xAPI API; a second send
stores nothing twice; refused credentials and an unreachable LRS are one line and lose nothing.

ralph-malph 5.1's file-system backend writes each user's statement file once (it creates the
file and refuses to add to it), so each test appliance has its own LRS user and target folder,
and makes one successful POST; later sends are answered from what is stored (409, then PUT
answered 204), which is what the idempotent resend must do anyway."""

import base64
import json
import os
import socket
import sqlite3
import subprocess
import sys
import time
import urllib.request

import pytest
from ruamel.yaml import YAML
from teaching_script import REPO, scripted_session

from appliance.cli import main

ralph = pytest.importorskip("ralph", reason="ralph-malph is not installed: make setup installs the test extras")
bcrypt = pytest.importorskip("bcrypt", reason="ralph-malph's bcrypt is not installed")

PASSWORD = "s3cret-for-the-test"
USERS = ("box-1", "box-2", "box-4")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def lrs(tmp_path_factory):
    home = tmp_path_factory.mktemp("lrs")
    auth = [{"agent": {"mbox": f"mailto:{user}@example.org", "objectType": "Agent"}, "scopes": ["all"], "target": user,
             "hash": bcrypt.hashpw(PASSWORD.encode(), bcrypt.gensalt(rounds=4)).decode(), "username": user}
            for user in USERS]
    (home / "auth.json").write_text(json.dumps(auth))
    for user in USERS:
        # The fs backend writes a user's target relative to its working directory (home).
        (home / user).mkdir()
    port = _free_port()
    env = {**os.environ, "RALPH_APP_DIR": str(home / "app"), "RALPH_AUTH_FILE": str(home / "auth.json"),
           "RALPH_RUNSERVER_BACKEND": "fs", "RALPH_BACKENDS__DATA__FS__DEFAULT_DIRECTORY_PATH": str(home / "data")}
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "ralph.api:app", "--host", "127.0.0.1", "--port", str(port)],
                            env=env, stdout=open(home / "lrs.log", "wb"), stderr=subprocess.STDOUT, cwd=home)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while True:
        try:
            with urllib.request.urlopen(url + "/__heartbeat__", timeout=2) as r:
                if r.status == 200:
                    break
        except OSError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail("the LRS did not start: " + (home / "lrs.log").read_text(errors="replace")[-2000:])
        time.sleep(0.3)
    yield url
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


def read_back(url: str, user: str) -> list[dict]:
    req = urllib.request.Request(url + "/xAPI/statements?limit=100", headers={
        "Authorization": "Basic " + base64.b64encode(f"{user}:{PASSWORD}".encode()).decode(),
        "X-Experience-API-Version": "1.0.3"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read())["statements"]


def appliance_with_lrs(tmp_path, endpoint: str, password: str, appliance_id: str):
    configs = tmp_path / "configs"
    if not configs.exists():
        import shutil
        shutil.copytree(REPO / "configs", configs)
    yaml = YAML(typ="rt")
    data = yaml.load((configs / "appliance-bench.yaml").read_text())
    data["data_dir"] = str(tmp_path / "data")
    data["teaching"] = {"lrs": {"endpoint": endpoint, "username": appliance_id, "password_file": "lrs-password",
                                "account_home_page": "https://booking.sim-centre.org", "appliance_id": appliance_id,
                                "timeout_s": 10}}
    (configs / "lrs-password").write_text(password + "\n")
    path = configs / "appliance-lrs.yaml"
    with open(path, "w") as f:
        yaml.dump(data, f)
    return path


def test_statements_reach_the_lrs_once_and_read_back(lrs, tmp_path, capsys):
    config = appliance_with_lrs(tmp_path, lrs + "/xAPI/", PASSWORD, "box-1")
    scripted_session(tmp_path / "data" / "ledger.sqlite")
    assert main(["lrs", "send", "--config", str(config)]) == 0
    assert capsys.readouterr().out.startswith("1 session(s) queued, 4 statement(s) sent")
    mine = [s for s in read_back(lrs, "box-1") if s["context"]["extensions"]["urn:fluorosim:appliance"] == "box-1"]
    by_object = {s["object"]["definition"]["name"]["en"]: s for s in mine}
    assert set(by_object) == {"A", "B", "C", "three spheres"}
    assert {k: by_object[k]["verb"]["id"].rsplit("/", 1)[1] for k in "ABC"} == {"A": "passed", "B": "passed", "C": "failed"}
    a = by_object["A"]
    assert a["actor"]["account"] == {"homePage": "https://booking.sim-centre.org", "name": "Ada Lovelace"}
    assert a["result"]["success"] is True and a["result"]["duration"] == "PT8.00S"
    assert a["result"]["extensions"]["urn:fluorosim:metric:fluoro_time_s"] == pytest.approx(5.0)
    assert a["result"]["extensions"]["urn:fluorosim:metric:blank_exposures"] == 1
    assert by_object["three spheres"]["result"]["score"] == {"raw": 2, "min": 0, "max": 3}
    assert all(s["context"]["extensions"]["urn:fluorosim:session"] == 1 for s in mine)
    # Again: nothing new to queue or send, and the LRS still holds each statement once.
    assert main(["lrs", "send", "--config", str(config)]) == 0
    assert capsys.readouterr().out.startswith("0 session(s) queued, 0 statement(s) sent")
    # An answer lost on the way (the queue thinks nothing was sent): resent, still stored once.
    with sqlite3.connect(tmp_path / "data" / "ledger.sqlite") as q:
        q.execute("UPDATE outbox_deliveries SET sent_wall = NULL WHERE item_id IN "
                  "(SELECT id FROM outbox_items WHERE kind = 'xapi')")
    assert main(["lrs", "send", "--config", str(config)]) == 0
    capsys.readouterr()
    again = [s for s in read_back(lrs, "box-1") if s["context"]["extensions"]["urn:fluorosim:appliance"] == "box-1"]
    assert sorted(s["id"] for s in again) == sorted(s["id"] for s in mine)


def test_refused_credentials_and_a_dead_endpoint_lose_nothing(lrs, tmp_path, capsys):
    scripted_session(tmp_path / "data" / "ledger.sqlite")
    config = appliance_with_lrs(tmp_path, lrs + "/xAPI", "wrong password", "box-2")
    assert main(["lrs", "send", "--config", str(config)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "refused the credentials (HTTP 401)" in err[0] and "4 statement(s) kept" in err[0], err
    dead = f"http://127.0.0.1:{_free_port()}/xAPI"
    config = appliance_with_lrs(tmp_path, dead, PASSWORD, "box-2")
    assert main(["lrs", "send", "--config", str(config)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot be reached" in err[0] and "4 statement(s) kept" in err[0], err
    assert not [s for s in read_back(lrs, "box-2") if s["context"]["extensions"]["urn:fluorosim:appliance"] == "box-2"]
    # Fixed: what was kept goes now, all of it.
    config = appliance_with_lrs(tmp_path, lrs + "/xAPI", PASSWORD, "box-2")
    assert main(["lrs", "send", "--config", str(config)]) == 0
    assert "0 session(s) queued, 4 statement(s) sent" in capsys.readouterr().out
    assert len([s for s in read_back(lrs, "box-2") if s["context"]["extensions"]["urn:fluorosim:appliance"] == "box-2"]) == 4


def test_a_bad_endpoint_is_refused_in_the_profile(tmp_path, capsys):
    config = appliance_with_lrs(tmp_path, "lrs.sim-centre.org/xAPI", PASSWORD, "box-3")
    assert main(["validate", str(config)]) == 2
    err = capsys.readouterr().err
    assert "teaching.lrs.endpoint: must be an http:// or https:// URL with a host" in err
