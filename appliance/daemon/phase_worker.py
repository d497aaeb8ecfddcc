"""The phase worker: the clock and the console's breath hold -> which phase of the 4D CT to draw now."""

from __future__ import annotations

import time

from ..console.state import ConsoleState
from ..errors import FluorosimError
from .handoff import LatestValue, PhaseValue
from .parts import Parts
from .worker import Worker

#: How often the worker looks up the patient's phase (s).
PHASE_PERIOD_S = 0.02
#: How long it waits before looking again while no phase is prepared yet (s).
NOT_READY_RETRY_S = 0.1


class PhaseWorker(Worker):
    """time since the case started -> PhaseTimeline.at() -> `phases`; the timeline's own thread
    loads and prepares the phases, so this only looks up what is ready.

    Owns the case clock: a breath hold freezes the patient where it is and breathing resumes
    from there; a new case (reload) starts at its time 0.
    """

    def __init__(self, parts: Parts, console_state: LatestValue[ConsoleState], phases: LatestValue[PhaseValue]):
        super().__init__("phases")
        self.parts, self.console_state, self.phases = parts, console_state, phases
        self._case_t0 = time.monotonic()
        self._hold_t: float | None = None
        self._case_started: LatestValue[float] = LatestValue("case started")
        self._case_started_seq = 0

    def restart_case(self) -> None:
        """The case was replaced (from another thread): its time starts again now."""
        self._case_started.put(time.monotonic())

    def step(self) -> bool:
        restarted = self._case_started.newer(self._case_started_seq)
        if restarted is not None:
            t0, self._case_started_seq = restarted
            self._case_t0 = t0 if t0 is not None else self._case_t0
        state, _ = self.console_state.get()
        t = time.monotonic() - self._case_t0
        if state is not None and state.breath_hold:
            if self._hold_t is None:
                self._hold_t = t
            t = self._hold_t
        elif self._hold_t is not None:
            self._case_t0 += t - self._hold_t  # breathing resumes where the hold began
            t = self._hold_t
            self._hold_t = None
        generation = self.parts.generation
        try:
            a, b, weight = self.parts.timeline.at(t)
        except FluorosimError:
            self.sleep(NOT_READY_RETRY_S)
            return False
        self.phases.put(PhaseValue(a, b, float(weight), generation))
        self.sleep(PHASE_PERIOD_S)
        return True
