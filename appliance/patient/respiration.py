"""Controllable breathing: the PTC simulator's two muscle groups, driven by one phase.

The seed (Villard et al. 2009, section 2.2) drives the rib cage and the diaphragm with one
sinusoid of frequency f:

    gamma(t)  = gamma_max  * 1/2 * (1 + sin(2 pi f t))   lateral excursion of each rib
    lambda(t) = lambda_max * 1/2 * (1 + sin(2 pi f t))   anteroposterior rotation of each rib
    F_d(t)    = F_max * sin(2 pi f t)                     the central tendon about its mid position

with F_max = diaphragm_mm / 2, so the tendon travels diaphragm_mm from end-expiration to
end-inspiration. Here `f t` becomes a phase counted in breaths that the clock advances at
the current rate: a rate change mid-breath keeps the phase (and so the anatomy) where it is
and only changes how fast it moves on; a depth change is eased in over `depth_ramp_s`;
a hold stops the phase and the depth where they are, and resume carries on from there.
Depth scales the excursion about end-expiration (the state breathing always returns to).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from ..config.case import Respiration


@dataclass(frozen=True)
class BreathState:
    """Where the breath is at one instant."""

    t_s: float
    cycles: float           # breaths since the start: f t for a constant rate
    inspired: float         # 1/2 (1 + sin(2 pi cycles)): 0 end-expiration, 1 end-inspiration
    depth: float            # multiple of the profile's amplitudes
    rate_per_min: float
    held: bool
    gamma_deg: float        # each rib's lateral-excursion rotation (deg)
    lambda_deg: float       # each rib's anteroposterior rotation (deg)
    tendon_mm: float        # F_d: the central tendon below its mid position (mm)
    descent_mm: float       # the central tendon below its end-expiration position (mm)

    @property
    def excursion(self) -> float:
        """depth x inspired: the fraction of the profile's full breath the anatomy is at (0 at end-expiration)."""
        return self.depth * self.inspired


def muscle_amplitudes(params: Respiration) -> tuple[float, float, float]:
    """(gamma_max deg, lambda_max deg, diaphragm excursion mm) at depth 1, the intercostal share applied."""
    rib, dia = 1.0, 1.0
    if params.intercostal_share is not None:
        rib, dia = params.intercostal_share / 0.5, (1.0 - params.intercostal_share) / 0.5
    return params.rib_gamma_deg * rib, params.rib_lambda_deg * rib, params.diaphragm_mm * dia


class Irregularity:
    """Breath-to-breath variation as a warp of the regular breath count.

    Breath n runs from one end-expiration to the next; in breaths of the set rate it lasts
    L_n = 1 + a u_n and reaches the depth times D_n = 1 + a v_n (u_n, v_n uniform in -1..1,
    drawn from the seed and n, so a lesson repeats). Both change only at end-expiration,
    where the breath stands still (inspired = 0 and its slope 0): the anatomy moves on without
    a jump or a kink, as the console's own rate changes do. Before the first end-expiration
    (the case's first three quarters of a breath) the breath is regular.
    """

    def __init__(self, amount: float, seed: int):
        import numpy as np

        self.amount, self.seed = amount, seed
        self._rng = np.random.default_rng([seed, 0x5EED])
        self._starts = [0.0]                  # regular breaths (from the first end-expiration) at which breath n starts
        self._lengths: list[float] = []
        self._depths: list[float] = []
        self._lock = threading.Lock()

    def _grow_to(self, c: float) -> None:
        while self._starts[-1] <= c:
            u, v = self._rng.uniform(-1.0, 1.0, 2)
            self._lengths.append(1.0 + self.amount * float(u))
            self._depths.append(1.0 + self.amount * float(v))
            self._starts.append(self._starts[-1] + self._lengths[-1])

    def warp(self, cycles: float) -> tuple[float, float]:
        """(irregular breath count, depth factor) for `cycles` regular breaths since the start."""
        import bisect

        c = cycles - 0.75                     # breaths since the first end-expiration
        if c < 0.0:
            return cycles, 1.0
        with self._lock:
            self._grow_to(c)
            n = bisect.bisect_right(self._starts, c) - 1
            return 0.75 + n + (c - self._starts[n]) / self._lengths[n], self._depths[n]


_IRREGULAR: dict[tuple[float, int], Irregularity] = {}
_IRREGULAR_LOCK = threading.Lock()


def irregularity_of(params: Respiration) -> Irregularity | None:
    """The profile's breath-to-breath variation (one per amount and seed, so every caller sees the same breaths)."""
    if not params.irregularity:
        return None
    key = (params.irregularity, params.irregularity_seed)
    with _IRREGULAR_LOCK:
        if key not in _IRREGULAR:
            _IRREGULAR[key] = Irregularity(*key)
        return _IRREGULAR[key]


def state_from(params: Respiration, t_s: float, cycles: float, depth: float, rate_per_min: float,
               held: bool) -> BreathState:
    """The muscle angles and tendon position for a phase `cycles` (breaths) and a `depth`; with
    `irregularity`, the breath count warped and the depth scaled breath by breath (Irregularity)."""
    gamma_max, lambda_max, excursion_mm = muscle_amplitudes(params)
    irregular = irregularity_of(params)
    if irregular is not None:
        cycles, factor = irregular.warp(cycles)
        depth *= factor
    s = math.sin(2.0 * math.pi * cycles)
    inspired = 0.5 * (1.0 + s)
    return BreathState(t_s=t_s, cycles=cycles, inspired=inspired, depth=depth, rate_per_min=rate_per_min, held=held,
                       gamma_deg=depth * gamma_max * inspired, lambda_deg=depth * lambda_max * inspired,
                       tendon_mm=depth * excursion_mm / 2.0 * s, descent_mm=depth * excursion_mm * inspired)


def state_at(params: Respiration, t_s: float) -> BreathState:
    """The breath at time `t_s` (s) of a case left alone: constant rate, depth 1."""
    return state_from(params, t_s, params.rate_per_min / 60.0 * t_s, 1.0, params.rate_per_min, params.rate_per_min == 0)


def _ease(x: float) -> float:
    """Smoothstep: 0 -> 1 with zero slope at both ends, so an eased change starts and ends without a kink."""
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


class BreathingControl:
    """The live breath: the console changes rate and depth, holds and resumes; the renderer asks `at(t)`.

    Times are the case clock (s) and must not go backwards; a change stamped before the last
    one is applied at the last one's time. Thread-safe: the console and the renderer run in
    different threads.
    """

    def __init__(self, params: Respiration, t0_s: float = 0.0):
        self.params = params
        self._lock = threading.Lock()
        self._anchor_t = t0_s
        self._anchor_cycles = params.rate_per_min / 60.0 * t0_s
        self._rate = params.rate_per_min
        self._held = False
        # Depth eases from _depth_from to _depth_to starting at _ramp_t (frozen while held).
        self._depth_from = self._depth_to = 1.0
        self._ramp_t = t0_s

    # -- what the renderer asks ----------------------------------------------------
    def _cycles(self, t: float) -> float:
        if self._held:
            return self._anchor_cycles
        return self._anchor_cycles + self._rate / 60.0 * max(t - self._anchor_t, 0.0)

    def _depth(self, t: float) -> float:
        if self._held:
            return self._depth_from
        w = _ease((t - self._ramp_t) / self.params.depth_ramp_s)
        return self._depth_from + (self._depth_to - self._depth_from) * w

    def at(self, t_s: float) -> BreathState:
        with self._lock:
            return state_from(self.params, t_s, self._cycles(t_s), self._depth(t_s), self._rate,
                              self._held or self._rate == 0)

    @property
    def rate_per_min(self) -> float:
        return self._rate

    @property
    def depth_target(self) -> float:
        return self._depth_to

    @property
    def held(self) -> bool:
        return self._held

    # -- what the console does -----------------------------------------------------
    def _reanchor(self, t: float) -> float:
        t = max(t, self._anchor_t)
        self._anchor_cycles = self._cycles(t)
        self._anchor_t = t
        return t

    def set_rate(self, t_s: float, rate_per_min: float) -> float:
        """Change the rate at time t without moving the anatomy; clamped to 0..rate_max. Returns the new rate."""
        with self._lock:
            self._reanchor(t_s)
            self._rate = min(max(float(rate_per_min), 0.0), self.params.rate_max_per_min)
            return self._rate

    def set_depth(self, t_s: float, depth: float) -> float:
        """Ease the depth toward `depth` (clamped to 0..depth_max) from time t. Returns the target."""
        with self._lock:
            t = self._reanchor(t_s)
            if not self._held:
                self._depth_from = self._depth(t)
                self._ramp_t = t
            self._depth_to = min(max(float(depth), 0.0), self.params.depth_max)
            return self._depth_to

    def faster(self, t_s: float) -> float:
        return self.set_rate(t_s, self._rate + self.params.rate_step_per_min)

    def slower(self, t_s: float) -> float:
        return self.set_rate(t_s, self._rate - self.params.rate_step_per_min)

    def deeper(self, t_s: float) -> float:
        return self.set_depth(t_s, self._depth_to + self.params.depth_step)

    def shallower(self, t_s: float) -> float:
        return self.set_depth(t_s, self._depth_to - self.params.depth_step)

    def hold(self, t_s: float) -> None:
        """Stop breathing where the breath is now."""
        with self._lock:
            t = self._reanchor(t_s)
            if not self._held:
                self._depth_from = self._depth(t)
                self._held = True

    def resume(self, t_s: float) -> None:
        """Carry on breathing from where the hold stopped (at the profile's rate if the rate was 0)."""
        with self._lock:
            t = self._reanchor(t_s)
            if self._held:
                self._held = False
                self._ramp_t = t            # a depth change asked for during the hold eases in now
            if self._rate == 0:
                self._rate = self.params.rate_per_min or self.params.rate_step_per_min

    def overlay_text(self, t_s: float) -> str:
        """One line for the monitor: rate, depth and whether the breath is held."""
        s = self.at(t_s)
        if s.held:
            return f"BREATH HELD  depth {self._depth_to:.2f}"
        return f"RESP {s.rate_per_min:.0f}/min  depth {self._depth_to:.2f}"
