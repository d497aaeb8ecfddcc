"""The webcam on the image intensifier: intrinsics and distortion from `fluorosim calibrate webcam`."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from .base import Findings, Section, matrix


class WebcamProfile(Section):
    name: str = Field("webcam", description="Which camera these numbers belong to.")
    width: int = Field(1280, gt=0, le=8192, description="Image width the intrinsics were measured at (pixels).")
    height: int = Field(720, gt=0, le=8192, description="Image height the intrinsics were measured at (pixels).")
    K: list[list[float]] = Field(description="Camera matrix [[fx,0,cx],[0,fy,cy],[0,0,1]] (pixels).")
    dist: list[float] = Field(min_length=5, max_length=5, description="OpenCV distortion k1 k2 p1 p2 k3 (dimensionless).")
    status: Literal["nominal", "calibrated"] = Field("nominal", description="'calibrated' once measured from a ChArUco board.")
    rms_px: float | None = Field(None, ge=0, description="Reprojection RMS of the calibration (pixels).")

    def problems(self) -> Findings:
        K = self.K
        if len(K) != 3 or any(len(r) != 3 for r in K):
            yield ("K",), "must be a 3x3 matrix"
            return
        if not (K[0][0] > 0 and K[1][1] > 0):
            yield ("K",), "focal lengths K[0][0] and K[1][1] must be greater than 0"
        if K[2] != [0.0, 0.0, 1.0] or K[1][0] != 0.0:
            yield ("K",), "last row must be 0 0 1 and K[1][0] must be 0"

    def camera_matrix(self) -> np.ndarray:
        return matrix(self.K)

    def distortion(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)
