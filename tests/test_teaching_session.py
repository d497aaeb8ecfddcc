"""A scripted teaching session with known presses and poses: counts, times, doses and verdicts
worked out by hand, against what the ledger-based metrics report.

Poses are built from a beam direction and the point the central ray passes through at the
isocentre, so which target is in the field follows from plain geometry: at the isocentre
(620 mm from the focal spot, SID 1000 mm) the widest intensifier field (230 mm at the
detector) has a radius of 115 x 0.62 = 71.3 mm.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.config.exercise import ExerciseProfile
from appliance.console.state import Console
from appliance.records.ledger import Ledger, open_readonly, verify
from appliance.teaching.live import LiveTeaching
from appliance.teaching.metrics import session_metrics, trainee_sessions
from appliance.teaching.views import view_detail
from drivers.input_event import InputEvent

REPO = Path(__file__).resolve().parents[1]
II = load_profile(REPO / "configs/fluoroscopes/generic-ii-carm.yaml", FluoroscopeProfile)
KEYMAP = load_profile(REPO / "configs/keymaps/usb-numeric-keypad.yaml", KeymapProfile)
SOD = 620.0

EXERCISE = ExerciseProfile.model_validate({
    "title": "three spheres", "case": "../cases/child-torso-vcug.yaml", "briefing": "test",
    "tasks": [
        {"name": "A", "target": {"name": "sphere A", "sphere": {"centre_mm": [0, 0, 0], "radius_mm": 10}},
         "field": {"centred_within_mm": 20}, "projection": {"beam_direction": [0, -1, 0], "within_deg": 15}},
        {"name": "B", "target": {"name": "sphere B", "sphere": {"centre_mm": [0, 0, -100], "radius_mm": 10}},
         "field": {"collimated": True, "zoom": [2]}},
        {"name": "C", "target": {"name": "sphere C", "sphere": {"centre_mm": [100, 0, 100], "radius_mm": 10}}},
    ],
    "references": {"fluoro_time_s": {"value": 100, "source": "test"}},
})


def pose(direction, through) -> np.ndarray:
    """T_xray_from_ct for a beam along `direction` (CT frame) whose central ray meets `through`
    at the isocentre distance."""
    z = np.asarray(direction, float) / np.linalg.norm(direction)
    x = np.cross([0.0, 0.0, 1.0], z)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.vstack([x, y, z])
    source = np.asarray(through, float) - SOD * z
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ source
    return T


AP = (0.0, -1.0, 0.0)
P_OFF = pose(AP, (0, 0, 300))
P_A = pose(AP, (0, 0, 0))
P_B = pose(AP, (0, 0, -100))


class Session:
    """Console + teaching + ledger, driven the way the daemon's input and render workers do."""

    def __init__(self, ledger: Ledger):
        self.console = Console(II, KEYMAP, t0=0.0)
        self.teaching = LiveTeaching(KEYMAP, EXERCISE, "exercises/test.yaml", view_period_s=0.2)
        self.ledger = ledger
        self.t = 0.0
        self.pose = P_OFF

    def _record(self, events):
        self.ledger.record(events)

    def press(self, t, key, pressed=True):
        self.advance(t)
        ev = InputEvent(t, "keypad", key, pressed)
        out = self.console.handle(ev)
        out += self.teaching.after(self.console, out)
        out += self.teaching.handle(self.console, ev)
        self._record(out)

    def tap(self, t, key):
        self.press(t, key, True)
        self.press(t + 0.05, key, False)

    def advance(self, until):
        """Frames every 0.1 s; while exposing, each frame's image geometry is offered."""
        while self.t + 0.1 <= until + 1e-9:
            self.t = round(self.t + 0.1, 6)
            out = self.console.tick(self.t)
            state = self.console.snapshot()
            if state.fluoro_on:
                view = view_detail(II, self.pose, state.zoom, state.collimation_mm, t_case_s=self.t)
                out += self.teaching.offer_view(self.console, self.t, view)
            self._record(out)

    def expose(self, t0, t1, pose):
        self.pose = pose
        self.press(t0, "pedal", True)
        self.advance(t1)
        self.press(t1, "pedal", False)


def field_area_cm2(width, height, diameter, steps=4000):
    """Area of a centred rectangle clipped by a centred circle, by the midpoint rule over x,
    scaled from the detector to the reference point (470 mm of 1000 mm), in cm^2."""
    r = diameter / 2
    xs = (np.arange(steps) + 0.5) / steps * min(width / 2, r)
    dx = min(width / 2, r) / steps
    half_h = np.minimum(np.sqrt(np.maximum(r * r - xs * xs, 0)), height / 2)
    return 4 * float(np.sum(half_h) * dx) * 0.47 ** 2 / 100


def typed(text):
    """The key transitions a keyboard-like badge reader sends for `text` and Enter."""
    out = []
    for ch in text:
        key = "KEY_SPACE" if ch == " " else f"KEY_{ch.upper()}"
        if ch.isupper():
            out.append(("KEY_LEFTSHIFT", True))
        out += [(key, True), (key, False)]
        if ch.isupper():
            out.append(("KEY_LEFTSHIFT", False))
    return out + [("KEY_ENTER", True), ("KEY_ENTER", False)]


@pytest.fixture
def session_ledger(tmp_path):
    path = tmp_path / "ledger.sqlite"
    with Ledger(path) as ledger:
        ledger.start_session("trainee", "child", II.name, 1.7e9, t_monotonic=0.0)
        s = Session(ledger)
        # The badge reader types "Ada Lovelace" and Enter before anything else.
        for i, (key, pressed) in enumerate(typed("Ada Lovelace")):
            s.press(0.3 + 0.005 * i, key, pressed)
        s.tap(1.0, "KEY_NUMLOCK")                  # exercise start
        s.expose(2.0, 4.0, P_OFF)                  # 1: blank
        s.expose(5.0, 8.0, P_A)                    # 2: A in the field
        s.tap(9.0, "KEY_KPPLUS")                   # save 1 (held): A met
        s.tap(10.0, "KEY_KP2")                     # zoom 2
        s.expose(11.0, 13.0, P_B)                  # 3: B, not collimated
        s.tap(13.5, "KEY_KPPLUS")                  # save 2: B not met (not collimated)
        s.tap(14.0, "KEY_KP9")                     # blades in 10 mm horizontally
        s.expose(15.0, 16.0, P_B)                  # 4
        s.tap(16.5, "KEY_KPPLUS")                  # save 3: B met
        s.tap(17.0, "KEY_KP8")                     # skip C: the exercise ends
        s.expose(18.0, 19.0, P_A)                  # 5: after the exercise
        s.advance(20.0)
        ledger.record(s.console.end(20.0))
        ledger.end_session(1.7e9 + 20.0)
    return path, s


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
    kerma = 8.0 / 60 * (2 + 3) + 11.0 / 60 * (2 + 1 + 1)
    assert whole["air_kerma_mgy"] == pytest.approx(kerma, rel=1e-9)
    a1, a2 = field_area_cm2(230, 230, 230), field_area_cm2(170, 170, 170)
    a2c = field_area_cm2(160, 170, 170)
    dap = (8.0 / 60 * 5 * a1 + 11.0 / 60 * 2 * a2 + 11.0 / 60 * 2 * a2c) / 1000
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
    assert [t.state for t in s.teaching.progress.tasks] == ["met", "met", "skipped"]
    conn = open_readonly(path)
    try:
        kinds = [r[0] for r in conn.execute("SELECT kind FROM events WHERE kind IN "
                                            "('trainee', 'exercise_start', 'task_met', 'task_skip', 'exercise_end')")]
        assert trainee_sessions(conn, "ada lovelace") == [1] and trainee_sessions(conn, "Grace") == []
    finally:
        conn.close()
    assert kinds == ["trainee", "exercise_start", "task_met", "task_met", "task_skip", "exercise_end"]
