"""Key-moment snapshots and the contact sheet, checked pixel by pixel against known images."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import pytest

from appliance.daemon.snapshots import Snapshotter, contact_sheet, key_moments, read_png, roll_deg
from appliance.geometry import make_transform, rotation_about


def _pose(roll_deg_true: float, yaw_deg: float = 0.0) -> np.ndarray:
    # Camera above the box looking down at its top face: phantom z maps to webcam -z.
    R_facing = rotation_about([1, 0, 0], math.pi)
    R = rotation_about([0, 0, 1], math.radians(yaw_deg)) @ R_facing @ rotation_about([1, 0, 0], math.radians(roll_deg_true))
    return make_transform(R, [10.0, -20.0, 600.0])


@pytest.mark.parametrize("roll", [0.0, 30.0, 90.0, -90.0, -45.0, 170.0])
@pytest.mark.parametrize("yaw", [0.0, 37.0, -120.0])
def test_roll_is_the_rotation_about_the_box_long_axis(roll, yaw):
    assert roll_deg(_pose(roll, yaw)) == pytest.approx(roll, abs=1e-9)


def test_contact_sheet_places_each_image_in_its_tile():
    colours = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (0, 255, 255)]
    images = [(f"tile {k}", np.full((100, 200, 3), c, np.uint8)) for k, c in enumerate(colours)]
    sheet = contact_sheet(images, columns=2, tile_width=100, label_height=20)
    # Tiles 100 x 50 (the 200 x 100 aspect), captions 20 high: 3 rows of 70, 2 columns of 100.
    assert sheet.shape == (210, 200, 3)
    for k, c in enumerate(colours):
        r, col = divmod(k, 2)
        y, x = r * 70, col * 100
        assert (sheet[y:y + 50, x:x + 100] == c).all(), k
        assert (sheet[y + 50:y + 70, x:x + 100] != c).any()  # the caption strip is not the image
    assert (sheet[140:190, 100:200] == 24).all()  # the empty sixth cell stays background


@dataclass
class _Frame:
    rgb: np.ndarray
    state: SimpleNamespace
    live: bool = True
    image: np.ndarray | None = field(default_factory=lambda: np.zeros((4, 4), np.float32))
    pose: object = None
    banners: list = field(default_factory=list)
    saved_flash: bool = False

    def rgb_source(self):
        return self.rgb


def _state(**kw):
    base = dict(zoom=1, fov_mm=230.0, collimation_mm=(230.0, 230.0), invert=False, breath_hold=False, alarm_sounding=False, fluoro_on=True)
    base.update(kw)
    return SimpleNamespace(**base)


def test_each_moment_is_taken_once_from_the_first_frame_that_shows_it(tmp_path):
    snap = Snapshotter(tmp_path, key_moments())
    alarm_on = np.full((9, 8, 3), 50, np.uint8)
    alarm_on[6:, :] = (220, 0, 0)                       # the red banner in the lower third
    frames = [
        _Frame(np.full((9, 8, 3), 10, np.uint8), _state()),
        _Frame(np.full((9, 8, 3), 10, np.uint8), _state()),     # the same pixels again: no second name for them
        _Frame(np.full((9, 8, 3), 15, np.uint8), _state()),     # zoom 1 still: not yet "back to zoom 1"
        _Frame(np.full((9, 8, 3), 30, np.uint8), _state(zoom=3, fov_mm=130.0, collimation_mm=(130.0, 130.0))),
        _Frame(np.full((9, 8, 3), 20, np.uint8), _state()),
        _Frame(np.full((9, 8, 3), 40, np.uint8), _state(collimation_mm=(120.0, 230.0))),
        _Frame(np.full((9, 8, 3), 45, np.uint8), _state(alarm_sounding=True)),   # banner in its dark half
        _Frame(alarm_on, _state(alarm_sounding=True)),
        _Frame(np.full((9, 8, 3), 60, np.uint8), _state(alarm_sounding=False, fluoro_on=False), live=False),
        _Frame(np.full((9, 8, 3), 65, np.uint8), _state(alarm_sounding=False, fluoro_on=False), live=False),
        _Frame(np.full((9, 8, 3), 70, np.uint8), _state(), pose=SimpleNamespace(pose=SimpleNamespace(
            ok=True, T_webcam_from_phantom=_pose(88.0)))),
    ]
    for f in frames:
        snap(f)
    expect = {"first-live": 10, "zoom-1": 20, "zoom-3": 30, "collimated": 40, "alarm": alarm_on,
              "alarm-reset": 60, "last-image-hold": 65, "roll-plus-90": 70}
    assert set(snap.taken) == set(expect)
    assert snap.missing() == ["zoom-2", "zoom-4", "inverted", "roll-minus-90", "end-expiration",
                              "end-inspiration", "breath-hold", "saved", "tracking-lost"]
    for name, value in expect.items():
        assert (read_png(snap.taken[name]) == value).all(), name
    assert snap.taken["zoom-3"].name == "03-zoom-3.png"
    pictures = [read_png(p).tobytes() for p in snap.taken.values()]
    assert len(set(pictures)) == len(pictures), "no snapshot is a copy of another"


@pytest.mark.parametrize("width, height", [(1280, 1024), (1920, 1080)])
def test_the_alarm_banner_is_read_from_the_composed_screen_in_both_flash_phases(width, height):
    from appliance.daemon.snapshots import alarm_banner_shown
    from appliance.display.compositor import ALARM_FLASH_PERIOD_S, Compositor, Overlay

    overlay = Overlay(live=True, zoom=1, fov_mm=230.0, collimation_mm=None, fluoro_time_s=301.0, air_kerma_mgy=1.0,
                      dap_gy_cm2=0.1, mode="continuous", alarm=True, saved_flash=False, invert=False, breath_hold=False,
                      case="c", operator="o", fluoroscope="f", warnings=["tracking lost: bring the box markers into view"],
                      fps=20.0)
    comp = Compositor(width, height)
    image = np.random.default_rng(0).uniform(0, 1, (256, 256)).astype(np.float32)
    assert alarm_banner_shown(comp.compose(image, overlay, now=5.0 + 0.1 * ALARM_FLASH_PERIOD_S))
    assert not alarm_banner_shown(comp.compose(image, overlay, now=5.0 + 0.7 * ALARM_FLASH_PERIOD_S))


def _posed(value: int, t: float, inspired: float, T: np.ndarray, **state) -> SimpleNamespace:
    rgb = np.full((8, 8, 3), value, np.uint8)
    return SimpleNamespace(rgb_source=lambda: rgb, image=rgb, state=_state(**state), live=True, t_wall=t, banners=[],
                           saved_flash=False, inspired=inspired,
                           pose=SimpleNamespace(pose=SimpleNamespace(ok=True, T_webcam_from_phantom=T)))


def test_breathing_pair_is_taken_at_one_pose_once_each_extreme_has_settled(tmp_path):
    """End-expiration, then end-inspiration at the same pose, each only after the breath (held)
    and the C-arm have stood still for more than BREATH_SETTLE_FRAMES images, so the recursive
    filter shows the still anatomy; the breath-hold snapshot comes from a hold elsewhere."""
    from appliance.daemon.snapshots import BREATH_SETTLE_FRAMES

    snap = Snapshotter(tmp_path, key_moments())
    home, moved, other = _pose(0.0), _pose(0.0, yaw_deg=2.0), _pose(0.0, yaw_deg=20.0)
    n = BREATH_SETTLE_FRAMES + 3
    frames = [_posed(1, 0.0, 0.5, home)]                                            # first live
    frames += [_posed(10 + k, 1.0 + k, 0.01, home, breath_hold=True) for k in range(n)]
    frames += [_posed(30 + k, 20.0 + k, 0.99, moved) for k in range(n)]              # another pose: not the pair
    frames += [_posed(50, 30.0, 0.6, home)]                                           # breathing on
    frames += [_posed(60 + k, 31.0 + k, 0.995, home, breath_hold=True) for k in range(n)]
    frames += [_posed(80 + k, 40.0 + k, 0.2, other, breath_hold=True) for k in range(n)]
    for f in frames:
        snap(f)
    # Each run's first image starts the count, so the image BREATH_SETTLE_FRAMES after it is taken.
    assert (read_png(snap.taken["end-expiration"]) == 10 + BREATH_SETTLE_FRAMES).all()
    assert (read_png(snap.taken["end-inspiration"]) == 60 + BREATH_SETTLE_FRAMES).all()
    assert (read_png(snap.taken["breath-hold"]) == 80 + BREATH_SETTLE_FRAMES).all()
    kept = snap.kept["end-inspiration"]
    assert kept.inspired == 0.995 and (kept.image == 60 + BREATH_SETTLE_FRAMES).all()


def test_the_background_writer_runs_ten_nice_steps_below_the_thread_that_took_the_snapshot(tmp_path):
    """The PNG writer yields the CPU to the render worker: its thread's nice value (read from the
    kernel) is 10 above that of the thread the snapshot was taken on (at most 19, Linux's last)."""
    import os
    import threading
    import time

    from appliance.daemon.snapshots import Moment

    screen = np.zeros((6, 10, 3), np.uint8)
    shown = SimpleNamespace(rgb_source=lambda: screen, state=SimpleNamespace(alarm_sounding=False))
    snapper = Snapshotter(tmp_path, [Moment("first", "first image", lambda f: True)], background=True)
    want = min(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) + 10, 19)
    snapper(shown)
    writer = snapper._writer
    assert writer is not None
    seen, deadline = None, time.monotonic() + 5.0
    while seen != want and time.monotonic() < deadline:      # the writer sets it as it starts
        seen = os.getpriority(os.PRIO_PROCESS, writer.native_id)
        time.sleep(0.01)
    snapper.flush()
    assert seen == want
    assert (tmp_path / "00-first.png").is_file()
