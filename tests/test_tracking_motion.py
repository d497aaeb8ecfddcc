"""Scripted trajectories, pose smoothing, and the camera the appliance profile names."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from appliance.config import FluoroscopeProfile, PhantomProfile, load_appliance, load_profile
from appliance.errors import FluorosimError
from appliance.geometry import make_transform, rotation_about, rotation_angle_deg
from appliance.tracking.markers import ray_to_normal_deg
from appliance.tracking.scene import synthetic_camera
from appliance.tracking.smoothing import PoseFilter, SmoothingSettings
from appliance.tracking.sources import open_camera, tracker_for
from appliance.tracking.tracker import Tracker
from appliance.tracking.trajectory import R_HOME, Trajectory, load_trajectory, pose_from_angles
from drivers.camera import FileCamera, SyntheticCamera, V4L2Camera

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "configs" / "trajectories" / "demo.jsonl"


def test_pose_from_angles_home_and_roll():
    T = pose_from_angles([1, 2, 500])
    # Home: the webcam looks at the top face: phantom z toward the camera, phantom x along image columns.
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [1, 2, 500])
    rolled = pose_from_angles([0, 0, 500], roll_deg=90)
    # Rolled +90 deg about the long axis, the box's +y side (normal phantom +y) faces the camera.
    np.testing.assert_allclose(rolled[:3, :3] @ [0, 1, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(rolled[:3, 0], [1, 0, 0], atol=1e-12)


def test_slerp_between_keyframes():
    a = make_transform(R_HOME, [0, 0, 500])
    b = make_transform(R_HOME @ rotation_about((1, 0, 0), np.radians(80)), [40, 0, 600])
    tr = Trajectory.from_poses([1.0, 3.0], [a, b], loop=False)
    mid = tr(2.0)
    np.testing.assert_allclose(mid[:3, :3], R_HOME @ rotation_about((1, 0, 0), np.radians(40)), atol=1e-9)
    np.testing.assert_allclose(mid[:3, 3], [20, 0, 550])
    np.testing.assert_allclose(tr(0.0), a)          # clamped before the first keyframe
    np.testing.assert_allclose(tr(9.0), b)          # and after the last one
    looped = Trajectory.from_poses([0.0, 2.0], [a, b], loop=True)
    np.testing.assert_allclose(looped(2.5)[:3, 3], looped(0.5)[:3, 3])


def test_still_spans_are_the_keyframe_runs_of_one_pose():
    a = make_transform(R_HOME, [0, 0, 500])
    b = make_transform(R_HOME, [30, 0, 500])
    turned = make_transform(R_HOME @ rotation_about((1, 0, 0), np.radians(1e-3)), [30, 0, 500])
    tr = Trajectory.from_poses([0, 2, 3, 5, 6, 7, 9], [a, b, b, b, turned, turned, a])
    # 3-5 joins 2-3; a thousandth of a degree is motion (5-6); 6-7 still; 7-9 moves back.
    assert tr.still_spans() == [(2.0, 5.0), (6.0, 7.0)]
    assert Trajectory.from_poses([0, 4], [a, b]).still_spans() == []
    # The demo's path stands still three times a loop, two seconds each (its keyframes).
    assert load_trajectory(DEMO).still_spans() == [(6.0, 8.0), (14.0, 16.0), (28.0, 30.0)]


def test_demo_path_covers_the_working_range():
    tr = load_trajectory(DEMO)
    ts = np.arange(0.0, tr.duration, 0.1)
    poses = [tr(t) for t in ts]
    # The box's centre stays within 100 mm of the isocentre along the beam, where a patient lies
    # (the webcam sits on the intensifier, looking back toward the source).
    fluoroscope = load_profile(ROOT / "configs" / "fluoroscopes" / "generic-ii-carm.yaml", FluoroscopeProfile)
    T_xray_from_webcam = np.array(fluoroscope.webcam.T_xray_from_webcam)
    depth = [(T_xray_from_webcam @ T)[2, 3] for T in poses]          # source to box centre (mm)
    iso = fluoroscope.geometry.source_to_isocentre_mm
    assert iso - 100 <= min(depth) and max(depth) <= iso + 100
    # Roll: angle of the box's long-axis rotation away from home, read off where phantom z points.
    rolls = [np.degrees(np.arctan2((T[:3, :3].T @ [0, 0, -1])[1], (T[:3, :3].T @ [0, 0, -1])[2])) for T in poses]
    assert max(rolls) > 85 and min(rolls) < -85
    # Some marker always faces the webcam well enough to be tracked.
    phantom = load_profile(ROOT / "configs" / "phantoms" / "box-v1.yaml", PhantomProfile)
    for T in poses:
        assert min(ray_to_normal_deg(T @ m.T()) for m in phantom.markers) < 60


def test_the_demo_is_tracked_all_along():
    config = load_appliance(ROOT / "configs" / "appliance.yaml")
    cam = open_camera(config)
    tracker = Tracker(config.phantom, config.webcam, smoothing=False)
    for t in np.linspace(0.0, 36.0, 13):
        image, truth = cam.render_at(float(t))
        pose = tracker.track(image, float(t))
        assert pose.ok, t
        assert np.linalg.norm(pose.T_webcam_from_phantom[:3, 3] - truth[:3, 3]) < 1.0, t
        assert rotation_angle_deg(pose.T_webcam_from_phantom, truth) < 0.5, t


def test_a_smoothed_pose_carries_the_pose_measured_before_the_filter():
    """Through the demo path's first stop (it stands still from 6 s): each smoothed pose carries
    the unsmoothed tracker's pose of the same image, on the camera's truth, while the filtered
    pose still lags behind the stop; an unsmoothed pose carries none (it is the measured one)."""
    config = load_appliance(ROOT / "configs" / "appliance.yaml")
    cam = open_camera(config)
    smoothed, bare = Tracker(config.phantom, config.webcam), Tracker(config.phantom, config.webcam, smoothing=False)
    lags = []
    for t in np.arange(5.0, 6.02, 1 / 30):
        image, truth = cam.render_at(float(t))
        pose, plain = smoothed.track(image, float(t)), bare.track(image, float(t))
        assert pose.ok and plain.ok and plain.T_measured is None
        np.testing.assert_array_equal(pose.T_measured, plain.T_webcam_from_phantom)
        assert np.linalg.norm(pose.T_measured[:3, 3] - truth[:3, 3]) < 0.2
        lags.append(np.linalg.norm(pose.T_webcam_from_phantom[:3, 3] - truth[:3, 3]))
    assert lags[-1] > 0.3           # at the stop the filtered pose is still on its way (0.55 mm)


@pytest.mark.parametrize("line, message", [
    ('{"t": 0, "position_mm": [0, 0]}', "position_mm must be three numbers"),
    ('{"t": 0, "position_mm": [0, 0, 500], "pitch": 3}', "unknown key"),
    ('{"position_mm": [0, 0, 500]}', 'needs a number "t"'),
    ("{t: 0}", "not valid JSON"),
    ('{"t": 0, "position_mm": [0, 0, -500]}', "in front of the webcam"),
])
def test_bad_trajectory_names_file_and_line(tmp_path, line, message):
    p = tmp_path / "path.jsonl"
    p.write_text('# a comment\n{"t": -1, "position_mm": [0, 0, 500]}\n' + line + "\n")
    with pytest.raises(FluorosimError, match=message) as e:
        load_trajectory(p)
    assert f"{p}:3:" in str(e.value)


def test_trajectory_times_must_increase(tmp_path):
    p = tmp_path / "path.jsonl"
    p.write_text('{"t": 1, "position_mm": [0, 0, 500]}\n{"t": 1, "position_mm": [0, 0, 510]}\n')
    with pytest.raises(FluorosimError, match=r":2: t = 1 s does not increase"):
        load_trajectory(p)
    with pytest.raises(FluorosimError, match="does not exist"):
        load_trajectory(tmp_path / "absent.jsonl")


def _still(rng, n, sigma_mm, sigma_deg, fps=30.0):
    T = pose_from_angles([10, -5, 550], 20, 5, 10)
    out = []
    for k in range(n):
        R = rotation_about(rng.normal(size=3), np.radians(rng.normal(0, sigma_deg))) @ T[:3, :3]
        out.append((k / fps, make_transform(R, T[:3, 3] + rng.normal(0, sigma_mm, 3))))
    return T, out


def test_filter_removes_standstill_jitter():
    rng = np.random.default_rng(0)
    T, frames = _still(rng, 300, 0.06, 0.02)      # about what the tracker shows at 700 mm, rolled
    f = PoseFilter()
    out = [f(Tm, t) for t, Tm in frames][60:]
    raw = [Tm for _, Tm in frames][60:]
    rms = lambda poses: np.sqrt(np.mean([np.sum((P[:3, 3] - T[:3, 3]) ** 2) for P in poses]))
    rot = lambda poses: np.sqrt(np.mean([rotation_angle_deg(P, T) ** 2 for P in poses]))
    assert rms(out) < 0.35 * rms(raw)
    assert rot(out) < 0.35 * rot(raw)


def test_filter_follows_motion_with_little_lag():
    # 200 mm/s along x: the filter's cut-off opens up, so it trails by a few frames at most.
    f = PoseFilter()
    T0 = pose_from_angles([0, 0, 550])
    lag_mm = []
    for k in range(60):
        t = k / 30.0
        T = make_transform(T0[:3, :3], T0[:3, 3] + [200 * t, 0, 0])
        lag_mm.append(T[0, 3] - f(T, t)[0, 3])
    assert max(lag_mm[30:]) < 200 * 0.03          # under 30 ms behind once moving steadily
    # With the speed term switched off it is a plain low-pass filter and trails far behind.
    slow = PoseFilter(dataclasses.replace(SmoothingSettings(), beta_per_mm_s=0.0))
    for k in range(60):
        t = k / 30.0
        last = slow(make_transform(T0[:3, :3], T0[:3, 3] + [200 * t, 0, 0]), t)
    assert 200 * (59 / 30.0) - last[0, 3] > 5 * max(lag_mm[30:])


def test_filter_restarts_after_a_gap():
    f = PoseFilter()
    a, b = pose_from_angles([0, 0, 500]), pose_from_angles([100, 0, 600], 30)
    f(a, 0.0)
    f(a, 0.033)
    np.testing.assert_allclose(f(b, 5.0), b)          # tracking lost for 5 s: no glide from the old pose


def test_open_camera_from_the_appliance_profile(tmp_path):
    config = load_appliance(ROOT / "configs" / "appliance.yaml")
    cam = open_camera(config)
    assert isinstance(cam, SyntheticCamera)
    image, truth = cam.render_at(14.5)             # the demo path holds the box rolled by 90 deg here
    assert image.shape == (config.webcam.height, config.webcam.width, 3)
    np.testing.assert_allclose(truth, load_trajectory(DEMO)(14.5 - cam.settings.exposure_s / 2))

    for source, kind in (("/dev/fluorosim/camera", V4L2Camera), ("frames", FileCamera)):
        changed = config.appliance.model_copy(update={"devices": config.appliance.devices.model_copy(
            update={"camera": config.appliance.devices.camera.model_copy(update={"source": source})})})
        cam = open_camera(dataclasses.replace(config, appliance=changed))
        assert isinstance(cam, kind)


def test_tracker_for_takes_the_profile_tracking_section(tmp_path):
    config = load_appliance(ROOT / "configs" / "appliance.yaml")
    tr = tracker_for(config)
    assert tr.method == "joint" and tr.filter is not None
    assert tr.filter.s.min_cutoff_hz == config.appliance.tracking.min_cutoff_hz
    changed = config.appliance.model_copy(update={"tracking": config.appliance.tracking.model_copy(
        update={"method": "marker", "smoothing": False})})
    tr = tracker_for(dataclasses.replace(config, appliance=changed))
    assert tr.method == "marker" and tr.filter is None


def test_a_capture_size_the_webcam_was_not_calibrated_at_is_refused():
    config = load_appliance(ROOT / "configs" / "appliance.yaml")
    changed = config.appliance.model_copy(update={"devices": config.appliance.devices.model_copy(
        update={"camera": config.appliance.devices.camera.model_copy(update={"source": "/dev/video0", "width": 1920,
                                                                             "height": 1080})})})
    with pytest.raises(FluorosimError, match="1920x1080 but the webcam profile .* calibrated at 1280x720"):
        open_camera(dataclasses.replace(config, appliance=changed))


def test_a_seeded_synthetic_camera_is_reproducible():
    config = load_appliance(ROOT / "configs" / "appliance.yaml")
    make = lambda seed: synthetic_camera(config.phantom, config.webcam, load_trajectory(DEMO), seed=seed)
    a, b, c = make(7).render_at(3.0)[0], make(7).render_at(3.0)[0], make(8).render_at(3.0)[0]
    assert np.array_equal(a, b) and not np.array_equal(a, c)
