"""Health checks: small classes that each look at one thing and say how it is.

Each `check()` returns a `Health`: a level, the banner shown on screen when it is not OK
(one short sentence a trainee understands), and context for the log. A degraded mode is
nothing more than a check that is not OK: its banner shows while it lasts and goes away
by itself when the check passes again.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any, Protocol

from drivers.camera import CaptureState
from drivers.input_event import DeviceState


class Level(IntEnum):
    OK = 0
    WARNING = 1
    ERROR = 2


@dataclass(frozen=True)
class Health:
    level: Level
    banner: str = ""
    context: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.level == Level.OK


OK = Health(Level.OK)


class HealthCheck(Protocol):
    name: str

    def check(self) -> Health: ...


class DiskSpace:
    """Free space of the file system holding data_dir (ledger, saved images, logs)."""

    name = "disk"

    def __init__(self, path: Path, min_free_mb: float):
        self.path = Path(path)
        self.min_free_mb = min_free_mb

    def check(self) -> Health:
        try:
            usage = shutil.disk_usage(self.path)
        except OSError as e:
            return Health(Level.ERROR, f"data folder unreadable: {e.strerror or e}", {"path": str(self.path)})
        free_mb = usage.free / 2**20
        context = {"path": str(self.path), "free_mb": round(free_mb, 1), "min_free_mb": self.min_free_mb}
        if free_mb < self.min_free_mb:
            return Health(Level.WARNING, f"disk nearly full: {free_mb:.0f} MiB free - export and delete old images", context)
        return Health(Level.OK, "", context)


class CameraState:
    """The camera source's own state: 'starting', 'ok' or 'camera lost'."""

    name = "camera"

    def __init__(self, camera: Callable[[], Any]):
        self._camera = camera

    def check(self) -> Health:
        cam = self._camera()
        state = getattr(cam, "state", CaptureState.LOST) if cam is not None else CaptureState.LOST
        if state == CaptureState.OK:
            return OK
        if state == CaptureState.STARTING:
            return Health(Level.WARNING, "camera starting", {"state": state})
        return Health(Level.WARNING, "tracking lost: camera lost - check the webcam cable", {"state": state})


#: TrackingState's banner while the markers are out of the camera's view.
MARKERS_LOST = "tracking lost: bring the box markers into the camera's view"


def banners_for_frame(banners: list[str], live: bool) -> list[str]:
    """The supervisor's banners as a frame shows them. The supervisor checks the tracking once a
    health period (a second); a live frame is drawn from a pose the tracker has just given, so
    on it the markers-lost banner is stale: without this, the first live frames after the
    markers come back showed it over the live image for up to a second."""
    return [b for b in banners if b != MARKERS_LOST] if live else banners


class TrackingState:
    """Whether the last camera frame gave a pose of the box."""

    name = "tracking"

    def __init__(self, pose_ok: Callable[[], bool | None]):
        self._pose_ok = pose_ok

    def check(self) -> Health:
        ok = self._pose_ok()
        if ok is None or ok:
            return OK
        return Health(Level.WARNING, MARKERS_LOST, {})


class InputDeviceState:
    """A keypad or pedal: 'ok', 'none' (not configured) or 'unplugged'."""

    def __init__(self, name: str, device: Callable[[], Any]):
        self.name = name
        self._device = device

    def check(self) -> Health:
        dev = self._device()
        state = getattr(dev, "state", "none") if dev is not None else "none"
        if state in (DeviceState.OK, DeviceState.NONE):
            return OK
        problem = getattr(dev, "problem", "")
        banner = f"{self.name}: {problem}" if problem else f"{self.name} unplugged - plug it back in"
        return Health(Level.WARNING, banner, {"state": state})


class Reported:
    """A condition another part of the appliance reports as a one-line problem (None while all
    is well): shown as `banner` with the problem filled in."""

    def __init__(self, name: str, problem: Callable[[], str | None], level: Level, banner: str):
        self.name, self._problem, self._level, self._banner = name, problem, level, banner

    def check(self) -> Health:
        problem = self._problem()
        if not problem:
            return OK
        return Health(self._level, self._banner.format(problem), {"problem": problem})


def renderer_fault_check(fault: Callable[[], str | None]) -> Reported:
    """Whether rendering still runs on the OpenCL device the profile asked for."""
    return Reported("renderer", fault, Level.WARNING, "OpenCL device failed; rendering on the CPU ({})")


def profile_reload_check(problem: Callable[[], str | None]) -> Reported:
    """Whether the last SIGHUP reload was refused (the appliance runs on the last good profiles)."""
    return Reported("profile", problem, Level.WARNING, "profile not reloaded, running on the last good one: {}")


#: How the records worker starts a problem that is only a missing picture (the save press is in
#: the ledger), so the banner does not say the events wait.
IMAGE_NOT_SAVED = "image not saved (the save is in the ledger): "


def records_check(problem: Callable[[], str | None]) -> Reported:
    """Whether the ledger and saved images are being written (a full or read-only disk stops them)."""
    def banner() -> str | None:
        said = problem()
        if not said or said.startswith(IMAGE_NOT_SAVED):
            return said     # the events are written; only a picture is missing
        return f"records not written, kept in memory until they can be: {said}"
    return Reported("records", banner, Level.ERROR, "{}")


def run_check(check: HealthCheck) -> Health:
    """`check.check()`, with a failing check reported as an error rather than raised."""
    try:
        return check.check()
    except Exception as e:  # noqa: BLE001 - a broken check must not stop the supervisor
        return Health(Level.ERROR, f"health check {check.name} failed: {type(e).__name__}: {e}", {})
