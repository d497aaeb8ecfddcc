"""The synthetic webcam built from the phantom and webcam profiles."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from drivers.camera import SyntheticCamera
from drivers.camera_scene import RenderSettings

from ..config.phantom import PhantomProfile
from ..config.webcam import WebcamProfile
from ..geometry import make_transform, rotation_about


def synthetic_camera(phantom: PhantomProfile, webcam: WebcamProfile, trajectory: Callable[[float], np.ndarray],
                     clock: Callable[[], float] = time.monotonic, fps: float = 30.0,
                     settings: RenderSettings | None = None, seed: int | None = None,
                     T_phantom_from_marker: dict[int, np.ndarray] | None = None, nice: int = 0) -> SyntheticCamera:
    """A SyntheticCamera showing `phantom` through `webcam` along `trajectory` (t in s -> T_webcam_from_phantom).

    `T_phantom_from_marker` overrides where markers really sit (to test calibration against a
    layout the profile does not know); by default the profile's placements are used.
    """
    placed = T_phantom_from_marker or {m.id: m.T() for m in phantom.markers}
    ids = [m.id for m in phantom.markers]
    b = phantom.box
    return SyntheticCamera(ids, [placed[i] for i in ids], phantom.marker_size_mm, phantom.aruco_dictionary,
                           (b.length_mm, b.width_mm, b.height_mm), webcam.camera_matrix(), webcam.distortion(),
                           webcam.width, webcam.height, trajectory, clock=clock, fps=fps, settings=settings, seed=seed,
                           nice=nice)


def markers_stuck_by_hand(phantom: PhantomProfile, rng: np.random.Generator) -> dict[int, np.ndarray]:
    """Where a technician's markers really sit: each up to 8 mm and 10 deg off the drawing, the root as drawn.

    The layout the composite calibration has to recover, in the benchmark and in its tests alike.
    """
    true = {}
    for m in phantom.markers:
        T = m.T()
        if m.id != phantom.root_marker_id:
            T = T @ make_transform(rotation_about((0, 0, 1), np.radians(rng.uniform(-10, 10))),
                                   [rng.uniform(-8, 8), rng.uniform(-8, 8), 0.0])
        true[m.id] = T
    return true
