"""The phase worker: the clock and the console's breath hold -> which phase of the 4D CT to draw now."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from ..console.state import ConsoleState
from ..errors import FluorosimError
from .handoff import LatestValue, PhaseValue
from .parts import Parts
from .worker import Worker

#: How often the worker looks up the patient's phase (s).
PHASE_PERIOD_S = 0.02
#: How long it waits before looking again while no phase is prepared yet (s).
NOT_READY_RETRY_S = 0.1
#: The case times ahead of now (s) whose phases are handed on as `upcoming`: a view held at rest
#: casts them beside the live frames (ProgressiveRenderer.render) before breathing brings them.
#: One phase's cast at the adult chest's 512 matrix takes about 0.1 s so on two cores; a breath
#: of the shipped cases moves to its next state every 0.3-0.7 s, and in steps of 0.1 s even a
#: breath twice as fast skips none.
LOOKAHEAD_S = (0.1, 0.2, 0.3, 0.4)


class PhaseWorker(Worker):
    """time since the case started -> PhaseTimeline.at() -> `phases`; the timeline's own thread
    loads and prepares the phases, so this only looks up what is ready.

    Owns the case clock, which runs on the appliance clock (`clock`, the console's) from the
    session's start (`parts.t0`): one clock for the console, the scripted input, the camera path
    and the patient, so a phase window of an exercise means the same second to all of them.
    A breath hold on a case breathing under the model stops the breath only (the contrast's
    timeline goes on, as a bladder keeps filling while a child holds its breath); on a 4D CT,
    whose phases carry breath and everything else together, it freezes the whole patient where
    it is and the case resumes from there. A new case (reload) starts at its time 0.
    """

    def __init__(self, parts: Parts, console_state: LatestValue[ConsoleState], phases: LatestValue[PhaseValue],
                 clock: Callable[[], float] = time.monotonic):
        super().__init__("phases")
        self.parts, self.console_state, self.phases = parts, console_state, phases
        self.case_clock = clock     # not `clock`: the worker's heartbeat keeps the wall clock
        t0 = getattr(parts, "t0", 0.0)
        self._case_t0 = t0 if t0 else clock()
        self._hold_t: float | None = None
        self._case_started: LatestValue[float] = LatestValue("case started")
        self._case_started_seq = 0
        # Console presses of the breathing keys already handed to the breathing model.
        self._breath_steps = (0, 0)
        self._held_control: Any = None     # the breathing model this worker holds (BreathingControl)

    def restart_case(self) -> None:
        """The case was replaced (from another thread): its time starts again now."""
        self._case_started.put(self.case_clock())

    def step(self) -> bool:
        restarted = self._case_started.newer(self._case_started_seq)
        if restarted is not None:
            t0, self._case_started_seq = restarted
            self._case_t0 = t0 if t0 is not None else self._case_t0
        state, _ = self.console_state.get()
        t = self.case_clock() - self._case_t0
        control = getattr(self.parts.timeline, "control", None)     # a breathing model, when the case has one
        hold = state is not None and state.breath_hold
        if control is not None:
            # At the console's time of the press, not when this worker sees it (a busy machine may
            # see it a breath later).
            at = min(t, state.breath_changed_t - self._case_t0) if state is not None else t
            if hold and self._held_control is not control:       # a new timeline (reload) is held too
                control.hold(at)
                self._held_control = control
            elif not hold and self._held_control is not None:
                if self._held_control is control:
                    control.resume(at)
                self._held_control = None
        elif hold:
            if self._hold_t is None:
                self._hold_t = t
            t = self._hold_t
        elif self._hold_t is not None:
            self._case_t0 += t - self._hold_t  # breathing resumes where the hold began
            t = self._hold_t
            self._hold_t = None
        generation = self.parts.generation
        if control is not None and state is not None:
            # At the press's console time too, so a busy worker does not shift the breath's phase.
            self._apply_breath_keys(control, state, min(t, state.breath_step_t - self._case_t0))
        try:
            a, b, weight = self.parts.timeline.at(t)
        except FluorosimError:
            self.sleep(NOT_READY_RETRY_S)
            return False
        text = control.overlay_text(t) if control is not None else ""
        inspired = control.at(t).inspired if control is not None else None
        # A 4D CT held by the console stands still at its hold's time: nothing is coming.
        upcoming = () if hold and control is None else self._upcoming(t, (a, b))
        self.phases.put(PhaseValue(a, b, float(weight), generation, t_case_s=t, breathing=text, inspired=inspired,
                                   upcoming=upcoming))
        self.sleep(PHASE_PERIOD_S)
        return True

    def _upcoming(self, t: float, now: tuple) -> tuple:
        """The phases the timeline gives within LOOKAHEAD_S of case time `t` that are not in
        `now`, nearest first; looking ahead does not steer the timeline's loader."""
        ahead: list = []
        for dt in LOOKAHEAD_S:
            try:
                phases = self.parts.timeline.at(t + dt, steer=False)[:2]
            except FluorosimError:
                break
            ahead += [p for p in phases if p is not None and p not in now and p not in ahead]
        return tuple(ahead)

    def _apply_breath_keys(self, control, state: ConsoleState, t: float) -> None:
        """Each faster/slower/deeper/shallower press since the last look, applied at case time t."""
        rate, depth = state.breath_rate_steps, state.breath_depth_steps
        done_rate, done_depth = self._breath_steps
        for _ in range(abs(rate - done_rate)):
            (control.faster if rate > done_rate else control.slower)(t)
        for _ in range(abs(depth - done_depth)):
            (control.deeper if depth > done_depth else control.shallower)(t)
        self._breath_steps = (rate, depth)
