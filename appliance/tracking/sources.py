"""The camera and the tracker the appliance profile asks for."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from drivers.camera import CameraSource, FileCamera, V4L2Camera

from ..config.loading import ApplianceConfig
from ..errors import FluorosimError
from .scene import synthetic_camera
from .smoothing import SmoothingSettings
from .tracker import Tracker
from .trajectory import load_trajectory

#: The scripted demo path shipped with the appliance, used when the profile names none.
DEMO_TRAJECTORY = Path(__file__).resolve().parents[2] / "configs" / "trajectories" / "demo.jsonl"


def open_camera(config: ApplianceConfig, clock: Callable[[], float] = time.monotonic) -> CameraSource:
    """The camera source of `config.appliance.devices.camera` (not yet started); a synthetic
    camera's path runs on `clock` (the appliance's)."""
    cam = config.appliance.devices.camera
    if cam.source == "synthetic":
        path = config.resolve(cam.trajectory) if cam.trajectory else DEMO_TRAJECTORY
        return synthetic_camera(config.phantom, config.webcam, load_trajectory(path), clock=clock, fps=cam.fps,
                                nice=cam.synthetic_nice)
    source = config.resolve(cam.source)
    if (cam.width, cam.height) != (config.webcam.width, config.webcam.height):
        # Intrinsics hold for the resolution they were measured at; another one would bias every pose.
        raise FluorosimError(f"{config.path}: devices.camera asks for {cam.width}x{cam.height} but the webcam "
                             f"profile {config.webcam_path} was calibrated at {config.webcam.width}x"
                             f"{config.webcam.height}; capture at that size or run 'fluorosim calibrate webcam'")
    if cam.source.startswith("/dev/"):
        return V4L2Camera(cam.source, cam.width, cam.height, cam.fps, cam.fourcc)
    return FileCamera(source, fps=cam.fps)


def tracker_for(config: ApplianceConfig) -> Tracker:
    """The tracker of `config.appliance.tracking` for the active phantom and webcam."""
    t = config.appliance.tracking
    return Tracker(config.phantom, config.webcam, method=t.method, smoothing=t.smoothing,
                   smoothing_settings=SmoothingSettings.from_profile(t))
