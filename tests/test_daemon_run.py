"""The whole appliance, run for real: `fluorosim run` under a real NOTIFY_SOCKET with real
signals, and a camera that disappears and comes back."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from appliance_setup import REPO, make_appliance
from notify_listener import NotifyListener
from stop_deadline import stop_deadline_s

from appliance.config import load_appliance
from appliance.daemon.notify import Notifier
from appliance.daemon.parts import is_cpu
from appliance.daemon.pipeline import Appliance
from appliance.daemon.reload import ProfileKeeper
from appliance.records.ledger import open_readonly, verify
from appliance.tracking.scene import synthetic_camera
from appliance.tracking.trajectory import pose_from_angles
from drivers.framebuffer import open_display

DISPLAY = (320, 256)


def _wait(predicate, timeout_s: float, poll_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())


def _screen(data_dir: Path) -> np.ndarray:
    display = open_display("file", str(data_dir / "screen.raw"), *DISPLAY, 32, read_only=True)
    try:
        return display.read_back()
    finally:
        display.close()


def _image_region(rgb: np.ndarray) -> np.ndarray:
    """The middle of the screen, inside the circular field of view, clear of the corner texts
    and of the bone rod (which lies 75 mm off-centre at the detector)."""
    h, w = rgb.shape[:2]
    return rgb[h // 2 - h // 8:h // 2 + h // 8, w // 2 - w // 8:w // 2 + w // 8]


def _shows_the_water_cylinder(region: np.ndarray) -> bool:
    """The central rays cross the cylinder's full 192 mm of water: mu = 0.023-0.027 /mm over
    40-50 keV (NIST), so -ln(I/I0) = 4.4-5.2; the profile's window 6 / level 3 shows that as
    0.73-0.87 of full scale. Allow for beam hardening and noise: 150-235 of 255."""
    return 150 < float(region.mean()) < 235


def test_run_is_ready_after_the_first_frame_survives_a_bad_reload_and_stops_on_sigterm(tmp_path):
    config = make_appliance(tmp_path, display=DISPLAY)
    data = tmp_path / "data"
    listener = NotifyListener(tmp_path / "notify.sock")
    env = dict(os.environ, NOTIFY_SOCKET=listener.path, WATCHDOG_USEC="1000000")
    env.pop("WATCHDOG_PID", None)
    t_start = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "appliance", "run", "--config", str(config)], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        t_ready = listener.wait_for("READY=1", 60)
        assert t_ready is not None, proc.stdout.read() if proc.poll() is not None else "no READY=1"
        # READY=1 came once the appliance's own screen was up (not the start-up screen it
        # shows while preparing), and with the pedal held the X-ray image follows at once.
        assert _wait(lambda: _shows_the_water_cylinder(_image_region(_screen(data))), 5)

        # Live frames with the pedal held, and watchdog pings at half of WatchdogSec.
        assert _wait(lambda: any(s.startswith("STATUS=") and not s.startswith("STATUS=0.0 fps")
                                 for s in listener.starting("STATUS=")), 20)
        time.sleep(1.2)
        assert len([t for t in listener.times_of("WATCHDOG=1") if t > t_ready]) >= 2

        # A technician's bad edit: the appliance keeps running on the last good profiles and says why.
        fl = config.parent / "fluoroscopes" / "generic-ii-carm.yaml"
        good = fl.read_text()
        fl.write_text(good.replace("source_to_image_mm: 1000", "source_to_image_mm: -5"))
        t_hup = time.monotonic()
        proc.send_signal(signal.SIGHUP)
        assert _wait(lambda: any("profile not reloaded" in s and "generic-ii-carm.yaml" in s
                                 and "geometry.source_to_image_mm" in s for s in listener.starting("STATUS=")), 10)
        assert "RELOADING=1" in [l for _, l in listener.lines()]
        time.sleep(1.2)
        assert proc.poll() is None
        assert [t for t in listener.times_of("WATCHDOG=1") if t > t_hup + 0.6]  # still healthy
        fl.write_text(good)
        n_status = len(listener.starting("STATUS="))
        proc.send_signal(signal.SIGHUP)
        assert _wait(lambda: len(listener.starting("STATUS=")) > n_status + 1
                     and "profile not reloaded" not in listener.starting("STATUS=")[-1], 10)

        t_term = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(10)
        took = time.monotonic() - t_term
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        listener.close()
    assert rc == 0
    assert took < stop_deadline_s(), (took, os.getloadavg())
    assert listener.times_of("STOPPING=1")

    conn = open_readonly(data / "ledger.sqlite")
    try:
        sessions = [dict(r) for r in conn.execute("SELECT * FROM sessions")]
        assert verify(conn).ok
    finally:
        conn.close()
    assert len(sessions) == 1 and sessions[0]["end_reason"] == "ended"
    # The pedal was down from the console's start (before READY) until SIGTERM (after it).
    assert t_term - t_ready - 0.5 <= sessions[0]["fluoro_time_s"] <= t_term - t_start + 0.5
    assert sessions[0]["air_kerma_mgy"] > 0


class PtyPedal:
    """A foot pedal held down, on a pty reached through a symlink as udev's /dev/fluorosim/pedal:
    it repeats its state (heartbeat and DOWN) every 0.1 s; unplugging closes its end.
    (The state is repeated because opening the port discards what was sent before.)"""

    def __init__(self, link: Path):
        self.link = link
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.master = self.slave = -1

    def plug(self) -> None:
        self.master, self.slave = os.openpty()
        self.link.unlink(missing_ok=True)
        self.link.symlink_to(os.ttyname(self.slave))
        self._stop.clear()
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(0.1):
            os.write(self.master, b"HB\nDOWN\n")

    def unplug(self) -> None:
        self._stop.set()
        self._thread.join()
        self.link.unlink()
        os.close(self.master)
        os.close(self.slave)


def test_camera_and_pedal_that_disappear_and_return(tmp_path):
    # A folder of webcam images of the box at a known pose, played in a loop.
    folder = tmp_path / "frames"
    folder.mkdir()
    pedal = PtyPedal(tmp_path / "pedal")
    pedal.plug()
    config = make_appliance(tmp_path, camera=str(folder), display=DISPLAY, keypad="none", pedal=str(pedal.link))
    cfg = load_appliance(config)
    cam = synthetic_camera(cfg.phantom, cfg.webcam, lambda t: pose_from_angles([0.0, 0.0, 550.0]))
    for k in range(3):
        image, _ = cam.render_at(float(k))
        cv2.imwrite(str(folder / f"frame-{k}.png"), image)

    app = Appliance(ProfileKeeper(config), Notifier({}))
    stop = threading.Event()
    runner = threading.Thread(target=app.run, kwargs={"until": stop.is_set, "signals": False})
    runner.start()

    def banner(start: str) -> bool:
        return any(b.startswith(start) for b in app.supervisor.banners())

    try:
        # The pedal is down: live images.
        assert _wait(lambda: app.stats.frames >= 3, 30), app.supervisor.banners()
        assert not banner("tracking lost") and not banner("pedal")

        folder.rename(tmp_path / "unplugged")
        assert _wait(lambda: banner("tracking lost: camera lost"), 10)
        frames = app.stats.frames
        time.sleep(0.3)
        held = _image_region(_screen(tmp_path / "data"))
        time.sleep(0.6)
        assert app.stats.frames <= frames + 1            # nothing new to draw...
        # ...so the last image stays on screen, unchanged (a live image's noise would differ).
        assert _shows_the_water_cylinder(held)
        assert np.array_equal(_image_region(_screen(tmp_path / "data")), held)
        assert app.supervisor.worker_problems == []      # and the appliance is healthy

        (tmp_path / "unplugged").rename(folder)
        assert _wait(lambda: not banner("tracking lost") and app.stats.frames >= frames + 3, 15)

        # Pulling the pedal's cable releases the pedal: fluoroscopy stops, the image is held.
        pedal.unplug()
        assert _wait(lambda: banner(f"pedal: {pedal.link}"), 10), app.supervisor.banners()
        assert _wait(lambda: not app.console_state.get()[0].fluoro_on, 2)
        frames = app.stats.frames
        time.sleep(0.6)
        assert app.stats.frames <= frames + 1
        assert app.supervisor.worker_problems == []

        # Plugged back in (the driver retries once a second) and pressed again: live once more.
        pedal.plug()
        assert _wait(lambda: not banner("pedal") and app.stats.frames >= frames + 3, 15), app.supervisor.banners()
    finally:
        stop.set()
        runner.join(10)
        pedal.unplug()
    assert not runner.is_alive()


class FailingGpu:
    """An OpenCL GPU whose driver fails on the next frame (a lost device, out of resources). This
    machine has only PoCL's CPU device, so the failure is staged around the real renderer: the
    appliance sees a GPU that raises, as pyopencl does, when a kernel cannot be enqueued."""

    def __init__(self, renderer):
        import pyopencl as cl
        self._renderer = renderer
        self.device = SimpleNamespace(type=cl.device_type.GPU, name="staged GPU")

    def render(self, *args, **kwargs):
        raise RuntimeError("clEnqueueNDRangeKernel failed: OUT_OF_RESOURCES")

    def __getattr__(self, name):
        return getattr(self._renderer, name)


def test_an_opencl_device_failure_falls_back_to_the_cpu_and_keeps_imaging(tmp_path):
    config = make_appliance(tmp_path, display=DISPLAY, render_px=128)     # the pedal is held throughout
    text = config.read_text().replace("cpu_fallback_matrix_px: 256", "cpu_fallback_matrix_px: 64")
    assert "cpu_fallback_matrix_px: 64" in text
    config.write_text(text)
    app = Appliance(ProfileKeeper(config), Notifier({}))
    first = app.parts.renderer
    assert first.shape == (128, 128)
    app.parts.renderer = FailingGpu(first)
    stop = threading.Event()
    runner = threading.Thread(target=app.run, kwargs={"until": stop.is_set, "signals": False})
    runner.start()
    try:
        assert _wait(lambda: any(b.startswith("OpenCL device failed; rendering on the CPU")
                                 for b in app.supervisor.banners()), 30), app.supervisor.banners()
        assert "OUT_OF_RESOURCES" in app.renderer_fault
        # A new renderer on the CPU device at the smaller fallback matrix, with the case's phases
        # prepared again there; live images go on and no worker has died.
        renderer = app.parts.renderer
        assert renderer is not first and is_cpu(renderer) and renderer.shape == (64, 64)
        frames = app.stats.frames
        assert _wait(lambda: app.stats.frames >= frames + 5, 60), app.supervisor.banners()
        assert _shows_the_water_cylinder(_image_region(_screen(tmp_path / "data")))
        assert app.supervisor.worker_problems == []
        assert "renderer staged GPU" not in app.status_text() and "(CPU)" in app.status_text()
    finally:
        stop.set()
        runner.join(10)
    assert not runner.is_alive()


class RecordingRenderer:
    """The appliance's own ProgressiveRenderer, with what each live frame asked of it written down."""

    def __init__(self, renderer):
        self._renderer = renderer
        self.asked: list[tuple[np.ndarray, np.ndarray | None]] = []

    def render(self, volume, T_xray_from_ct, view, **kwargs):
        self.asked.append((np.array(T_xray_from_ct), kwargs.get("measured")))
        return self._renderer.render(volume, T_xray_from_ct, view, **kwargs)

    def __getattr__(self, name):
        return getattr(self._renderer, name)


def test_each_live_frame_is_rendered_with_the_pose_measured_before_the_filter(tmp_path):
    """The render worker hands the renderer the tracker's measured pose beside the filtered one
    (the renderer judges a stop on it, progressive.py): on the demo path's first seconds, which
    move, every live frame has one, a rigid transform, and the filter's lag sets the two apart."""
    config = make_appliance(tmp_path, display=DISPLAY)
    app = Appliance(ProfileKeeper(config), Notifier({}))
    spy = app.parts.renderer = RecordingRenderer(app.parts.renderer)
    stop = threading.Event()
    runner = threading.Thread(target=app.run, kwargs={"until": stop.is_set, "signals": False})
    runner.start()
    try:
        assert _wait(lambda: len(spy.asked) >= 20, 60), app.supervisor.banners()
    finally:
        stop.set()
        runner.join(10)
    assert not runner.is_alive()
    asked = spy.asked[:20]
    assert all(measured is not None for _, measured in asked)
    for _, measured in asked:
        np.testing.assert_allclose(measured[:3, :3] @ measured[:3, :3].T, np.eye(3), atol=1e-9)
    apart = [np.linalg.norm(T[:3, 3] - measured[:3, 3]) for T, measured in asked]
    assert np.median(apart) > 0.05                  # mm: the filter lags the moving path


def test_without_a_gpu_a_profile_without_a_matrix_renders_the_cpu_s_and_keeps_it_on_reload(tmp_path):
    """A profile naming no render_matrix_px on PoCL's CPU device renders daemon.cpu_fallback_matrix_px
    (here 64 of the detector's 128), and a reloaded fluoroscope profile is read out at that matrix
    too, not at the detector's."""
    from appliance.xray.device import is_cpu_device, pick_device

    if not is_cpu_device(pick_device("auto")):
        pytest.skip("this machine has a GPU: the appliance renders the detector's matrix there")
    config = make_appliance(tmp_path, display=DISPLAY, render_px=64)
    text = config.read_text()
    assert "render_matrix_px: 64" in text and "cpu_fallback_matrix_px: 256" in text
    config.write_text(text.replace("render_matrix_px: 64", "").replace("cpu_fallback_matrix_px: 256",
                                                                          "cpu_fallback_matrix_px: 64"))
    app = Appliance(ProfileKeeper(config), Notifier({}))
    try:
        assert app.parts.renderer.shape == (64, 64) and app.keeper.current.fluoroscope.detector.columns == 128
        assert app.status_text().endswith("(CPU) at 64 px")        # what systemctl status shows
        fluoroscope = tmp_path / "configs" / "fluoroscopes" / "generic-ii-carm.yaml"
        edited = fluoroscope.read_text().replace("kvp: 75", "kvp: 80", 1)
        assert edited != fluoroscope.read_text()
        fluoroscope.write_text(edited)
        app.reload()
        assert app.parts.renderer.fluoroscope.tube.kvp == 80
        assert app.parts.renderer.shape == (64, 64)
    finally:
        app.parts.close()
