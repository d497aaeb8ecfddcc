"""Physical and regulatory bounds that profiles and input files are checked against.

These are not tunables: they are what the law allows a fluoroscope to do, and what a real
C-arm, intensifier or webcam can physically be. A profile outside them is a typo or a
wrong file, so it is refused with the bound in the message instead of being simulated
(and recorded in the dose ledger) as if it were a machine.
"""

from __future__ import annotations

import math

import numpy as np

# The latest time a keypad script or trajectory may name (one day, s), shared with the driver.
from drivers.scripted_input import MAX_SCRIPT_TIME_S as MAX_SCRIPT_TIME_S

#: 21 CFR 1020.32(d)(1): fluoroscopic equipment shall not operate at an air-kerma rate above
#: 88 mGy/min in normal mode (mGy/min).
MAX_AIR_KERMA_RATE_MGY_PER_MIN = 88.0
#: 21 CFR 1020.32(d)(3): with an activated high-level control, at most 176 mGy/min (mGy/min).
MAX_HIGH_LEVEL_AIR_KERMA_RATE_MGY_PER_MIN = 176.0
#: 21 CFR 1020.32(h)(2): the cumulative-time alarm sounds at most every 5 minutes (s).
MAX_ALARM_PERIOD_S = 300.0
#: Below this the alarm would sound continuously: a console re-arms it in well over a second (s).
MIN_ALARM_PERIOD_S = 10.0

#: The patient lies between isocentre and detector, inside the intensifier's housing at
#: least this far from the focal spot's image plane: no C-arm has isocentre and input
#: plane closer (mm).
MIN_ISOCENTRE_TO_IMAGE_MM = 100.0
#: A calibrated focal length (fx * pixel pitch) differs from the nominal SID by the
#: intensifier's magnification and the calibration's error, never by more than this factor.
MAX_FOCAL_LENGTH_RATIO = 1.5
#: Radial pincushion of a real image intensifier displaces the corner of the image by at
#: most some 15%; beyond 30% the model's polynomial folds back on itself (fraction).
MAX_CORNER_DISTORTION = 0.30
#: Tangential distortion comes from a decentred lens and is a few pixels at most (fraction
#: of the radius at the detector corner).
MAX_CORNER_TANGENTIAL = 0.05
#: The webcam rides on the intensifier housing: its offset from the focal spot is at most
#: the SID plus the housing's reach (mm).
WEBCAM_HOUSING_REACH_MM = 500.0
#: A webcam's focal length in pixels, from fisheye (0.2) to telephoto (20), per pixel of image width.
WEBCAM_FOCAL_PER_WIDTH = (0.2, 20.0)
#: Barrel or pincushion of a webcam lens at the image corner, beyond which it is not a webcam (fraction).
MAX_WEBCAM_CORNER_DISTORTION = 0.6
#: The phantom box and the CT placed in it lie within this distance of their frames' origin (mm).
MAX_PLACEMENT_OFFSET_MM = 2000.0
#: A phantom seen by the webcam is within this distance of it (mm).
MAX_WEBCAM_DISTANCE_MM = 5000.0


def finite(value: object) -> bool:
    """Whether `value` is a real number (not NaN or infinite), arrays included."""
    try:
        return bool(np.all(np.isfinite(np.asarray(value, dtype=np.float64))))
    except (TypeError, ValueError):
        return False


def corner_distortion(k1: float, k2: float, k3: float, r: float) -> float:
    """Relative radial displacement k1 r^2 + k2 r^4 + k3 r^6 at normalised radius `r`."""
    r2 = r * r
    return k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2


def fmt(x: float) -> str:
    """A number as a person wrote it: 1e+12 rather than 1000000000000.0."""
    return f"{x:g}" if math.isfinite(x) else str(x)
