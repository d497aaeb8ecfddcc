"""A one-CT case breathing under the console's control, as the daemon's patient timeline.

The CT (end-expiration) is moved once to `depth_states` states evenly spaced from
end-expiration to the deepest breath the console allows (depth_max), each prepared on the
device by one background thread, end-expiration first. A frame then costs no more than a
4D CT's: `at(t)` asks the BreathingControl where the breath is and hands the renderer the two
states either side with the weight between them (blended in projection space by the
renderer's existing phase blend). Same interface as PhaseTimeline.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
from collections.abc import Callable
from functools import partial

import numpy as np

from ..config.case import Materials, Respiration
from ..errors import FluorosimError
from .breathing_motion import BreathingAnatomy
from .heap import release_freed
from .respiration import BreathingControl, BreathState, muscle_amplitudes
from .timeline import Timeline
from .volume import Volume

log = logging.getLogger(__name__)


class BreathingTimeline:
    """The breathing patient: precomputed depth states, picked and weighted by the live breath.

    `source` is the end-expiration CT's loader, or the stages of a study on its own clock
    (e.g. the built-in patient's VCUG: (time_s, loader) of each stage at end-expiration,
    repeating every `cycle_s`); each stage gets its own depth states, the motion split once
    from the first stage (later stages differ from it in soft tissue and contrast only).
    """

    def __init__(self, source, params: Respiration, materials: Materials, renderer,
                 load_labels: Callable[[Volume], np.ndarray | None] | None = None, control: BreathingControl | None = None,
                 cycle_s: float | None = None):
        self.params = params
        self.control = control or BreathingControl(params)
        self.renderer = renderer
        stages = [(0.0, source)] if callable(source) else list(source)
        if not stages:
            raise FluorosimError("a breathing timeline needs at least one CT")
        self.stage_times = [float(t) for t, _ in stages]
        self._loaders = [loader for _, loader in stages]
        self.cycle_s = cycle_s if cycle_s is not None else math.inf
        n = params.depth_states
        #: Excursion (multiple of the profile's full breath) of each state.
        self.excursions = [params.depth_max * k / (n - 1) for k in range(n)]
        self._load_labels, self._materials = load_labels, materials
        self._states: list[list] = [[None] * n for _ in stages]
        self._prepared = self._states[0]          # the first stage's states (what a one-CT case has)
        self._wanted = 0
        self._error: str | None = None
        self._cond = threading.Condition()
        self._stop = False
        self.period_s = 60.0 / params.rate_per_min if params.rate_per_min > 0 else math.inf
        self._thread = threading.Thread(target=self._run, name="breathing-states", daemon=True)
        self._thread.start()

    def state_of(self, excursion: float) -> BreathState:
        """The anatomy at `excursion` (multiple of the profile's full breath): every muscle scales with it."""
        g, lam, d = muscle_amplitudes(self.params)
        inspired = min(excursion, 1.0)
        depth = excursion / inspired if excursion > 1.0 else 1.0
        return BreathState(0.0, 0.0, inspired, depth, self.params.rate_per_min, False,
                           g * excursion, lam * excursion, d * excursion - d * depth / 2.0, d * excursion)

    def _next_stage(self) -> int | None:
        n = len(self._states)
        with self._cond:
            for step in range(n):          # the stage wanted now, then the ones after it
                j = (self._wanted + step) % n
                if any(p is None for p in self._states[j]):
                    return j
        return None

    def _run(self) -> None:
        self._build()
        release_freed()     # the end-expiration CT and the breathing model built from it are gone too

    def _build(self) -> None:
        try:
            ct = self._loaders[0]()
            labels = self._load_labels(ct) if self._load_labels else None
            anatomy = BreathingAnatomy(ct, self.params, self._materials, labels)
            while not self._stop:
                j = self._next_stage()
                if j is None:
                    return
                soft = None if j == 0 else anatomy.soft_of(self._loaders[j]())
                for k, e in enumerate(self.excursions):
                    if self._stop:
                        return
                    prepared = self.renderer.prepare(anatomy.volume_at(self.state_of(e), soft))
                    prepared.time_s = self.stage_times[j]
                    release_freed()     # the deformed CT and its temporaries are gone; their pages too
                    with self._cond:
                        self._states[j][k] = prepared
                        self._cond.notify_all()
        except FluorosimError as e:
            log.error("breathing states: %s", e)
            with self._cond:
                self._error = str(e)
                self._cond.notify_all()
        except Exception as e:  # a bug must not kill the thread silently
            log.exception("breathing states failed")
            with self._cond:
                self._error = f"{type(e).__name__}: {e}"
                self._cond.notify_all()

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=5)

    def wait_ready(self, timeout_s: float | None = None, all_phases: bool = False) -> bool:
        """Block until end-expiration of the first stage (or every state of every stage) is prepared; True when ready."""
        def done():
            if self._error is not None:
                return True
            if not all_phases:
                return self._states[0][0] is not None
            return all(p is not None for stage in self._states for p in stage)
        with self._cond:
            self._cond.wait_for(done, timeout=timeout_s)
            if self._error is not None and self._states[0][0] is None:
                raise FluorosimError(f"the breathing patient cannot be prepared: {self._error}")
            return done()

    @property
    def ready_count(self) -> int:
        return sum(p is not None for stage in self._states for p in stage)

    def stage_at(self, t_s: float) -> int:
        """Which stage of the study is on at case time `t_s` (s)."""
        t = t_s % self.cycle_s if math.isfinite(self.cycle_s) else t_s
        return max(bisect.bisect_right(self.stage_times, t) - 1, 0)

    def at(self, t_s: float, steer: bool = True):
        """(state, next state or None, weight of the next) for the breath at case time `t_s` (s);
        `steer` False (a look ahead) leaves the stage the loader prepares first as it was."""
        e = self.control.at(t_s).excursion
        step = self.excursions[1]
        i = min(int(e / step), len(self.excursions) - 1)
        w = e / step - i
        j = self.stage_at(t_s)
        with self._cond:
            if steer and self._wanted != j:
                self._wanted = j
            # A stage still being prepared: the latest earlier one that is ready stands in.
            for jj in [j, *range(j - 1, -1, -1), *range(len(self._states) - 1, j, -1)]:
                states = self._states[jj]
                if states[i] is not None and (i + 1 >= len(states) or states[i + 1] is not None):
                    break
            else:
                ready = [p for p in self._states[0][: i + 1] if p is not None]
                if not ready:
                    raise FluorosimError("the breathing patient is still being prepared")
                return ready[-1], None, 0.0
            a = states[i]
            b = states[i + 1] if i + 1 < len(states) else None
        if b is None or w <= 0.0:
            return a, None, 0.0
        return a, b, float(w)


def breathing_timeline(case_path, case, renderer, cache_dir=None) -> Timeline:
    """The timeline of a case with a `respiration:` section: one CT, or the built-in patient's
    VCUG stages at end-expiration (its own breathing left out, the contrast on its own clock)."""
    from ..config.loading import resolve
    from .breathing_motion import load_labels
    from .volume_io import load_volume

    params = case.respiration
    if case.phases is not None and len(case.phases) > 1:
        from .breathing_4d import FourDBreathing
        from .timeline import PhaseTimeline
        ct_phases = [(ph.time_s, partial(load_volume, resolve(case_path, ph.volume))) for ph in case.phases]
        return FourDBreathing(PhaseTimeline(ct_phases, renderer, at_end="loop"), params,
                              params.ct_end_expiration_s)
    if case.builtin is not None:
        from .builtin import SEQUENCE_S, builtin_phases, timeline
        phases = builtin_phases(case.builtin, cache_dir)
        stages = [(spec.time_s, load) for spec, (_, load) in zip(timeline(), phases) if spec.breath == 0.0]
        return BreathingTimeline(stages, params, case.materials, renderer, cycle_s=SEQUENCE_S)
    path = resolve(case_path, case.phases[0].volume)
    return BreathingTimeline(lambda: load_volume(path), params, case.materials, renderer,
                             load_labels=lambda ct: load_labels(case_path, params, ct))
