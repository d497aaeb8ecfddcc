"""The webcam on the image intensifier: intrinsics and distortion from `fluorosim calibrate webcam`."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from . import limits
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
        fx, fy, cx, cy = K[0][0], K[1][1], K[0][2], K[1][2]
        low, high = limits.WEBCAM_FOCAL_PER_WIDTH
        for name, f in (("K[0][0]", fx), ("K[1][1]", fy)):
            if f > 0 and not low * self.width <= f <= high * self.width:
                yield (("K",), f"focal length {name} = {limits.fmt(f)} px is no webcam's: a lens from fisheye to "
                               f"telephoto gives {low:g}..{high:g} x the width ({low * self.width:g}..{high * self.width:g} px)")
        if not (-0.5 <= cx <= self.width - 0.5 and -0.5 <= cy <= self.height - 0.5):
            yield ("K",), f"principal point ({limits.fmt(cx)}, {limits.fmt(cy)}) px lies outside the {self.width}x{self.height} image"
        if fx > 0 and fy > 0:
            corner = float(np.hypot(self.width / 2 / fx, self.height / 2 / fy))
            k1, k2, _, _, k3 = self.dist
            radial = limits.corner_distortion(k1, k2, k3, corner)
            if abs(radial) > limits.MAX_WEBCAM_CORNER_DISTORTION:
                yield (("dist",), f"k1, k2, k3 move the image corner by {radial:+.0%}; a webcam lens stays within "
                                  f"{limits.MAX_WEBCAM_CORNER_DISTORTION:.0%} (are these OpenCV's coefficients?)")

    def camera_matrix(self) -> np.ndarray:
        return matrix(self.K)

    def distortion(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)
