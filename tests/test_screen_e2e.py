"""What the monitor shows, read back from the framebuffer of the running appliance
(`fluorosim run` as its own process), not from the compositor's inputs."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
from appliance_setup import REPO, make_appliance
from ruamel.yaml import YAML

from appliance.config import load_appliance
from appliance.tracking.scene import synthetic_camera
from appliance.tracking.trajectory import pose_from_angles
from drivers.framebuffer import open_display

DISPLAY = (320, 256)


def screen(data_dir: Path) -> np.ndarray | None:
    path = data_dir / "screen.raw"
    if not path.exists():
        return None
    display = open_display("file", str(path), *DISPLAY, 32, read_only=True)
    try:
        return display.read_back()
    finally:
        display.close()


def image_region(rgb: np.ndarray) -> np.ndarray:
    """Grey levels of the middle of the field, clear of every corner text."""
    h, w = rgb.shape[:2]
    return rgb[h // 2 - h // 6:h // 2 + h // 6, w // 2 - h // 6:w // 2 + h // 6].astype(int)


def still_box(tmp_path: Path, config: Path, empty: bool = False) -> None:
    """The camera's folder: webcam images of the box alternating between two poses 2 mm apart
    (or of nothing), so every camera frame is a new pose to render, as when a trainee's hand
    is never quite still, yet each pose's image is always the same."""
    folder = tmp_path / "frames"
    folder.mkdir()
    cfg = load_appliance(config)
    cam = synthetic_camera(cfg.phantom, cfg.webcam, lambda t: pose_from_angles([0.0, 0.0, 550.0 + 2.0 * (int(t) % 2)]))
    for k in range(4):
        image, _ = cam.render_at(float(k))
        if empty:
            image[:] = 128                              # the box has left the webcam's view
        cv2.imwrite(str(folder / f"frame-{k}.png"), image)


def still_trajectory(config: Path) -> None:
    """The synthetic webcam held still over the box: a new camera frame (and so a new live
    image) every frame time, each of the same pose."""
    yaml = YAML(typ="rt")
    data = yaml.load(config.read_text())
    path = config.parent / "trajectories" / "still.jsonl"
    path.write_text('{"t": 0, "position_mm": [0, 0, 550]}\n{"t": 100, "position_mm": [0, 0, 550]}\n')
    data["devices"]["camera"]["trajectory"] = "trajectories/still.jsonl"
    with open(config, "w") as f:
        yaml.dump(data, f)


def static_noise_free(config: Path) -> None:
    """One phase and no quantum noise: at a still pose every frame is the same image."""
    yaml = YAML(typ="rt")
    case = config.parent / "cases" / "cylinder.yaml"
    data = yaml.load(case.read_text())
    data["phases"] = data["phases"][:1]
    with open(case, "w") as f:
        yaml.dump(data, f)
    fluoroscope = config.parent / yaml.load(config.read_text())["fluoroscope"]
    profile = yaml.load(fluoroscope.read_text())
    profile["display"]["noise"] = False
    with open(fluoroscope, "w") as f:
        yaml.dump(profile, f)


class Running:
    """`fluorosim run` as its own process, its log collected as it comes."""

    def __init__(self, config: Path):
        env = dict(os.environ)
        env.pop("NOTIFY_SOCKET", None)
        self.proc = subprocess.Popen([sys.executable, "-m", "appliance", "run", "--config", str(config)], cwd=REPO,
                                     env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append(line)

    def said(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))

    def poll(self):
        return self.proc.poll()

    def stop(self) -> str:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._reader.join(5)
        return "".join(self.lines)


def test_invert_flips_every_displayed_pixel(tmp_path):
    # The pedal is held throughout; INVERT is pressed every 2 s of console time. Each screen read
    # back is classed by the ledger's INVERT presses before it; only screens at least 1 s after a
    # press count (a held image re-composed for a moment must not pass for a rendered one). Four
    # presses give two settled seconds of each polarity, the first normal one before any press.
    script = ['{"t": 0.0, "hold": "pedal", "for_s": 600.0}'] + [f'{{"t": {2.0 * k}, "tap": "invert"}}'
                                                                for k in range(1, 30)]
    config = make_appliance(tmp_path, script=script, display=DISPLAY)
    static_noise_free(config)
    still_trajectory(config)
    proc = Running(config)
    captures: list[tuple[float, np.ndarray]] = []
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and proc.poll() is None and len(invert_presses(tmp_path)) < 4:
            time.sleep(0.2)
            rgb = screen(tmp_path / "data")
            if rgb is not None:
                captures.append((time.time(), image_region(rgb)))
    finally:
        out = proc.stop()
    presses = invert_presses(tmp_path)
    settled = {True: [], False: []}
    for t, region in captures:
        before = [p for p in presses if p <= t]
        if before and t - before[-1] < 1.0 or (not before and region.std() < 2):
            continue
        settled[len(before) % 2 == 1].append(region)
    assert len(settled[True]) >= 3 and len(settled[False]) >= 3, (len(settled[True]), len(settled[False]), out[-800:])
    normal = settled[False][-1]
    assert normal.std() > 2 and 20 < normal.mean() < 235, "a real image on screen"
    for inverted in settled[True]:
        worst = int(np.abs(inverted + normal - 255).max())
        assert worst <= 1, f"INVERT on: a pixel p shows as {worst} away from 255 - p"


def invert_presses(tmp_path: Path) -> list[float]:
    """Wall times (s) of the INVERT presses in the ledger, in order."""
    path = tmp_path / "data" / "ledger.sqlite"
    if not path.exists():
        return []
    try:
        conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=1.0)
        try:
            return [r[0] for r in conn.execute("SELECT t_wall FROM events WHERE kind = 'invert' ORDER BY id")]
        finally:
            conn.close()
    except sqlite3.Error:
        return []


def test_tracking_lost_banner_is_on_screen_when_the_markers_leave_the_view(tmp_path):
    script = ['{"t": 0.0, "hold": "pedal", "for_s": 600.0}']
    config = make_appliance(tmp_path, camera=str(tmp_path / "frames"), script=script, display=DISPLAY)
    still_box(tmp_path, config, empty=True)
    proc = Running(config)
    found = False
    try:
        deadline = time.monotonic() + 60
        # Once the appliance has said so, the banner must be on the screen it shows.
        while time.monotonic() < deadline and not proc.said("tracking lost") and proc.poll() is None:
            time.sleep(0.2)
        while time.monotonic() < deadline and not found and proc.poll() is None:
            time.sleep(0.2)
            rgb = screen(tmp_path / "data")
            if rgb is None:
                continue
            r, g, b = (rgb[..., i].astype(int) for i in range(3))
            amber = (r > 220) & (g > 140) & (g < 200) & (b < 40)    # a warning banner's fill
            found = amber.sum() > 0.02 * rgb.shape[0] * rgb.shape[1]
    finally:
        out = proc.stop()
    assert "tracking lost" in out, out[-800:]
    assert found, f"no warning banner on screen; appliance said: {out[-800:]}"
