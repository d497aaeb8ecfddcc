"""Calibration sessions at known geometry, and the figures that compare a result with the truth.

The benchmark and the tests both need: a "true" machine that differs from the nominal
profile the way a real one does, phantom poses a technician would use (tilted up to ~12
degrees, turned any way, shifted about the field), the webcam's marker reading at each
pose with realistic tracking noise, and error measures for intrinsics, distortion and the
webcam transform. Nothing here is used by the calibration itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...config.calibration_phantom import CalibrationPhantomProfile
from ...config.fluoroscope import FluoroscopeProfile
from ...geometry import invert, make_transform, rotation_about, rotation_angle_deg


@dataclass(frozen=True)
class Machine:
    """The imaging geometry the images are made with (the truth a calibration must find)."""

    K: np.ndarray
    dist: np.ndarray
    T_xray_from_webcam: np.ndarray


def true_machine(nominal: FluoroscopeProfile) -> Machine:
    """A machine off its nominal profile by typical amounts: 0.6 % in focal length, a few
    pixels of principal point, a stronger pincushion with k2 and decentring, and a webcam
    mounted 3 mm and 1.5 degrees away from the drawing."""
    K = nominal.intrinsics.K().copy()
    K[0, 0] *= 1.006
    K[1, 1] *= 0.996
    K[0, 2] += 4.3
    K[1, 2] -= 3.1
    k1 = nominal.intrinsics.distortion.k1 or 2.5
    dist = np.array([1.1 * k1, 4.0, 8e-4, -6e-4, 0.0])
    T_nominal = nominal.T_xray_from_webcam()
    wobble = make_transform(rotation_about([0.3, -1.0, 0.4], np.radians(1.5)), [2.0, -1.5, 2.0])
    return Machine(K, dist, T_nominal @ wobble)


def phantom_poses(n: int, rng: np.random.Generator, depth_mm: tuple[float, float] = (600.0, 700.0),
                  max_tilt_deg: float = 12.0, max_shift_mm: float = 15.0) -> list[np.ndarray]:
    """T_xray_from_phantom for n images: tilted, turned about its normal, shifted in the field.

    The phantom's top plate faces the detector (+z of the X-ray frame), as it lies on the
    table under an over-table intensifier.
    """
    poses = []
    for i in range(n):
        # Spread the tilt directions evenly so every image set constrains depth both ways.
        tilt_dir = 2 * np.pi * (i + rng.uniform(0, 1)) / n
        tilt = np.radians(rng.uniform(0.4, 1.0) * max_tilt_deg)
        R = rotation_about([np.cos(tilt_dir), np.sin(tilt_dir), 0.0], tilt) @ rotation_about([0, 0, 1], rng.uniform(0, 2 * np.pi))
        t = [rng.uniform(-max_shift_mm, max_shift_mm), rng.uniform(-max_shift_mm, max_shift_mm), rng.uniform(*depth_mm)]
        poses.append(make_transform(R, t))
    return poses


def marker_reading(machine: Machine, T_xray_from_phantom: np.ndarray, phantom: CalibrationPhantomProfile,
                   rng: np.random.Generator, noise_mm: float = 0.3, noise_deg: float = 0.1) -> np.ndarray:
    """T_webcam_from_marker as the tracker would report it, with noise about the marker centre."""
    exact = invert(machine.T_xray_from_webcam) @ T_xray_from_phantom @ phantom.T_phantom_from_marker()
    axis = rng.normal(size=3)
    noise = make_transform(rotation_about(axis, np.radians(rng.normal(0.0, noise_deg))), rng.normal(0.0, noise_mm / np.sqrt(3), 3))
    return exact @ noise


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error in mm, rotation error in degrees)."""
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), rotation_angle_deg(T_est, T_true)


def distortion_error_px(K_true: np.ndarray, dist_true: np.ndarray, K_est: np.ndarray, dist_est: np.ndarray,
                        centre: tuple[float, float], radius_px: float, step_px: float = 8.0) -> tuple[float, float]:
    """(worst, RMS) difference of the distortion displacement over the field (pixels).

    For each pixel p of a grid covering the disc, each model's displacement is p minus where
    its own pinhole would put the same ray; the error is the difference of the two
    displacements, so it measures the distortion alone, not the focal length.
    """
    g = np.arange(-radius_px, radius_px + step_px, step_px)
    uu, vv = np.meshgrid(centre[0] + g, centre[1] + g)
    inside = (uu - centre[0]) ** 2 + (vv - centre[1]) ** 2 <= radius_px ** 2
    p = np.stack([uu[inside], vv[inside]], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    und_true = cv2.undistortPoints(p, K_true, dist_true, None, K_true, None, criteria).reshape(-1, 2)
    und_est = cv2.undistortPoints(p, K_est, dist_est, None, K_est, None, criteria).reshape(-1, 2)
    diff = np.linalg.norm((p.reshape(-1, 2) - und_true) - (p.reshape(-1, 2) - und_est), axis=1)
    return float(diff.max()), float(np.sqrt((diff ** 2).mean()))
