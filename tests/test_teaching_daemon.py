"""The running appliance records what teaching needs: the trainee typed on a badge reader, the
exercise's start, one view per live image (at most one per view period) with its pose and
case time, each save's view and verdict; the exercise ends when the appliance stops."""

import json
import threading
import time

from appliance_setup import make_appliance

from appliance.daemon.notify import Notifier
from appliance.daemon.pipeline import Appliance
from appliance.daemon.reload import ProfileKeeper
from appliance.records.ledger import open_readonly, verify
from appliance.teaching.metrics import session_metrics

EXERCISE = """title: Cylinder drill
case: ../cases/cylinder.yaml
briefing: Find the water cylinder.
tasks:
  - name: cylinder
    target:
      name: water cylinder
      sphere: {centre_mm: [0, 0, 0], radius_mm: 80}
  - name: nowhere
    target:
      name: a point far outside the box
      sphere: {centre_mm: [0, 0, 5000], radius_mm: 5}
"""

SCRIPT = [
    '{"t": 0.1, "key": "KEY_LEFTSHIFT", "pressed": true}', '{"t": 0.12, "tap": "KEY_B", "tap_s": 0.01}',
    '{"t": 0.14, "key": "KEY_LEFTSHIFT", "pressed": false}', '{"t": 0.16, "tap": "KEY_O", "tap_s": 0.01}',
    '{"t": 0.18, "tap": "KEY_ENTER", "tap_s": 0.01}',
    '{"t": 0.3, "tap": "KEY_NUMLOCK"}',
    '{"t": 0.5, "hold": "pedal", "for_s": 2.0}',
    '{"t": 3.0, "tap": "KEY_KPPLUS"}',
    '{"t": 3.5, "hold": "pedal", "for_s": 1.0}',
    '{"t": 5.0, "tap": "KEY_KPPLUS"}',
]


def test_the_appliance_records_the_exercise_views_and_verdicts(tmp_path):
    config = make_appliance(tmp_path, script=SCRIPT)
    (config.parent / "exercises" / "cylinder.yaml").write_text(EXERCISE)
    text = config.read_text()
    config.write_text(text + "teaching:\n  exercise: exercises/cylinder.yaml\n  view_period_s: 0.5\n")
    app = Appliance(ProfileKeeper(config), Notifier({}))
    stop = threading.Event()
    runner = threading.Thread(target=app.run, kwargs={"until": stop.is_set, "signals": False})
    runner.start()
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (app.parts.keypad.finished and app.clock() > 6.0):
            time.sleep(0.1)
        status, _ = app.teaching_status.get()
        assert status is not None and status.exposures == 2 and status.trainee == "Bo"
        assert status.task == "task 2/2: nowhere"
    finally:
        stop.set()
        runner.join(20)
    assert not runner.is_alive()
    conn = open_readonly(tmp_path / "data" / "ledger.sqlite")
    try:
        assert verify(conn).ok
        events = [(r[0], r[1], json.loads(r[2])) for r in conn.execute(
            "SELECT kind, t_monotonic, detail FROM events WHERE session_id = 1 ORDER BY id")]
        m = session_metrics(conn, 1)
    finally:
        conn.close()
    kinds = [k for k, _, _ in events]
    assert kinds.count("trainee") == 1 and events[kinds.index("trainee")][2]["name"] == "Bo"
    assert kinds.index("exercise_start") < kinds.index("fluoro_on")
    views = [(t, d) for k, t, d in events if k == "view"]
    # Two exposures of 2 s and 1 s with a view at most every 0.5 s, the first of each always.
    assert 2 <= len(views) <= 3 + 2 + 2
    assert all(b - a >= 0.5 - 1e-9 for (a, _), (b, _) in zip(views, views[1:]) if b - a < 0.9)
    first = views[0][1]
    assert first["zoom"] == 1 and first["t_case_s"] is not None and len(first["T_xray_from_ct"]) == 3
    save_views = [d for k, _, d in events if k == "save_view"]
    assert [d["n"] for d in save_views] == [1, 2] and all(d["view"] is not None for d in save_views)
    met = [d for k, _, d in events if k == "task_met"]
    assert [d["name"] for d in met] == ["cylinder"]
    assert kinds[-3:] == ["exercise_end", "fluoro_off", "session_end"] or kinds[-2:] == ["exercise_end", "session_end"]
    ex = m["exercises"][0]
    assert [t["state"] for t in ex["tasks"]] == ["met", "not done"]
    assert m["metrics"]["exposures"] == 2 and m["metrics"]["blank_exposures"] == 0
    assert m["session"]["trainee"] == "Bo"


def test_a_badge_readers_keys_name_the_trainee_and_never_reach_the_console(tmp_path):
    """A keymap that maps KEY_F to fluoroscopy, and a badge that types "Fay": the name is
    recorded, and no exposure starts."""
    import queue

    from appliance_setup import REPO

    from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
    from appliance.console.alarm_sound import AlarmSound
    from appliance.console.state import Console
    from appliance.daemon.handoff import LatestValue
    from appliance.daemon.input_worker import InputWorker
    from appliance.teaching.live import LiveTeaching
    from drivers.input_event import NoInput
    from drivers.scripted_input import ScriptedInput

    fl = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
    keymap = KeymapProfile(name="test", keys={"KEY_F": "fluoro", "KEY_KPPLUS": "save"})
    script = tmp_path / "badge.jsonl"
    script.write_text("\n".join([
        '{"t": 0.1, "key": "KEY_LEFTSHIFT", "pressed": true}', '{"t": 0.11, "key": "KEY_F", "pressed": true}',
        '{"t": 0.12, "key": "KEY_F", "pressed": false}', '{"t": 0.13, "key": "KEY_LEFTSHIFT", "pressed": false}',
        '{"t": 0.14, "tap": "KEY_A", "tap_s": 0.01}', '{"t": 0.16, "tap": "KEY_Y", "tap_s": 0.01}',
        '{"t": 0.18, "tap": "KEY_ENTER", "tap_s": 0.01}']) + "\n")
    badge = ScriptedInput(script, t0=0.0)
    badge.source = "badge"       # as the evdev BadgeReader names its events
    now = [0.0]
    console = Console(fl, keymap, t0=0.0)
    events: queue.Queue = queue.Queue()
    worker = InputWorker(console, [NoInput()], AlarmSound(), lambda: now[0], console_state=LatestValue("c"),
                         events=events, fluoroscope=LatestValue("f"), exposure_factor=LatestValue("e"),
                         teaching=LiveTeaching(keymap, None), teaching_status=LatestValue("t"), badge=badge)
    for step in range(1, 40):
        now[0] = step * 0.01
        worker.step()
    recorded = []
    while not events.empty():
        recorded.append(events.get_nowait().event)
    kinds = [e.kind for e in recorded]
    assert "fluoro_on" not in kinds and console.snapshot().runs == 0
    assert [e.detail for e in recorded if e.kind == "trainee"] == [{"name": "Fay", "source": "badge"}]
