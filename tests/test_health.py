"""Health checks: disk space against statvfs, device and reported states to banners."""

from __future__ import annotations

import os

import pytest

from appliance.daemon.health import (
    CameraState,
    DiskSpace,
    InputDeviceState,
    Level,
    TrackingState,
    banners_for_frame,
    profile_reload_check,
    records_check,
    renderer_fault_check,
)


def test_disk_space_against_statvfs(tmp_path):
    st = os.statvfs(tmp_path)
    free_mb = st.f_bavail * st.f_frsize / 2**20
    ok = DiskSpace(tmp_path, min_free_mb=0).check()
    assert ok.level == Level.OK
    assert ok.context["free_mb"] == pytest.approx(free_mb, abs=64)
    full = DiskSpace(tmp_path, min_free_mb=free_mb + 10_000).check()
    assert full.level == Level.WARNING and full.banner.startswith("disk nearly full")
    missing = DiskSpace(tmp_path / "gone", min_free_mb=0).check()
    assert missing.level == Level.ERROR and "data folder" in missing.banner

class _Device:
    def __init__(self, state):
        self.state = state

def test_device_states_map_to_banners():
    cam = _Device("ok")
    check = CameraState(lambda: cam)
    assert check.check().ok
    cam.state = "camera lost"
    assert check.check().banner.startswith("tracking lost")
    cam.state = "starting"
    assert check.check().level == Level.WARNING
    assert CameraState(lambda: None).check().level == Level.WARNING

    pedal = _Device("unplugged")
    assert InputDeviceState("pedal", lambda: pedal).check().banner == "pedal unplugged - plug it back in"
    pedal.problem = "/dev/fluorosim/pedal: pedal silent for more than 0.5 s; counted as released"
    assert InputDeviceState("pedal", lambda: pedal).check().banner == f"pedal: {pedal.problem}"
    pedal.state = "ok"
    assert InputDeviceState("pedal", lambda: pedal).check().ok
    assert InputDeviceState("keypad", lambda: _Device("none")).check().ok
    assert renderer_fault_check(lambda: None).check().ok
    assert "CPU" in renderer_fault_check(lambda: "clBuildProgram failed").check().banner
    assert profile_reload_check(lambda: "x.yaml:3: a: bad").check().banner.endswith("x.yaml:3: a: bad")
    records = records_check(lambda: "ledger.sqlite: disk full").check()
    assert records.level == Level.ERROR and records.banner.endswith("ledger.sqlite: disk full")


def test_a_live_frame_does_not_show_the_markers_lost_banner_the_supervisor_has_not_cleared_yet():
    """The supervisor's tracking banner is a second old at most; a live frame, drawn from a pose
    the tracker just gave, leaves it out and keeps every other banner. A held frame shows it."""
    lost = TrackingState(lambda: False).check().banner
    others = ["pedal unplugged - plug it back in", "tracking lost: camera lost - check the webcam cable"]
    banners = [lost, *others]
    assert banners_for_frame(banners, live=True) == others
    assert banners_for_frame(banners, live=False) == banners
    assert TrackingState(lambda: True).check().ok
