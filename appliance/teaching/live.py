"""The teaching side of the console, live: trainee name, exercise keys, view records, the cue.

`LiveTeaching` runs beside the console in the input worker. It turns the keymap's
exercise keys (`exercise_start`, `exercise_skip`, `exercise_end`, `trainee_next`) and the
characters a keyboard-like badge or barcode reader types into ledger records through
`Console.note`, so they sit in the hash chain in order with the doses. The render worker
offers it the geometry of each image it shows (`offer_view`); it records at most one per
`view_period_s` (and always the first of an exposure), and for every save the view of the
image saved, judged at once against the current task: a met task gives the on-screen cue.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from drivers.input_event import InputEvent

from ..config.exercise import ExerciseProfile
from ..console.keys import action_for
from .progress import ExerciseProgress
from .views import Beam

#: Actions of the keymap that belong to teaching, not to the fluoroscope.
TEACHING_ACTIONS = ("exercise_start", "exercise_skip", "exercise_end", "trainee_next")

#: evdev keys a keyboard-like badge reader types, and the character each stands for.
_LETTERS = {f"KEY_{c}": c.lower() for c in "ABCDEFGHIJKLMNOPQRSTUVWXYZ"}
_DIGITS = {f"KEY_{d}": d for d in "0123456789"}
_PUNCT = {"KEY_SPACE": " ", "KEY_MINUS": "-", "KEY_DOT": ".", "KEY_APOSTROPHE": "'", "KEY_COMMA": ","}
CHARACTER_KEYS = {**_LETTERS, **_DIGITS, **_PUNCT}
SHIFT_KEYS = ("KEY_LEFTSHIFT", "KEY_RIGHTSHIFT")
#: Every key a badge reader's events may carry.
BADGE_KEYS = frozenset(CHARACTER_KEYS) | frozenset(SHIFT_KEYS) | {"KEY_ENTER", "KEY_BACKSPACE"}
#: Longest name kept (characters): a badge reader that never sends Enter does not grow a record forever.
MAX_NAME = 64


class NameEntry:
    """Characters typed by a badge or barcode reader (an evdev keyboard), Enter ends a name."""

    def __init__(self):
        self.typed = ""
        self._shift = 0

    def feed(self, event: InputEvent) -> str | None:
        """One key transition; the whole name when Enter ends it, else None."""
        key = event.key
        if key in SHIFT_KEYS:
            self._shift += 1 if event.pressed else -1
            self._shift = max(self._shift, 0)
            return None
        if not event.pressed:
            return None
        if key == "KEY_ENTER":
            name, self.typed = " ".join(self.typed.split()), ""
            return name or None
        if key == "KEY_BACKSPACE":
            self.typed = self.typed[:-1]
        elif key in CHARACTER_KEYS and len(self.typed) < MAX_NAME:
            c = CHARACTER_KEYS[key]
            self.typed += c.upper() if self._shift else c
        return None


@dataclass(frozen=True)
class TeachingStatus:
    """What the screen shows of teaching: the shot counter, the task line and the cue."""

    exposures: int
    trainee: str
    task: str           # "" when no exercise runs
    state: str          # "", "current", "done"
    cue: str            # "" or e.g. "task met: early filling AP"


class LiveTeaching:
    def __init__(self, keymap, exercise: ExerciseProfile | None, exercise_path: str = "", *,
                 view_period_s: float = 0.2, trainees: tuple[str, ...] = (), cue_s: float = 2.0):
        self.keymap = keymap
        self.exercise = exercise
        self.exercise_path = exercise_path
        self.view_period_s = view_period_s
        self.trainees = tuple(trainees)
        self.cue_s = cue_s
        self.names = NameEntry()
        self.trainee = ""
        self._roster_index: int | None = None
        self.progress: ExerciseProgress | None = None
        self.exposures = 0
        self._last_view_t = -1e300
        self._latest_view: dict | None = None
        self._exposing = False
        self._cue = ("", -1e300)

    # --- input ----------------------------------------------------------------------------
    def handle(self, console, event: InputEvent) -> list:
        """Teaching keys and badge characters (others are the console's); ledger events out."""
        t = event.t_monotonic
        action = None if event.source == "badge" else action_for(self.keymap, event.key)
        if action is None:
            name = self.names.feed(event)
            return self.set_trainee(console, t, name, "badge") if name else []
        if not event.pressed or action not in TEACHING_ACTIONS:
            return []
        if action == "trainee_next":
            if self.trainees:
                self._roster_index = 0 if self._roster_index is None else (self._roster_index + 1) % len(self.trainees)
            return []
        if action == "exercise_start":
            out = []
            if self._roster_index is not None:
                out += self.set_trainee(console, t, self.trainees[self._roster_index], "keypad")
                self._roster_index = None
            return out + self.start(console, t)
        if action == "exercise_skip":
            return self.skip(console, t)
        return self.end(console, t)

    def set_trainee(self, console, t: float, name: str, source: str) -> list:
        self.trainee = name
        return console.note(t, "trainee", name=name, source=source)

    def start(self, console, t: float) -> list:
        if self.exercise is None or (self.progress is not None and not self.progress.finished):
            return []
        self.progress = ExerciseProgress(self.exercise, t)
        return console.note(t, "exercise_start", title=self.exercise.title, path=self.exercise_path,
                            profile=self.exercise.model_dump(mode="json"))

    def skip(self, console, t: float) -> list:
        if self.progress is None or self.progress.finished:
            return []
        task = self.progress.skip(t)
        assert task is not None     # not finished: there is a current task
        out = console.note(t, "task_skip", task=task.index, name=task.name)
        if self.progress.finished:
            out += console.note(t, "exercise_end", reason="all tasks done")
        return out

    def end(self, console, t: float) -> list:
        if self.progress is None or self.progress.t_end is not None:
            return []
        self.progress.end(t)
        return console.note(t, "exercise_end", reason="ended")

    # --- what the console did ---------------------------------------------------------------
    def after(self, console, events: list) -> list:
        """Follow the console's events: count exposures, and judge each save's image."""
        out = []
        for ce in events:
            if ce.kind == "fluoro_on" and ce.detail.get("reason") == "pressed":
                self.exposures += 1
                self._exposing = True
                self._last_view_t = -1e300     # the first image of each exposure is recorded
            elif ce.kind == "fluoro_off" and ce.detail.get("reason") not in ("settings changed", "profile reloaded"):
                self._exposing = False
            elif ce.kind == "save":
                out += self._save(console, ce.t_monotonic, int(ce.detail.get("n", 0)))
        return out

    def _save(self, console, t: float, n: int) -> list:
        view = self._latest_view
        out = console.note(t, "save_view", n=n, view=view)
        if self.progress is None or self.progress.finished:
            return out
        task = self.progress.current
        assert task is not None     # not finished: there is a current task
        verdict = self.progress.save(t, n, Beam.of(view) if view is not None else None)
        if verdict is not None and verdict.met:
            out += console.note(t, "task_met", task=task.index, name=task.name, n=n)
            self._cue = (f"task met: {task.name}", time.monotonic())
            if self.progress.finished:
                out += console.note(t, "exercise_end", reason="all tasks done")
        elif verdict is not None:
            self._cue = ("not yet: " + "; ".join(verdict.reasons[:2]), time.monotonic())
        return out

    def offer_view(self, console, t: float, view: dict) -> list:
        """The geometry of an image just shown (a `views.view_detail`); recorded when due."""
        self._latest_view = view
        if t - self._last_view_t < self.view_period_s:
            return []
        out = console.note(t, "view", **view)
        # The console records it no earlier than its own time: space the records by that time.
        self._last_view_t = out[-1].t_monotonic
        return out

    # --- the screen -------------------------------------------------------------------------
    def status(self, wall_now: float | None = None) -> TeachingStatus:
        """What the screen shows now; the cue lasts `cue_s` of wall-clock time (time.monotonic), as the
        saved-image flash does, whatever the console's clock rate."""
        now = time.monotonic() if wall_now is None else wall_now
        cue, t_cue = self._cue
        trainee = self.trainee
        if self._roster_index is not None:
            trainee = f"{self.trainees[self._roster_index]}? (start to confirm)"
        elif self.names.typed:
            trainee = self.names.typed + "_"
        if self.progress is None:
            task, state = ("press start for the exercise" if self.exercise is not None else ""), ""
            if self.exercise is not None and not self._exposing and not cue:
                # Before the start, and never over a live image: what the exercise asks.
                cue, t_cue = f"{self.exercise.title}: {' '.join(self.exercise.briefing.split())}", now
        else:
            task, state = self.progress.status(), ("done" if self.progress.finished else "current")
        return TeachingStatus(self.exposures, trainee, task, state, cue if now - t_cue < self.cue_s else "")


def same_patient(case_path, case) -> bool:
    """Whether the case profile at `case_path` shows the same patient as `case`: the same built-in
    patient lying the same way in the box (its breathing may differ: the built-in child's own
    4 s breath or the controllable one), so an exercise's targets (CT mm) and phase windows
    (the built-in study's timeline, which breathing does not change) hold on both."""
    from ..config.case import CaseProfile
    from ..config.loading import load_profile
    from ..errors import FluorosimError

    if case.builtin is None:
        return False
    try:
        other = load_profile(case_path, CaseProfile)
    except FluorosimError:
        return False
    return other.builtin == case.builtin and other.T_phantom_from_ct == case.T_phantom_from_ct


def live_teaching_for(cfg) -> LiveTeaching:
    """The live teaching of an ApplianceConfig: its exercise (when written for the active case) and settings."""
    import logging

    t = cfg.appliance.teaching
    exercise = cfg.exercise
    if exercise is not None and cfg.exercise_path is not None:
        case_of_exercise = (cfg.exercise_path.parent / exercise.case).resolve()
        if case_of_exercise != cfg.case_path.resolve() and not same_patient(case_of_exercise, cfg.case):
            logging.getLogger(__name__).warning("%s is written for %s, not the active case %s; no exercise offered",
                                                cfg.exercise_path, case_of_exercise, cfg.case_path)
            exercise = None
    path = "" if cfg.exercise_path is None else str(cfg.exercise_path)
    return LiveTeaching(cfg.keymap, exercise, path, view_period_s=t.view_period_s, trainees=tuple(t.trainees), cue_s=t.cue_s)
