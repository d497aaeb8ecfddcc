"""A scripted teaching session for the tests: console, live teaching and a real ledger,
driven with known presses and poses the way the daemon's input and render workers drive them.

Poses are built from a beam direction and the point the central ray passes through at the
isocentre, so which target is in the field follows from plain geometry: at the isocentre
(620 mm from the focal spot, SID 1000 mm) the widest intensifier field (230 mm at the
detector) has a radius of 115 x 0.62 = 71.3 mm.
"""

from pathlib import Path

import numpy as np

from appliance.config import FluoroscopeProfile, KeymapProfile, load_profile
from appliance.config.exercise import ExerciseProfile
from appliance.console.state import Console
from appliance.records.ledger import Ledger
from appliance.teaching.live import LiveTeaching
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


def scripted_session(path: Path, t_wall: float = 1.7e9) -> "Session":
    """Session 1 of a fresh ledger at `path`: the script the metrics tests work out by hand."""
    with Ledger(path) as ledger:
        ledger.start_session("trainee", "child", II.name, t_wall, t_monotonic=0.0)
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
        s.tap(17.0, "KEY_F9")                      # skip C: the exercise ends
        s.expose(18.0, 19.0, P_A)                  # 5: after the exercise
        s.advance(20.0)
        ledger.record(s.console.end(20.0))
        ledger.end_session(t_wall + 20.0)
    return s
