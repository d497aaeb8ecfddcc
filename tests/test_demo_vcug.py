"""The demo's scripted VCUG: the shipped keypad script and camera path, on one clock, played
through the real console, the real trajectory and the live teaching, meet the exercise's tasks.

Ground truth: each still pose of configs/trajectories/vcug-demo.jsonl was solved by hand to put
its task's target on the central ray; here the exercise's own rules (field, projection, zoom,
collimation, phase window of the case's 32 s VCUG) judge the saved views, with the case time
the console time, as the daemon's phase worker now keeps it.
"""

from pathlib import Path

import pytest

from appliance.config import load_appliance
from appliance.config.base import matrix
from appliance.console.state import Console
from appliance.daemon.parts import rendered_fluoroscope
from appliance.daemon.snapshots import roll_deg
from appliance.teaching.live import live_teaching_for
from appliance.teaching.views import view_detail
from appliance.tracking.trajectory import load_trajectory
from drivers.scripted_input import ScriptedInput

REPO = Path(__file__).resolve().parents[1]
#: The console's tick (s), and every how many ticks an exposure's view is offered (the
#: teaching records one per 0.2 s): coarser than the daemon's, for speed; the script's
#: windows are seconds wide and its poses still for seconds around each save.
FRAME_S = 0.05
VIEW_EVERY = 5


@pytest.fixture(scope="module")
def played():
    """The demo session frame by frame: console events, teaching records and the live views."""
    cfg = load_appliance(REPO / "configs" / "appliance-demo.yaml")
    fl = rendered_fluoroscope(cfg)
    path = load_trajectory(cfg.resolve(cfg.appliance.devices.camera.trajectory))
    script = ScriptedInput(cfg.resolve(cfg.appliance.devices.keypad.script), t0=0.0)
    console = Console(cfg.fluoroscope, cfg.keymap, t0=0.0)
    teaching = live_teaching_for(cfg)
    T_phantom_from_ct = matrix(cfg.case.T_phantom_from_ct)
    now, events, rolls, tick = 0.0, [], {}, 0
    while not script.finished:
        now += FRAME_S
        tick += 1
        for e in script.poll(now):
            done = console.handle(e)
            events += done + teaching.after(console, done) + teaching.handle(console, e)
        events += console.tick(now)
        s = console.snapshot()
        if s.fluoro_on and tick % VIEW_EVERY == 0:
            T_webcam = path(now)
            rolls[round(roll_deg(T_webcam))] = now
            T = fl.T_xray_from_webcam() @ T_webcam @ T_phantom_from_ct
            events += teaching.offer_view(console, now, view_detail(fl, T, s.zoom, s.collimated_mm, now))
    return cfg, console, teaching, events, rolls


def test_the_demo_teaching_case_is_the_exercise_patient(played):
    cfg, _, teaching, _, _ = played
    # The demo breathes under the model; the VCUG exercise, written for the built-in child, is offered on it.
    assert cfg.case.respiration is not None and cfg.case.builtin == "child-torso"
    assert teaching.exercise is not None and teaching.exercise.title.startswith("VCUG")


def test_a_good_trainee_meets_every_task_of_the_vcug(played):
    _, _, teaching, events, _ = played
    progress = teaching.progress
    assert progress is not None and progress.finished
    met = [e.detail.get("name") for e in events if e.kind == "task_met"]
    assert met == [t.name for t in progress.exercise.tasks]
    assert progress.met_count() == len(progress.tasks) == 5


def test_the_session_keeps_the_alarm_and_the_snapshots_states(played):
    _, console, _, events, rolls = played
    kinds = [e.kind for e in events]
    s = console.snapshot()
    # The script's own sum: 9 + 3 + 3 + 7 + 7 + 6 + 2.5 + 10 + 10 + 100 + 20 + 132.5 s.
    assert s.fluoro_time_s == pytest.approx(310.0, abs=0.05)
    alarms = [e for e in events if e.kind == "alarm"]
    assert len(alarms) == 1 and alarms[0].t_monotonic == pytest.approx(394.5, abs=1e-6)
    assert kinds.count("save") == 6 and kinds.count("hold_breath") == 3 == kinds.count("resume_breath")
    # Both laterals are exposed (the +-90 degree snapshots).
    assert max(rolls) > 75 and min(rolls) < -75


def test_breath_holds_stop_on_the_contract_times(played):
    """The pair's holds fall on end-expiration (3/(4f) + k/f) and end-inspiration (1/(4f) + k/f)
    of the case's breath, and every hold lasts whole breaths, so the breath keeps those times."""
    cfg, _, _, events, _ = played
    f = cfg.case.respiration.rate_per_min / 60.0
    holds = [e.t_monotonic for e in events if e.kind == "hold_breath"]
    resumes = [e.t_monotonic for e in events if e.kind == "resume_breath"]
    assert len(holds) == len(resumes) == 3
    for h, r in zip(holds, resumes):
        assert (r - h) * f == pytest.approx(round((r - h) * f), abs=1e-6) and r > h
    expiration, inspiration = holds[0], holds[1]
    assert ((expiration * f) - 0.75) % 1.0 == pytest.approx(0.0, abs=1e-6)
    assert ((inspiration * f) - 0.25) % 1.0 == pytest.approx(0.0, abs=1e-6)
