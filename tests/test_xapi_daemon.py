"""The running appliance sends an ended session's xAPI statements through the ledger's send
queue to a real LRS (ralph-malph on loopback, as in test_teaching_xapi): an LRS that is down
keeps them queued with a banner; once the profile names a working LRS, the send worker
delivers them, each once, and `fluorosim lrs send` finds nothing left to send."""

from __future__ import annotations

import threading
from pathlib import Path

from appliance_setup import make_appliance
from ruamel.yaml import YAML
from stop_deadline import join_left_behind_sends
from test_dicom_daemon import _wait
from test_teaching_daemon import EXERCISE, SCRIPT
from test_teaching_xapi import PASSWORD, _free_port, lrs, read_back  # noqa: F401 - the fixture

from appliance.cli import main
from appliance.daemon.notify import Notifier
from appliance.daemon.pipeline import Appliance
from appliance.daemon.reload import ProfileKeeper
from appliance.daemon.send_worker import SendWorker, xapi_send_check
from appliance.records.ledger import open_readonly
from appliance.records.outbox import Outbox
from appliance.teaching import xapi

USER = "box-4"   # this test's own LRS user (the fs backend writes each user's file once)


def with_lrs(config: Path, endpoint: str, *, exercise: bool) -> Path:
    yaml = YAML(typ="rt")
    data = yaml.load(config.read_text())
    teaching = {"view_period_s": 0.5, "lrs": {
        "endpoint": endpoint, "username": USER, "password_file": "lrs-password", "appliance_id": USER,
        "account_home_page": "https://booking.sim-centre.org", "timeout_s": 2, "send_at_shutdown_s": 1,
        "retry": {"first_delay_s": 0.1, "max_delay_s": 0.2, "warn_after_failures": 1, "poll_period_s": 0.2}}}
    if exercise:
        teaching["exercise"] = "exercises/cylinder.yaml"
    data["teaching"] = teaching
    with open(config, "w") as f:
        yaml.dump(data, f)
    return config


def mine(url: str) -> list[dict]:
    return [s for s in read_back(url, USER) if s["context"]["extensions"]["urn:fluorosim:appliance"] == USER]


def test_an_ended_sessions_statements_reach_the_lrs_through_the_send_worker(lrs, tmp_path, capsys):  # noqa: F811
    # The console clock at x3: the script's 6 s in 2.
    config = make_appliance(tmp_path, script=SCRIPT, clock_rate=3.0)
    (config.parent / "exercises" / "cylinder.yaml").write_text(EXERCISE)
    (config.parent / "lrs-password").write_text(PASSWORD + "\n")
    dead = f"http://127.0.0.1:{_free_port()}/xAPI/"
    with_lrs(config, dead, exercise=True)
    # Session 1: the exercise, run while the LRS is down; it ends at shutdown.
    app = Appliance(ProfileKeeper(config), Notifier({}))
    stop = threading.Event()
    runner = threading.Thread(target=app.run, kwargs={"until": stop.is_set, "signals": False})
    runner.start()
    try:
        assert _wait(lambda: app.parts.keypad.finished and app.clock() > 6.0, 60)
    finally:
        stop.set()
        runner.join(20)
    assert not runner.is_alive()
    join_left_behind_sends()        # a loaded machine may take longer than the 1 s budget to be refused
    ledger = tmp_path / "data" / "ledger.sqlite"
    with Outbox(ledger, xapi.KIND) as box:
        pending = box.pending()
    # Two tasks (passed, failed) and the exercise (completed): queued, tried at shutdown, kept.
    assert len(pending) == 3 and {p.destination for p in pending} == {"lrs"}
    assert all(p.attempts == 1 and "cannot be reached" in p.last_error for p in pending), pending
    assert sorted(p.label for p in pending) == ["xAPI 'completed Cylinder drill' of session 1",
                                                "xAPI 'failed nowhere' of session 1", "xAPI 'passed cylinder' of session 1"]
    capsys.readouterr()
    assert main(["lrs", "queue", "--config", str(config)]) == 0
    rows = capsys.readouterr().out.strip().splitlines()[1:]
    assert len(rows) == 3 and all("xAPI '" in r and " lrs " in r and "cannot be reached" in r for r in rows), rows
    # The send worker (the appliance's own, run on its own here to spare a second start-up)
    # while the LRS is still down: the banner; then the admin fixes the endpoint and reloads,
    # and the queued statements go.
    keeper = ProfileKeeper(config)
    sender = SendWorker(ledger, keeper)
    check = xapi_send_check(lambda: sender.xapi_problem)
    sender.start()
    try:
        assert _wait(lambda: not check.check().ok, 30)
        assert check.check().banner.startswith("xAPI send to 'lrs' failing (")
        assert check.check().banner.endswith("; trainees' results stay queued")
        with_lrs(config, lrs + "/xAPI/", exercise=True)
        assert keeper.reload()[1]
        assert _wait(lambda: len(mine(lrs)) == 3, 30)
        assert _wait(lambda: check.check().ok, 10)
        assert sender.alive
    finally:
        sender.stop()
        assert sender.join(10)
    stored = mine(lrs)
    conn = open_readonly(ledger)
    try:
        trainee = conn.execute("SELECT detail FROM events WHERE kind = 'trainee'").fetchone()[0]
    finally:
        conn.close()
    assert '"Bo"' in trainee and {s["actor"]["name"] for s in stored} == {"Bo"}
    verbs = sorted(s["verb"]["display"]["en"] for s in stored)
    assert verbs == ["completed", "failed", "passed"]
    assert {s["context"]["extensions"]["urn:fluorosim:session"] for s in stored} == {1}
    with Outbox(ledger, xapi.KIND) as box:
        assert box.pending() == [] and len(box.sent_keys("lrs")) == 3
    # Sent again by hand: nothing is due, and the LRS holds each statement once.
    assert main(["lrs", "send", "--config", str(config)]) == 0
    assert sorted(s["id"] for s in mine(lrs)) == sorted(s["id"] for s in stored)
