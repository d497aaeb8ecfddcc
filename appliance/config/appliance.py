"""The appliance itself: which profiles are active, which devices to open, where data goes.

Paths are relative to the directory of the file that names them.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from .base import Section
from .dicom import Dicom
from .rendering import Rendering
from .teaching import Teaching


class Camera(Section):
    source: str = Field(description="'synthetic' (built-in renderer of the box), a V4L2 device path "
                                    "(/dev/fluorosim/camera, /dev/v4l/by-id/...), or a video file or image folder.")
    webcam: str = Field(description="Webcam intrinsics profile (configs/webcams/*.yaml).")
    width: int = Field(1280, gt=0, le=8192, description="Requested capture width (pixels).")
    height: int = Field(720, gt=0, le=8192, description="Requested capture height (pixels).")
    fps: float = Field(30.0, gt=0, le=240, description="Requested frame rate (1/s).")
    fourcc: Literal["MJPG", "YUYV"] = Field("MJPG", description="Pixel format asked of the V4L2 device.")
    trajectory: str | None = Field(None, description="Synthetic camera only: scripted intensifier path (JSONL), relative to this file.")
    synthetic_nice: int = Field(10, ge=0, le=19, description="Synthetic camera only: how many nice steps below the "
                                                             "appliance its drawing thread runs, so that drawing the "
                                                             "box (which a real webcam's driver does not cost) yields "
                                                             "the CPU to tracking and rendering (nice increments; 0: "
                                                             "the same priority).")


class Keypad(Section):
    source: str = Field(description="'none', 'scripted', an evdev device (path, udev symlink, or 'name:TEXT'), "
                                    "or 'hid:VVVV:PPPP' (USB vendor:product, hex) for hidapi keypads.")
    script: str | None = Field(None, description="Scripted source only: JSONL timeline of key and pedal events, relative to this file.")
    grab: bool = Field(True, description="Take the evdev device exclusively so key presses do not reach a console.")


class Pedal(Section):
    source: str = Field("none", description="'none', 'scripted' (events come from the keypad script), or a serial port "
                                            "(/dev/fluorosim/pedal, /dev/serial/by-id/...).")
    baud: int = Field(9600, gt=0, description="Serial speed (bit/s).")
    press_line: str = Field("DOWN", min_length=1, description="Line the pedal sends when pressed.")
    release_line: str = Field("UP", min_length=1, description="Line the pedal sends when released.")
    heartbeat_line: str = Field("HB", min_length=1, description="Line the pedal sends periodically while connected.")
    silence_timeout_s: float = Field(0.5, gt=0, le=10, description="With no line for this long the pedal counts as released (s).")


class Display(Section):
    target: str = Field(description="A framebuffer device (/dev/fb0), or 'file' for a raw file of explicit geometry.")
    path: str | None = Field(None, description="File target only: the file, relative to data_dir unless absolute.")
    width: int = Field(1280, gt=0, le=8192, description="File target only: width (pixels).")
    height: int = Field(1024, gt=0, le=8192, description="File target only: height (pixels).")
    bpp: Literal[16, 24, 32] = Field(32, description="File target only: bits per pixel.")


class Devices(Section):
    camera: Camera
    keypad: Keypad
    pedal: Pedal = Field(default_factory=Pedal)
    display: Display


class Daemon(Section):
    """How the supervisor keeps the appliance up; the defaults suit a real appliance."""

    stall_timeout_s: float = Field(5.0, gt=0, le=120, description="A worker whose heartbeat is older than this counts as hung "
                                   "and the watchdog is no longer pinged; keep it below the unit's WatchdogSec (s).")
    restart_limit: int = Field(5, ge=0, le=100, description="Restarts of a crashed worker allowed within restart_window_s; "
                               "beyond that the supervisor lets the watchdog restart the whole service.")
    restart_window_s: float = Field(60.0, gt=0, description="Window over which worker restarts are counted (s).")
    disk_min_free_mb: float = Field(500.0, ge=0, description="Below this much free space in data_dir the disk counts as nearly full (MiB).")
    records_reserve_mb: float = Field(16.0, ge=0, le=10_000, description="Saved images and the demo's snapshots are not "
                                      "written while data_dir has less free space than this, which is kept for the dose "
                                      "ledger: a saved image takes a few MiB, a session's events well under one (MiB).")
    health_period_s: float = Field(1.0, gt=0, le=60, description="How often health checks run (s).")
    status_period_s: float = Field(2.0, gt=0, le=60, description="How often a STATUS= line goes to systemd and the log (s).")
    hold_refresh_hz: float = Field(5.0, gt=0, le=60, description="Overlay refresh rate while no new image is rendered (1/s).")
    render_matrix_px: int | None = Field(None, ge=64, le=8192, description="Render the X-ray image at this square matrix "
                                         "instead of the detector's own, scaled up on screen; for a computer too slow "
                                         "for the full matrix; omit to render at the detector's matrix (pixels).")
    cpu_fallback_matrix_px: int = Field(256, ge=64, le=8192, description="Matrix rendered on the CPU, which is far "
                                        "slower than a GPU: after the OpenCL device failed and rendering fell back to "
                                        "it, and where no GPU is found and render_matrix_px is not set (pixels).")
    clock_rate: float = Field(1.0, gt=0, le=100, description="Simulated seconds per wall-clock second for the console and its "
                              "scripted input (fluoroscopy time, dose, alarm); 1 on a real appliance (dimensionless).")
    clock_pace_s: float | None = Field(None, gt=0, le=60, description="On an accelerated clock (the demo's): the most "
                                       "simulated seconds it runs past the last image on screen before it waits for the "
                                       "next, so a slow renderer lengthens the session instead of skipping through it "
                                       "unseen; none: never waits (s, simulated).")
    save_bands: int = Field(64, ge=1, le=1024, description="A saved image's native re-render on a CPU device is cast "
                            "in this many bands of rows, live frames going in between (count).")
    save_device_share: float = Field(0.5, gt=0, le=1, description="While live frames come, that re-render takes at most "
                                     "this share of the time between its bands, the live view the rest (fraction; "
                                     "1: back to back).")
    log_max_mb: float = Field(10.0, gt=0, description="Size at which the log file in data_dir/logs is rotated (MiB).")
    log_backups: int = Field(5, ge=0, le=100, description="Rotated log files kept.")


class Tracking(Section):
    method: Literal["auto", "joint", "marker"] = Field(
        "auto", description="'joint': one PnP over every visible marker's corners (auto); 'marker': the single most "
                            "head-on marker (the seed paper's method).")
    smoothing: bool = Field(True, description="One Euro filter on the pose: removes standstill jitter.")
    min_cutoff_hz: float = Field(0.5, gt=0, le=30, description="Smoothing cut-off at standstill (Hz); lower removes more jitter.")
    beta_per_mm_s: float = Field(0.2, ge=0, le=10, description="Cut-off increase per mm/s of phantom speed (Hz per mm/s); "
                                                                "higher follows motion with less lag.")
    beta_per_deg_s: float = Field(0.4, ge=0, le=10, description="Cut-off increase per deg/s of rotation speed (Hz per deg/s).")
    d_cutoff_hz: float = Field(1.0, gt=0, le=30, description="Cut-off of the speed estimate the filter adapts to (Hz).")
    reset_after_s: float = Field(0.5, gt=0, le=60, description="After losing the phantom this long the filter restarts "
                                                               "at the next pose instead of gliding to it (s).")


class ApplianceProfile(Section):
    fluoroscope: str = Field(description="Active fluoroscope profile (configs/fluoroscopes/*.yaml).")
    case: str = Field(description="Active case (configs/cases/*.yaml).")
    phantom: str = Field(description="Box phantom profile (configs/phantoms/*.yaml).")
    keymap: str = Field(description="Keypad map (configs/keymaps/*.yaml).")
    operator: str = Field("trainee", min_length=1, description="Default operator name recorded with each session.")
    devices: Devices
    tracking: Tracking = Field(default_factory=Tracking, description="How the phantom's pose is computed and smoothed.")
    data_dir: str = Field(description="Ledger, logs, saved images and caches live here; relative to this file unless absolute.")
    daemon: Daemon = Field(default_factory=Daemon, description="Supervisor, watchdog and logging settings.")
    rendering: Rendering = Field(default_factory=Rendering, description="Projection cache and progressive resolution.")
    dicom: Dicom = Field(default_factory=Dicom, description="Identity on the DICOM network and where images and dose "
                         "reports are sent.")
    teaching: Teaching = Field(default_factory=Teaching, description="Exercises, the shot counter and trainee names.")
