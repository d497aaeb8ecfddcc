"""Shadows that crowd each other, and what that says about how the phantom lies.

A shadow whose neighbour lies closer than about one and a half diameters shares its centroid
window or background ring with it, so neither centre can be measured: `crowded` marks such
shadows (detection drops them, identification drops the balls its pose predicts to crowd).

Balls of the two plates crowd when the phantom is tilted: the tilt shifts one plate's shadows
against the other's by the plates' gap times tan(tilt) and foreshortens the plate, until balls
that lie apart in plan view land on each other. When an image cannot be identified and many of
its shadows were dropped for crowding, that, not the field, is what went wrong, and
`crowding_advice` says so with the tilt from which this phantom's shadows start to crowd,
worked out from its ball positions (a property of the phantom, not a measurement of the image).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree

from ..config.calibration_phantom import CalibrationPhantomProfile
from ..geometry import rotation_about

#: Crowded: a neighbour's centre nearer than this many of the shadow's own diameters plus this
#: many of the neighbour's (the centroid window is 1.15 diameters, the neighbour's edge half one).
OWN_DIAMETERS, NEIGHBOUR_DIAMETERS = 1.15, 0.5
#: An unidentified image is put down to crowding when at least this share of its shadows, and at
#: least CROWDED_MIN of them, were dropped for it (fraction, count): a few crowd in any image.
CROWDED_SHARE, CROWDED_MIN = 0.05, 4
#: Tilts and tilt directions searched for the phantom's crowding tilt (deg).
TILTS_DEG = np.arange(0.0, 61.0, 1.0)
DIRECTIONS_DEG = np.arange(0.0, 360.0, 7.5)   # both senses of each tilt axis


def crowded(uv: np.ndarray, diameter: np.ndarray) -> np.ndarray:
    """(n,) bool: which shadows (centres in any unit, diameters in the same) have a neighbour too near."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    d = np.asarray(diameter, np.float64)
    if len(uv) < 2:
        return np.zeros(len(uv), bool)
    reach = OWN_DIAMETERS * d.max() + NEIGHBOUR_DIAMETERS * d.max()
    pairs = cKDTree(uv).query_pairs(reach, output_type="ndarray")
    out = np.zeros(len(uv), bool)
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        gap = np.linalg.norm(uv[i] - uv[j], axis=1)
        out[i[gap < OWN_DIAMETERS * d[i] + NEIGHBOUR_DIAMETERS * d[j]]] = True
        out[j[gap < OWN_DIAMETERS * d[j] + NEIGHBOUR_DIAMETERS * d[i]]] = True
    return out


@lru_cache(maxsize=8)
def _crowding_tilt(centres: bytes, diameters: bytes) -> float:
    c = np.frombuffer(centres).reshape(-1, 3)
    d = np.frombuffer(diameters)
    c = c - c.mean(axis=0)
    worst = float(TILTS_DEG[-1])
    for direction in np.radians(DIRECTIONS_DEG):
        axis = [np.cos(direction), np.sin(direction), 0.0]
        for tilt in TILTS_DEG:
            if tilt >= worst:
                break
            # The beam is narrow (a few degrees): a parallel projection along the principal ray.
            plan = (c @ rotation_about(axis, np.radians(tilt)).T)[:, :2]
            if crowded(plan, d).mean() >= CROWDED_SHARE:
                worst = float(tilt)
                break
    return worst


def crowding_tilt_deg(centres_mm: np.ndarray, diameters_mm: np.ndarray) -> float:
    """The smallest tilt (deg, in 1 deg steps, over all tilt directions) at which CROWDED_SHARE of
    a phantom's balls (centres in the phantom frame, plates along its z) crowd, as many as make an
    image fail for it; the search's top (60 deg) when none do."""
    return _crowding_tilt(np.ascontiguousarray(centres_mm, np.float64).tobytes(),
                          np.ascontiguousarray(diameters_mm, np.float64).tobytes())


def crowding_advice(kept: int, dropped: int, phantom: CalibrationPhantomProfile) -> str | None:
    """What to tell a person when an image failed and `dropped` of its `kept + dropped` shadows
    were dropped for crowding; None when too few were to explain it."""
    total = kept + dropped
    if dropped < max(CROWDED_MIN, CROWDED_SHARE * total):
        return None
    limit = crowding_tilt_deg(phantom.centres(), phantom.diameters())
    return (f"{dropped} of its {total} ball shadows lie too close to another to be measured: the balls of the two "
            f"plates overlap, as they do when the phantom is tilted too far; tilt it less than {limit:.0f} deg (from "
            f"there this phantom's shadows start to crowd, in the worst direction; 5 deg or more helps fx and fy), "
            f"all of it in the field")
