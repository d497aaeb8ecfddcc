"""One Euro filter for rigid poses: strong smoothing at standstill, little lag in motion.

Casiez, Roussel and Vogel (CHI 2012): a first-order low-pass filter whose cut-off frequency
rises with the filtered speed, `cutoff = min_cutoff + beta * |speed|`. Translation and
rotation are filtered separately, each with its own speed: rotation as a step along the
geodesic from the filtered rotation toward the measured one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..config.appliance import Tracking
from ..geometry import make_transform

_PROFILE_DEFAULTS = Tracking()


@dataclass
class SmoothingSettings:
    """The filter's numbers; they come from the appliance profile's `tracking` section (units there)."""

    min_cutoff_hz: float = _PROFILE_DEFAULTS.min_cutoff_hz
    beta_per_mm_s: float = _PROFILE_DEFAULTS.beta_per_mm_s
    beta_per_deg_s: float = _PROFILE_DEFAULTS.beta_per_deg_s
    d_cutoff_hz: float = _PROFILE_DEFAULTS.d_cutoff_hz
    reset_after_s: float = _PROFILE_DEFAULTS.reset_after_s

    @classmethod
    def from_profile(cls, tracking: Tracking) -> SmoothingSettings:
        return cls(tracking.min_cutoff_hz, tracking.beta_per_mm_s, tracking.beta_per_deg_s, tracking.d_cutoff_hz,
                   tracking.reset_after_s)


def _alpha(cutoff_hz: float, dt: float) -> float:
    tau = 1.0 / (2.0 * math.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


class PoseFilter:
    """Filters a stream of T_webcam_from_phantom (mm) stamped in seconds."""

    def __init__(self, settings: SmoothingSettings | None = None) -> None:
        self.s = settings or SmoothingSettings()
        self.reset()

    def reset(self) -> None:
        self._t: float | None = None
        self._p: np.ndarray | None = None
        self._R: Rotation | None = None
        self._v = 0.0      # filtered translation speed (mm/s)
        self._w = 0.0      # filtered rotation speed (deg/s)

    def __call__(self, T: np.ndarray, t: float) -> np.ndarray:
        p, R = T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3])
        if self._t is None or self._p is None or self._R is None or t - self._t > self.s.reset_after_s or t <= self._t:
            self._t, self._p, self._R, self._v, self._w = t, p, R, 0.0, 0.0
            return T.copy()
        dt = t - self._t
        self._t = t
        s = self.s
        a_d = _alpha(s.d_cutoff_hz, dt)
        # Translation.
        speed = float(np.linalg.norm(p - self._p)) / dt
        self._v = a_d * speed + (1 - a_d) * self._v
        a = _alpha(s.min_cutoff_hz + s.beta_per_mm_s * self._v, dt)
        self._p = self._p + a * (p - self._p)
        # Rotation: move along the geodesic toward the measurement.
        step = (self._R.inv() * R).as_rotvec()
        w = math.degrees(float(np.linalg.norm(step))) / dt
        self._w = a_d * w + (1 - a_d) * self._w
        a = _alpha(s.min_cutoff_hz + s.beta_per_deg_s * self._w, dt)
        self._R = self._R * Rotation.from_rotvec(a * step)
        return make_transform(self._R.as_matrix(), self._p)
