"""`fluorosim report session` and `report trainee` on the scripted session: the files are
there, their figures are the ledger's, the plot is a real PNG and a bad request is one line."""

import csv
import json

import cv2
import numpy as np
import pytest
from teaching_script import scripted_session

from appliance.cli import main
from appliance.records.ledger import open_readonly
from appliance.teaching.report import dose_rate


@pytest.fixture(scope="module")
def ledger(tmp_path_factory):
    folder = tmp_path_factory.mktemp("teaching")
    path = folder / "ledger.sqlite"
    scripted_session(path)
    # The saved image of save 1 (as the records worker names it); saves 2 and 3 have no file.
    images = folder / "images"
    images.mkdir()
    cv2.imwrite(str(images / "image-000001-0001.png"), np.full((256, 256), 128, np.uint8))
    return path


def test_session_report_figures_are_the_ledgers(ledger, tmp_path, capsys):
    assert main(["report", "session", "1", "--ledger", str(ledger), "--out", str(tmp_path)]) == 0
    folder = tmp_path / "session-000001"
    assert capsys.readouterr().out.strip() == str(folder / "index.html")
    conn = open_readonly(ledger)
    try:
        row = dict(conn.execute("SELECT * FROM sessions WHERE id = 1").fetchone())
        kerma_events = [r[0] for r in conn.execute("SELECT air_kerma_mgy FROM events WHERE session_id = 1 ORDER BY id")]
    finally:
        conn.close()
    with open(folder / "metrics.csv", newline="") as f:
        metrics = {(r["scope"], r["metric"]): r["value"] for r in csv.DictReader(f)}
    for key in ("fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2"):
        assert float(metrics[("session", key)]) == pytest.approx(row[key], rel=1e-12)
    assert int(metrics[("session", "images_saved")]) == row["saves"] == 3
    assert int(metrics[("session", "exposures")]) == 5
    assert int(metrics[("exercise 1", "tasks_met")]) == 2
    data = json.loads((folder / "report.json").read_text())
    assert data["series"]["air_kerma_mgy"][-1] == pytest.approx(kerma_events[-1])
    with open(folder / "tasks.csv", newline="") as f:
        tasks = list(csv.DictReader(f))
    assert [t["state"] for t in tasks] == ["met", "met", "skipped"]
    with open(folder / "saves.csv", newline="") as f:
        saves = list(csv.DictReader(f))
    assert [s["met"] for s in saves] == ["True", "False", "True"] and saves[1]["reasons"] == "not collimated"
    plot = cv2.imread(str(folder / "dose.png"))
    assert plot is not None and plot.shape[0] > 300
    assert cv2.imread(str(folder / "thumb-0001.png"), cv2.IMREAD_GRAYSCALE).shape == (200, 200)
    page = (folder / "index.html").read_text()
    assert "Ada Lovelace" in page and "B: not met - not collimated" in page and "(image file not found)" in page
    assert "<h2>Exercise 1: three spheres</h2><p>test</p>" in page
    assert "exercise 1" in (folder / "references.csv").read_text()


def test_dose_rate_spreads_each_increment_over_its_interval():
    # 0.1 and 0.2 mGy within the first second; 0.3 mGy over 1.0-2.5 s: 0.2 in the second, 0.1 in the third.
    t_bins, rate = dose_rate({"t": [0.0, 0.5, 1.0, 2.5], "air_kerma_mgy": [0.0, 0.1, 0.3, 0.6]}, bin_s=1.0)
    assert t_bins == [0.0, 1.0, 2.0]
    assert rate == pytest.approx([0.3 * 60, 0.2 * 60, 0.1 * 60])


def test_trainee_report_lists_the_session(ledger, tmp_path):
    assert main(["report", "trainee", "ada lovelace", "--ledger", str(ledger), "--out", str(tmp_path)]) == 0
    with open(tmp_path / "trainee-ada-lovelace" / "sessions.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["session"] == "1" and rows[0]["tasks_met"] == "2"
    assert cv2.imread(str(tmp_path / "trainee-ada-lovelace" / "trends.png")) is not None


@pytest.mark.parametrize("argv, message", [
    (["report", "session", "7"], "no session 7 in the ledger (sessions 1..1"),
    (["report", "trainee", "Grace Hopper"], "no sessions of trainee 'Grace Hopper'"),
    (["report", "trainee", "Ada", "--since", "2026-02-01", "--until", "2026-01-01"], "is not after --since"),
])
def test_bad_requests_are_one_line(ledger, tmp_path, capsys, argv, message):
    assert main(argv + ["--ledger", str(ledger), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_an_exercise_record_this_version_cannot_read_is_one_line(tmp_path, capsys):
    from appliance.records.ledger import Ledger

    path = tmp_path / "ledger.sqlite"
    with Ledger(path) as ledger:
        ledger.start_session("trainee", "child", "II", 1.7e9, t_monotonic=0.0)
        from appliance.console.state import ConsoleEvent
        ledger.record([ConsoleEvent(1.0, "exercise_start", {"title": "x", "profile": {"title": "x", "tasks": "?"}})])
        ledger.end_session(1.7e9 + 2)
    assert main(["report", "session", "1", "--ledger", str(path), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "records an exercise this fluorosim cannot read" in err[0]


def test_trainee_report_follows_the_sessions_in_the_period(tmp_path):
    import datetime as dt

    path = tmp_path / "ledger.sqlite"
    day = dt.datetime(2026, 3, 2, 10, 0).astimezone()
    for days in (0, 7, 14):
        scripted_session(path, t_wall=(day + dt.timedelta(days=days)).timestamp())
    assert main(["report", "trainee", "Ada Lovelace", "--ledger", str(path), "--out", str(tmp_path / "all")]) == 0
    with open(tmp_path / "all" / "trainee-ada-lovelace" / "sessions.csv", newline="") as f:
        assert [r["session"] for r in csv.DictReader(f)] == ["1", "2", "3"]
    # From the second week's day to the day before the third session's (a date as --until includes it).
    assert main(["report", "trainee", "Ada Lovelace", "--ledger", str(path), "--out", str(tmp_path / "some"),
                 "--since", "2026-03-09", "--until", "2026-03-15"]) == 0
    with open(tmp_path / "some" / "trainee-ada-lovelace" / "sessions.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["session"] for r in rows] == ["2"] and rows[0]["fluoro_time_s"] == "9.0"
    data = json.loads((tmp_path / "some" / "trainee-ada-lovelace" / "report.json").read_text())
    assert [t["state"] for t in data["sessions"][0]["exercises"][0]["tasks"]] == ["met", "met", "skipped"]
