"""The pose filter's response, against a first-order low-pass and the symmetry of its two channels.

Ground truth: with beta = 0 the One Euro filter is a first-order low-pass of cut-off f_c,
whose step response at t = tau = 1 / (2 pi f_c) is 1 - 1/e (sampled at 1 kHz, within 0.2 %),
for translation (mm) and rotation about a fixed axis (deg) alike; the speed term raises the
cut-off (less lag in motion); and translation in mm/s and rotation in deg/s are the same
filter, so a rotation ramp of w deg/s with beta_per_deg_s = b lags as many degrees as a
translation ramp of w mm/s with beta_per_mm_s = b lags millimetres.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from appliance.geometry import make_transform
from appliance.tracking.smoothing import PoseFilter, SmoothingSettings

DT = 0.001


def settings(beta_mm: float = 0.0, beta_deg: float = 0.0) -> SmoothingSettings:
    return SmoothingSettings(min_cutoff_hz=1.0, beta_per_mm_s=beta_mm, beta_per_deg_s=beta_deg, d_cutoff_hz=1.0,
                             reset_after_s=10.0)


def pose(x_mm: float = 0.0, angle_deg: float = 0.0) -> np.ndarray:
    return make_transform(Rotation.from_euler("z", angle_deg, degrees=True).as_matrix(), np.array([x_mm, 0.0, 0.0]))


def filtered(f: PoseFilter, T: np.ndarray, t: float) -> tuple[float, float]:
    out = f(T, t)
    return float(out[0, 3]), float(np.degrees(Rotation.from_matrix(out[:3, :3]).magnitude()))


@pytest.mark.parametrize("channel", ["translation", "rotation"])
def test_without_the_speed_term_a_step_rises_to_1_minus_1_over_e_at_tau(channel):
    f = PoseFilter(settings())
    f(pose(), 0.0)
    tau = 1.0 / (2.0 * math.pi * 1.0)
    step = pose(x_mm=10.0) if channel == "translation" else pose(angle_deg=10.0)
    n = round(tau / DT)
    for k in range(1, n + 1):
        x, a = filtered(f, step, k * DT)
    value = x if channel == "translation" else a
    assert value == pytest.approx(10.0 * (1.0 - math.exp(-n * DT / tau)), rel=2e-3)


def ramp_lag(s: SmoothingSettings, channel: str, speed: float = 30.0, seconds: float = 1.5, dt: float = 0.004) -> float:
    """How far the filtered pose trails a ramp of `speed` mm/s or deg/s once settled (mm or deg)."""
    f = PoseFilter(s)
    for k in range(round(seconds / dt) + 1):
        t = k * dt
        x, a = filtered(f, pose(x_mm=speed * t) if channel == "translation" else pose(angle_deg=speed * t), t)
    return speed * seconds - (x if channel == "translation" else a)


def test_the_speed_term_cuts_the_lag_and_each_channel_has_its_own_beta_in_its_own_unit():
    still_lag = ramp_lag(settings(), "rotation")
    assert still_lag == pytest.approx(30.0 / (2.0 * math.pi), rel=0.01)          # v tau
    moving = ramp_lag(settings(beta_deg=0.5), "rotation")
    assert moving < 0.5 * still_lag
    # Translation's beta does nothing to rotation, and the two channels are the same filter.
    assert ramp_lag(settings(beta_mm=0.5), "rotation") == pytest.approx(still_lag, rel=1e-6)
    assert moving == pytest.approx(ramp_lag(settings(beta_mm=0.5), "translation"), rel=1e-3)
