"""A one-CT case breathing under the console's control, as the daemon's patient timeline.

The CT (end-expiration) is moved once to `depth_states` states evenly spaced from
end-expiration to the deepest breath the console allows (depth_max), each prepared on the
device by one background thread, end-expiration first. A frame then costs no more than a
4D CT's: `at(t)` asks the BreathingControl where the breath is and hands the renderer the two
states either side with the weight between them (blended in projection space by the
renderer's existing phase blend). Same interface as PhaseTimeline.
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Callable

from ..config.case import Materials, Respiration
from ..errors import FluorosimError
from .breathing_motion import BreathingAnatomy
from .respiration import BreathingControl, BreathState, muscle_amplitudes
from .volume import Volume

log = logging.getLogger(__name__)


class BreathingTimeline:
    """The breathing patient: precomputed depth states, picked and weighted by the live breath."""

    def __init__(self, load_ct: Callable[[], Volume], params: Respiration, materials: Materials, renderer,
                 load_labels: Callable[[Volume], object] | None = None, control: BreathingControl | None = None):
        self.params = params
        self.control = control or BreathingControl(params)
        self.renderer = renderer
        n = params.depth_states
        #: Excursion (multiple of the profile's full breath) of each state.
        self.excursions = [params.depth_max * k / (n - 1) for k in range(n)]
        self._load_ct, self._load_labels, self._materials = load_ct, load_labels, materials
        self._prepared: list = [None] * n
        self._error: str | None = None
        self._cond = threading.Condition()
        self._stop = False
        self.period_s = 60.0 / params.rate_per_min if params.rate_per_min > 0 else math.inf
        self._thread = threading.Thread(target=self._build, name="breathing-states", daemon=True)
        self._thread.start()

    def state_of(self, excursion: float) -> BreathState:
        """The anatomy at `excursion` (multiple of the profile's full breath): every muscle scales with it."""
        g, lam, d = muscle_amplitudes(self.params)
        inspired = min(excursion, 1.0)
        depth = excursion / inspired if excursion > 1.0 else 1.0
        return BreathState(0.0, 0.0, inspired, depth, self.params.rate_per_min, False,
                           g * excursion, lam * excursion, d * excursion - d * depth / 2.0, d * excursion)

    def _build(self) -> None:
        try:
            ct = self._load_ct()
            labels = self._load_labels(ct) if self._load_labels else None
            anatomy = BreathingAnatomy(ct, self.params, self._materials, labels)
            for k, e in enumerate(self.excursions):
                if self._stop:
                    return
                prepared = self.renderer.prepare(anatomy.volume_at(self.state_of(e)))
                prepared.time_s = e
                with self._cond:
                    self._prepared[k] = prepared
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
        self._thread.join(timeout=30)

    def wait_ready(self, timeout_s: float | None = None, all_phases: bool = False) -> bool:
        """Block until end-expiration (or every state) is prepared; True when ready."""
        def done():
            if self._error is not None:
                return True
            return all(p is not None for p in self._prepared) if all_phases else self._prepared[0] is not None
        with self._cond:
            self._cond.wait_for(done, timeout=timeout_s)
            if self._error is not None and self._prepared[0] is None:
                raise FluorosimError(f"the breathing patient cannot be prepared: {self._error}")
            return done()

    @property
    def ready_count(self) -> int:
        return sum(p is not None for p in self._prepared)

    def at(self, t_s: float):
        """(state, next state or None, weight of the next) for the breath at case time `t_s` (s)."""
        e = self.control.at(t_s).excursion
        step = self.excursions[1]
        i = min(int(e / step), len(self.excursions) - 1)
        w = e / step - i
        with self._cond:
            a = self._prepared[i]
            b = self._prepared[i + 1] if i + 1 < len(self._prepared) else None
            if a is None:
                ready = [k for k, p in enumerate(self._prepared) if p is not None and k <= i]
                if not ready:
                    raise FluorosimError("the breathing patient is still being prepared")
                return self._prepared[ready[-1]], None, 0.0
        if b is None or w <= 0.0:
            return a, None, 0.0
        return a, b, float(w)


def breathing_timeline(case_path, case, renderer) -> BreathingTimeline:
    """The timeline of a one-CT case with a `respiration:` section."""
    from ..config.loading import resolve
    from .breathing_motion import load_labels
    from .volume_io import load_volume

    params = case.respiration
    path = resolve(case_path, case.phases[0].volume)
    return BreathingTimeline(lambda: load_volume(path), params, case.materials, renderer,
                             load_labels=lambda ct: load_labels(case_path, params, ct))
