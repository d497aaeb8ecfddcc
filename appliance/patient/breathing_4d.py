"""A 4D CT under the breathing controls: rate stretches its time, depth scales its excursion.

The CT's phases hold one breath of `period_s`; the breathing model's phase (counted in
breaths, end-expiration at 3/4 as in the seed's sines) picks the time in that breath, so the
console's rate changes stretch or squeeze the CT's cycle without a jump. Depth below 1
blends the phase with the end-expiration phase (weight = depth), the excursion scaled about
end-expiration in projection space; a CT cannot breathe deeper than it was scanned, so depth
above 1 shows its own excursion. Same interface as PhaseTimeline.
"""

from __future__ import annotations

from ..config.case import Respiration
from .respiration import BreathingControl
from .timeline import PhaseTimeline


class FourDBreathing:
    def __init__(self, timeline: PhaseTimeline, params: Respiration, end_expiration_s: float,
                 control: BreathingControl | None = None):
        self.timeline, self.params = timeline, params
        self.end_expiration_s = end_expiration_s
        self.control = control or BreathingControl(params)
        self.period_s = timeline.period_s

    def ct_time(self, t_s: float) -> tuple[float, float]:
        """(time in the CT's breath, depth) for case time `t_s` (s)."""
        s = self.control.at(t_s)
        return self.end_expiration_s + self.period_s * ((s.cycles - 0.75) % 1.0), s.depth

    def at(self, t_s: float, steer: bool = True):
        t_ct, depth = self.ct_time(t_s)
        a, b, w = self.timeline.at(t_ct, steer)
        if depth >= 1.0:
            return a, b, w
        rest, _, _ = self.timeline.at(self.end_expiration_s, steer)
        # Two volumes per frame: the phase nearest the breath, blended with end-expiration.
        nearest = b if b is not None and w >= 0.5 else a
        if depth <= 0.0 or nearest is rest:
            return rest, None, 0.0
        return rest, nearest, float(depth)

    def wait_ready(self, timeout_s: float | None = None, all_phases: bool = False) -> bool:
        return self.timeline.wait_ready(timeout_s, all_phases)

    @property
    def ready_count(self) -> int:
        return self.timeline.ready_count

    def close(self) -> None:
        self.timeline.close()
