"""Where the intensifier's webcam sits in the X-ray frame (the seed paper's Eq. 3), averaged over images.

For each X-ray image the fit gives `T_xray_from_phantom`, the phantom's construction gives
`T_phantom_from_marker`, and the webcam reported `T_webcam_from_marker` at the same moment:

    T_xray_from_webcam = T_xray_from_phantom @ T_phantom_from_marker @ inverse(T_webcam_from_marker)

Several images give several estimates. Rotations are averaged on SO(3) (the chordal L2
mean of scipy's `Rotation.mean`, Markley's quaternion method), never element-wise, which
would give a matrix that is not a rotation; translations are averaged arithmetically.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import invert, make_transform, rotation_angle_deg


def webcam_in_xray(T_xray_from_phantom: np.ndarray, T_phantom_from_marker: np.ndarray,
                   T_webcam_from_marker: np.ndarray) -> np.ndarray:
    """Eq. 3: one estimate of T_xray_from_webcam (4x4, mm)."""
    return T_xray_from_phantom @ T_phantom_from_marker @ invert(T_webcam_from_marker)


@dataclass(frozen=True)
class AveragedTransform:
    T: np.ndarray
    translation_spread_mm: np.ndarray  # (n,) distance of each estimate's translation from the mean
    rotation_spread_deg: np.ndarray    # (n,) angle of each estimate's rotation from the mean


def average_rigid(transforms: list[np.ndarray]) -> AveragedTransform:
    """Mean of rigid transforms: rotation averaged on SO(3), translation arithmetically."""
    Ts = np.asarray(transforms, dtype=np.float64)
    R_mean = Rotation.from_matrix(Ts[:, :3, :3]).mean().as_matrix()
    t_mean = Ts[:, :3, 3].mean(axis=0)
    T = make_transform(R_mean, t_mean)
    return AveragedTransform(
        T=T,
        translation_spread_mm=np.linalg.norm(Ts[:, :3, 3] - t_mean, axis=1),
        rotation_spread_deg=np.array([rotation_angle_deg(R, R_mean) for R in Ts[:, :3, :3]]),
    )
