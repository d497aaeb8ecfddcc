"""Webcam intrinsics and distortion from views of a printed ChArUco board."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import FluorosimError
from .markers import aruco_dictionary, to_gray

#: A view needs this many board corners to constrain the camera (a homography needs 4; more
#: keeps a partly hidden board from adding a weak view).
MIN_CORNERS_PER_VIEW = 8
#: Fewer views than this leave the distortion terms poorly determined.
MIN_VIEWS = 5


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board as printed (mm)."""

    squares_x: int = 7
    squares_y: int = 5
    square_mm: float = 30.0
    marker_mm: float = 22.0
    dictionary: str = "DICT_5X5_100"

    def board(self):
        if self.squares_x < 3 or self.squares_y < 3:
            raise FluorosimError(f"ChArUco board {self.squares_x}x{self.squares_y}: needs at least 3x3 squares")
        if not 0 < self.marker_mm < self.square_mm:
            raise FluorosimError(f"ChArUco board: marker side {self.marker_mm} mm must be smaller than the square "
                                 f"side {self.square_mm} mm")
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_mm, self.marker_mm,
                                      aruco_dictionary(self.dictionary))

    def image(self, px_per_mm: float) -> np.ndarray:
        """The board as printed, uint8, exactly squares_x * square_mm wide at `px_per_mm`."""
        w = int(round(self.squares_x * self.square_mm * px_per_mm))
        h = int(round(self.squares_y * self.square_mm * px_per_mm))
        return self.board().generateImage((w, h), marginSize=0, borderBits=1)


class BoardDetector:
    def __init__(self, spec: BoardSpec) -> None:
        self.spec = spec
        self.board = spec.board()
        self.detector = cv2.aruco.CharucoDetector(self.board)

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(object points (n, 3) mm, image points (n, 2) pixels) of the board corners seen, or None."""
        corners, ids, _, _ = self.detector.detectBoard(to_gray(image))
        if ids is None or len(ids) < MIN_CORNERS_PER_VIEW:
            return None
        obj, img = self.board.matchImagePoints(corners, ids)
        if obj is None or len(obj) < MIN_CORNERS_PER_VIEW:
            return None
        return obj.reshape(-1, 3).astype(np.float32), img.reshape(-1, 2).astype(np.float32)


@dataclass
class WebcamCalibration:
    K: np.ndarray
    dist: np.ndarray          # k1 k2 p1 p2 k3
    rms_px: float
    views: int
    width: int
    height: int


def calibrate_webcam(views: list[tuple[np.ndarray, np.ndarray]], width: int, height: int) -> WebcamCalibration:
    """Intrinsics from board views [(object points, image points)] of `width` x `height` images."""
    if len(views) < MIN_VIEWS:
        raise FluorosimError(f"only {len(views)} usable view(s) of the ChArUco board; need at least {MIN_VIEWS}, "
                             "with the board tilted differently and reaching the image corners")
    obj = [v[0] for v in views]
    img = [v[1] for v in views]
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (width, height), None, None)
    return WebcamCalibration(K=K, dist=dist.reshape(-1)[:5], rms_px=float(rms), views=len(views),
                             width=width, height=height)
