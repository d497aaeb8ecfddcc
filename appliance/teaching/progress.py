"""One run of an exercise as a state machine: which task is current, and what each save did.

The same machine runs live (the on-screen task and its cue) and when a report replays the
ledger, so what the trainee was told and what the report says cannot differ. Times are the
console's clock (s). Tasks go in order: the first is current at the start; a saved image
that meets the current task completes it and makes the next one current; skip gives the
current one up; ending the exercise leaves the rest not done.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..config.exercise import ExerciseProfile
from .views import Beam, Verdict, judge

#: States of a task.
WAITING, CURRENT, MET, SKIPPED, NOT_DONE = "waiting", "current", "met", "skipped", "not done"


@dataclass
class TaskRun:
    index: int
    name: str
    state: str = WAITING
    started_t: float | None = None
    ended_t: float | None = None
    saves: list[tuple[float, int, Verdict | None]] = field(default_factory=list)   # (t, save number, verdict)


class ExerciseProgress:
    def __init__(self, exercise: ExerciseProfile, t_start: float):
        self.exercise = exercise
        self.t_start = t_start
        self.t_end: float | None = None
        self.tasks = [TaskRun(i, task.name) for i, task in enumerate(exercise.tasks)]
        self._current = 0
        self.tasks[0].state, self.tasks[0].started_t = CURRENT, t_start

    @property
    def current(self) -> TaskRun | None:
        return self.tasks[self._current] if self._current < len(self.tasks) and self.t_end is None else None

    @property
    def finished(self) -> bool:
        return self.current is None

    def _advance(self, t: float, state: str) -> None:
        task = self.tasks[self._current]
        task.state, task.ended_t = state, t
        self._current += 1
        if self._current < len(self.tasks):
            nxt = self.tasks[self._current]
            nxt.state, nxt.started_t = CURRENT, t
        else:
            self.t_end = t

    def save(self, t: float, n: int, beam: Beam | None) -> Verdict | None:
        """A saved image (`beam` None: no tracked image to judge); the verdict on the current task."""
        task = self.current
        if task is None:
            return None
        verdict = judge(self.exercise.tasks[task.index], beam) if beam is not None else None
        task.saves.append((t, n, verdict))
        if verdict is not None and verdict.met:
            self._advance(t, MET)
        return verdict

    def skip(self, t: float) -> TaskRun | None:
        task = self.current
        if task is not None:
            self._advance(t, SKIPPED)
        return task

    def end(self, t: float) -> None:
        if self.t_end is not None:
            return
        for task in self.tasks[self._current:]:
            if task.state == CURRENT:
                task.ended_t = t
            task.state = NOT_DONE
        self.t_end = t

    def met_count(self) -> int:
        return sum(task.state == MET for task in self.tasks)

    def status(self) -> str:
        """One line for the screen: which task, of how many, and its name."""
        task = self.current
        n = len(self.tasks)
        if task is None:
            return f"{self.exercise.title}: done, {self.met_count()}/{n} tasks met"
        return f"task {task.index + 1}/{n}: {task.name}"
