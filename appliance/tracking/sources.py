"""Open the camera the appliance profile names: the synthetic webcam, a V4L2 device, or a file source."""

from __future__ import annotations

from pathlib import Path

from drivers.camera import CameraSource, FileCamera, V4L2Camera

from ..config.loading import ApplianceConfig
from .scene import synthetic_camera
from .trajectory import load_trajectory

#: The scripted demo path shipped with the appliance, used when the profile names none.
DEMO_TRAJECTORY = Path(__file__).resolve().parents[2] / "configs" / "trajectories" / "demo.jsonl"


def open_camera(config: ApplianceConfig) -> CameraSource:
    """The camera source of `config.appliance.devices.camera` (not yet started)."""
    cam = config.appliance.devices.camera
    if cam.source == "synthetic":
        path = config.resolve(cam.trajectory) if cam.trajectory else DEMO_TRAJECTORY
        return synthetic_camera(config.phantom, config.webcam, load_trajectory(path), fps=cam.fps)
    source = config.resolve(cam.source)
    if cam.source.startswith("/dev/"):
        return V4L2Camera(cam.source, cam.width, cam.height, cam.fps, cam.fourcc)
    return FileCamera(source, fps=cam.fps)
