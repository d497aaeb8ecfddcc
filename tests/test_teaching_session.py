"""The scripted teaching session (tests/teaching_script.py): counts, times, doses and verdicts
worked out by hand, against what the ledger-based metrics report."""

import pytest
from teaching_script import II, field_area_cm2, scripted_session

from appliance.records.ledger import open_readonly, verify
from appliance.teaching.metrics import session_metrics, trainee_sessions


@pytest.fixture
def session_ledger(tmp_path):
    path = tmp_path / "ledger.sqlite"
    return path, scripted_session(path)


def test_scripted_session_metrics_match_hand_worked_values(session_ledger):
    path, s = session_ledger
    conn = open_readonly(path)
    try:
        assert verify(conn).ok
        m = session_metrics(conn, 1)
    finally:
        conn.close()
    assert m["session"]["trainee"] == "Ada Lovelace"
    whole = m["metrics"]
    assert whole["exposures"] == 5
    assert whole["judged_exposures"] == 4 and whole["blank_exposures"] == 1
    assert whole["fluoro_time_s"] == pytest.approx(2 + 3 + 2 + 1 + 1, abs=1e-9)
    # The intensifier's continuous rates at zoom 1 and 2, as its profile states them (mGy/min).
    r1, r2 = (z.air_kerma_rate_mgy_per_min["continuous"] for z in II.zoom_levels[:2])
    assert (r1, r2) == (8.0, 14.6)
    kerma = r1 / 60 * (2 + 3) + r2 / 60 * (2 + 1 + 1)
    assert whole["air_kerma_mgy"] == pytest.approx(kerma, rel=1e-9)
    a1, a2 = field_area_cm2(230, 230, 230), field_area_cm2(170, 170, 170)
    a2c = field_area_cm2(160, 170, 170)
    dap = (r1 / 60 * 5 * a1 + r2 / 60 * 2 * a2 + r2 / 60 * 2 * a2c) / 1000
    assert whole["dap_gy_cm2"] == pytest.approx(dap, rel=1e-4)
    assert whole["collimated_share"] == pytest.approx(2 / 9)
    assert whole["mean_field_area_cm2"] == pytest.approx((5 * a1 + 2 * a2 + 2 * a2c) / 9, rel=1e-4)
    assert whole["zoom_time_s"] == pytest.approx({"1": 5.0, "2": 4.0, "3": 0.0, "4": 0.0})
    assert whole["pulsed_share"] == 0.0
    assert whole["images_saved"] == 3 and whole["held_image_saves"] == 3
    assert whole["images_on_target"] == 3 and whole["images_off_target"] == 0
    assert whole["tasks_met"] == 2
    # First image showing A: the first frame of exposure 2, at 5.1 s; the exercise began at 1.0 s.
    assert whole["time_to_first_on_target_s"] == pytest.approx(4.1, abs=1e-6)
    # The ledger's own totals are the report's.
    for key in ("fluoro_time_s", "air_kerma_mgy", "dap_gy_cm2"):
        assert whole[key] == pytest.approx(m["session"]["ledger_totals"][key], rel=1e-12)

    (ex,) = m["exercises"]
    assert ex["started_s"] == pytest.approx(1.0) and ex["ended_s"] == pytest.approx(17.0)
    a, b, c = ex["tasks"]
    assert (a["state"], b["state"], c["state"]) == ("met", "met", "skipped")
    assert a["time_to_met_s"] == pytest.approx(8.0) and b["time_to_met_s"] == pytest.approx(7.5)
    assert a["metrics"]["exposures"] == 2 and a["metrics"]["blank_exposures"] == 1
    assert a["metrics"]["fluoro_time_s"] == pytest.approx(5.0)
    assert b["metrics"]["exposures"] == 2 and b["metrics"]["blank_exposures"] == 0
    assert b["metrics"]["time_to_first_on_target_s"] == pytest.approx(2.1, abs=1e-6)
    assert c["metrics"]["exposures"] == 0
    save2 = b["saves"][0]["verdict"]
    assert not save2["met"] and save2["in_field"] and save2["reasons"] == ["not collimated"]
    assert a["saves"][0]["verdict"]["off_axis_mm"] == pytest.approx(0.0, abs=0.01)
    assert a["saves"][0]["verdict"]["angle_deg"] == pytest.approx(0.0, abs=0.01)
    assert ex["references"]["fluoro_time_s"][0]["value"] == 100


def test_live_state_agrees_with_the_replay(session_ledger):
    path, s = session_ledger
    assert s.teaching.exposures == 5
    # The last save met task B: its cue is on screen for cue_s of wall-clock time, then gone.
    import time
    assert s.teaching.status().cue == "task met: B"
    assert s.teaching.status(time.monotonic() + s.teaching.cue_s + 0.1).cue == ""
    assert [t.state for t in s.teaching.progress.tasks] == ["met", "met", "skipped"]
    conn = open_readonly(path)
    try:
        kinds = [r[0] for r in conn.execute("SELECT kind FROM events WHERE kind IN "
                                            "('trainee', 'exercise_start', 'task_met', 'task_skip', 'exercise_end')")]
        assert trainee_sessions(conn, "ada lovelace") == [1] and trainee_sessions(conn, "Grace") == []
    finally:
        conn.close()
    assert kinds == ["trainee", "exercise_start", "task_met", "task_met", "task_skip", "exercise_end"]


def test_roster_keys_pick_the_trainee_and_start_confirms():
    from teaching_script import EXERCISE, II, KEYMAP

    from appliance.console.state import Console
    from appliance.teaching.live import LiveTeaching
    from drivers.input_event import InputEvent

    console = Console(II, KEYMAP, t0=0.0)
    live = LiveTeaching(KEYMAP, EXERCISE, view_period_s=0.2, trainees=("Ann", "Ben"))
    out = []
    for t, key in ((0.1, "KEY_TAB"), (0.2, "KEY_TAB")):
        out += live.handle(console, InputEvent(t, "keypad", key, True))
    assert out == [] and live.status(0.3).trainee == "Ben? (start to confirm)"
    # Before the start the screen shows what the exercise asks.
    assert live.status(0.3).cue == "three spheres: test" and live.status(0.3).task == "press start for the exercise"
    out = live.handle(console, InputEvent(0.4, "keypad", "KEY_NUMLOCK", True))
    assert [(e.kind, e.detail.get("name"), e.detail.get("source")) for e in out][:1] == [("trainee", "Ben", "keypad")]
    assert out[1].kind == "exercise_start" and out[1].detail["title"] == "three spheres"
    status = live.status(0.5)
    assert status.trainee == "Ben" and status.task == "task 1/3: A" and status.state == "current" and status.cue == ""
    # A second start while the exercise runs does nothing; end ends it once.
    assert live.handle(console, InputEvent(0.6, "keypad", "KEY_NUMLOCK", True)) == []
    assert [e.kind for e in live.handle(console, InputEvent(0.7, "keypad", "KEY_BACKSPACE", True))] == ["exercise_end"]
    assert live.handle(console, InputEvent(0.8, "keypad", "KEY_BACKSPACE", True)) == []
    assert [t.state for t in live.progress.tasks] == ["not done"] * 3
