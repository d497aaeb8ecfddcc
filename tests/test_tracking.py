"""Tracking the box phantom on synthetic frames rendered at known poses."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.cli import main
from appliance.config import PhantomProfile, WebcamProfile, load_profile
from appliance.errors import FluorosimError
from appliance.geometry import rotation_angle_deg
from appliance.tracking.markers import MarkerDetector, marker_corners, ray_to_normal_deg
from appliance.tracking.scene import synthetic_camera
from appliance.tracking.tracker import Tracker
from appliance.tracking.trajectory import Trajectory, pose_from_angles

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "configs" / "phantoms" / "box-v1.yaml"
WEBCAM = ROOT / "configs" / "webcams" / "generic-720p.yaml"


@pytest.fixture(scope="module")
def profiles():
    return load_profile(PHANTOM, PhantomProfile), load_profile(WEBCAM, WebcamProfile)


def render(profiles, T, seed=1, **kw):
    phantom, webcam = profiles
    return synthetic_camera(phantom, webcam, Trajectory.still(T), seed=seed, **kw).render_at(0.0)


def errors(T, truth):
    return np.linalg.norm(T[:3, 3] - truth[:3, 3]), rotation_angle_deg(T, truth)


# Poses across the working range: near and far, tilted, and the patient rolled by +-90 degrees.
POSES = [pose_from_angles([0, 0, 400], 0, 0, 0), pose_from_angles([30, -20, 550], 35, 10, 20),
         pose_from_angles([-20, 10, 700], -60, -12, -25), pose_from_angles([0, 15, 600], 90, 5, 0),
         pose_from_angles([10, 0, 500], -90, -8, 10)]


@pytest.mark.parametrize("T", POSES)
def test_joint_pose_is_sub_millimetre(profiles, T):
    image, truth = render(profiles, T)
    pose = Tracker(*profiles, method="auto", smoothing=False).track(image, 1.0)
    assert pose.ok and pose.method == "joint" and pose.t_monotonic == 1.0
    et, er = errors(pose.T_webcam_from_phantom, truth)
    assert et < 0.5 and er < 0.2, (et, er)
    assert pose.rms_px < 0.5


def test_markers_reported_are_those_facing_the_camera(profiles):
    phantom, _ = profiles
    T = pose_from_angles([0, 0, 550], 90, 0, 0)     # rolled: the -y side faces the camera
    image, truth = render(profiles, T)
    pose = Tracker(*profiles, smoothing=False).track(image, 0.0)
    facing = [m.id for m in phantom.markers if ray_to_normal_deg(truth @ m.T()) < 60]
    assert set(facing) <= set(pose.markers)
    assert set(pose.markers) <= {6, 7, 8, 9, 10, 11, 0, 1, 2, 3, 4, 5}
    assert {9, 10, 11} <= set(pose.markers) or {6, 7, 8} <= set(pose.markers)


def test_single_marker_method_follows_the_paper(profiles):
    T = pose_from_angles([20, 0, 500], 30, 5, 10)
    image, truth = render(profiles, T)
    tracker = Tracker(*profiles, method="marker", smoothing=False)
    pose = tracker.track(image, 0.0)
    assert pose.ok and pose.method == "marker" and len(pose.used) == 1
    # The chosen marker is the most head-on of those seen (angles from the true pose).
    phantom, _ = profiles
    angles = {i: ray_to_normal_deg(truth @ phantom.marker(i).T()) for i in pose.markers}
    assert pose.used[0] == min(angles, key=angles.get)
    et, er = errors(pose.T_webcam_from_phantom, truth)
    assert et < 5 and er < 1.5, (et, er)


def test_detector_corners_match_projection(profiles):
    phantom, webcam = profiles
    T = pose_from_angles([0, 0, 550], 20, 10, 5)
    image, truth = render(profiles, T)
    K, dist = webcam.camera_matrix(), webcam.distortion()
    found = MarkerDetector(phantom.aruco_dictionary, K, dist).detect(image)
    assert len(found) >= 6
    for i, c in found.items():
        Tm = truth @ phantom.marker(i).T()
        expected, _ = cv2.projectPoints(marker_corners(phantom.marker_size_mm), cv2.Rodrigues(Tm[:3, :3])[0],
                                        Tm[:3, 3], K, dist)
        if ray_to_normal_deg(Tm) < 60:
            assert np.abs(c - expected.reshape(4, 2)).max() < 0.15


def test_no_phantom_in_view(profiles):
    image = np.full((720, 1280, 3), 90, np.uint8)
    pose = Tracker(*profiles).track(image, 2.0)
    assert not pose.ok and pose.T_webcam_from_phantom is None and pose.markers == []


def test_a_misplaced_marker_is_left_out(profiles):
    # Marker 3 has slid 15 mm off where the profile says; the joint pose must not follow it.
    phantom, webcam = profiles
    placed = {m.id: m.T() for m in phantom.markers}
    placed[3] = placed[3] @ np.array([[1, 0, 0, 15.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    T = pose_from_angles([0, 0, 500], 10, 5, 0)
    image, truth = render(profiles, T, T_phantom_from_marker=placed)
    pose = Tracker(phantom, webcam, smoothing=False).track(image, 0.0)
    assert pose.ok and 3 in pose.markers and 3 not in pose.used
    et, er = errors(pose.T_webcam_from_phantom, truth)
    assert et < 0.5 and er < 0.2


def test_distorted_webcam(profiles):
    phantom, webcam = profiles
    bent = webcam.model_copy(update={"dist": [-0.2, 0.05, 0.0005, -0.0003, 0.0]})
    T = pose_from_angles([40, 30, 500], -30, 10, 15)
    image, truth = synthetic_camera(phantom, bent, Trajectory.still(T), seed=2).render_at(0.0)
    pose = Tracker(phantom, bent, smoothing=False).track(image, 0.0)
    et, er = errors(pose.T_webcam_from_phantom, truth)
    assert pose.ok and et < 0.5 and er < 0.2
    # The same frame read with the undistorted model is measurably off: the distortion matters.
    wrong = Tracker(phantom, webcam, smoothing=False).track(image, 0.0)
    assert not wrong.ok or errors(wrong.T_webcam_from_phantom, truth)[0] > 2 * et


def test_unknown_method_is_refused(profiles):
    with pytest.raises(FluorosimError, match="tracking method"):
        Tracker(*profiles, method="best")


def test_track_command_json(profiles, tmp_path, capsys):
    paths = []
    truths = []
    for k, T in enumerate(POSES[:2]):
        image, truth = render(profiles, T, seed=k)
        p = tmp_path / f"frame{k}.png"
        cv2.imwrite(str(p), image)
        paths.append(str(p))
        truths.append(truth)
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.zeros((720, 1280, 3), np.uint8))
    rc = main(["track", "--phantom", str(PHANTOM), "--webcam", str(WEBCAM), *paths, str(blank), "--json"])
    assert rc == 0
    lines = [json.loads(l) for l in capsys.readouterr().out.splitlines()]
    assert [l["image"] for l in lines] == paths + [str(blank)]
    for l, truth in zip(lines, truths):
        assert l["ok"] is True and isinstance(l["markers"], list) and l["markers"]
        T = np.array(l["T_webcam_from_phantom"])
        assert T.shape == (4, 4)
        assert errors(T, truth)[0] < 0.5
    assert lines[2] == {"image": str(blank), "ok": False, "T_webcam_from_phantom": None, "markers": []}


def test_track_command_bad_inputs_exit_2_with_one_line(tmp_path, capsys):
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"this is not a png")
    args = ["track", "--phantom", str(PHANTOM), "--webcam", str(WEBCAM), "--json"]
    for bad, name in ((args + [str(junk)], "junk.png"), (args + [str(tmp_path / "absent.png")], "absent.png"),
                      (args[:4] + [str(tmp_path / "no-webcam.yaml"), "--json", str(junk)], "no-webcam.yaml")):
        assert main(bad) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and name in err, err


def test_a_poor_mjpg_webcam_frame_is_still_sub_millimetre(profiles):
    from drivers.camera_scene import RenderSettings
    harsh = RenderSettings(noise_sigma=5.0, blur_sigma_px=1.2, jpeg_quality=70)
    T = pose_from_angles([-30, 20, 650], -45, 10, -20)
    image, truth = render(profiles, T, settings=harsh)
    clean, _ = render(profiles, T)
    assert np.abs(image.astype(int) - clean.astype(int)).mean() > 2      # the degradation is really there
    pose = Tracker(*profiles, smoothing=False).track(image, 0.0)
    et, er = errors(pose.T_webcam_from_phantom, truth)
    assert pose.ok and et < 1.0 and er < 0.5


def test_window_search_finds_the_same_corners(profiles):
    phantom, webcam = profiles
    image, _ = render(profiles, pose_from_angles([0, 0, 600], 20, 5, 10))
    det = MarkerDetector(phantom.aruco_dictionary, webcam.camera_matrix(), webcam.distortion())
    full = det.detect(image)
    xy = np.concatenate(list(full.values()))
    window = (int(xy[:, 0].min()) - 30, int(xy[:, 1].min()) - 30, int(xy[:, 0].max()) + 30, int(xy[:, 1].max()) + 30)
    part = det.detect(image, window)
    assert set(part) == set(full)
    for i in full:
        np.testing.assert_allclose(part[i], full[i], atol=1e-3)


def test_following_a_path_searches_a_window_and_agrees_with_whole_images(profiles, tmp_path):
    phantom, webcam = profiles
    from appliance.tracking.trajectory import load_trajectory
    # Far enough that the box covers part of the image, so a window is smaller than the whole.
    (tmp_path / "path.jsonl").write_text('{"t": 8, "position_mm": [-70, -20, 450], "tilt_deg": 10}\n'
                                         '{"t": 11, "position_mm": [0, 0, 600], "roll_deg": 45}\n')
    path = load_trajectory(tmp_path / "path.jsonl")
    cam = synthetic_camera(phantom, webcam, path, seed=5)
    windowed = Tracker(phantom, webcam, smoothing=False)
    whole = Tracker(phantom, webcam, smoothing=False, window=False)
    for k in range(12):
        t = 9.0 + k / 30.0                      # rolling toward 45 degrees, moving away
        image, truth = cam.render_at(t)
        a, b = windowed.track(image, t), whole.track(image, t)
        assert a.ok and b.ok
        assert np.abs(a.T_webcam_from_phantom - b.T_webcam_from_phantom).max() < 1e-3
        assert errors(a.T_webcam_from_phantom, truth)[0] < 1.0
    assert windowed.window_searches == 11 and windowed.full_searches == 1


def test_a_window_that_misses_markers_falls_back_to_the_whole_image(profiles):
    # Two unrelated views 0.1 s apart: the window around the first holds only part of the second.
    phantom, webcam = profiles
    first, _ = render(profiles, pose_from_angles([-120, -60, 450], 0, 0, 0))
    second, truth = render(profiles, pose_from_angles([110, 70, 500], 30, 10, 0), seed=2)
    windowed, whole = Tracker(phantom, webcam, smoothing=False), Tracker(phantom, webcam, smoothing=False, window=False)
    assert windowed.track(first, 0.0).ok
    a, b = windowed.track(second, 0.1), whole.track(second, 0.1)
    assert windowed.window_searches == 1 and windowed.full_searches == 2
    assert a.markers == b.markers
    np.testing.assert_allclose(a.T_webcam_from_phantom, b.T_webcam_from_phantom, atol=1e-6)


def test_a_1080p_webcam_with_its_own_intrinsics(profiles):
    phantom, _ = profiles
    hd = WebcamProfile(width=1920, height=1080, K=[[1350.0, 0, 959.5], [0, 1350.0, 539.5], [0, 0, 1]],
                       dist=[0.05, -0.02, 0, 0, 0])
    for T in (pose_from_angles([0, 0, 350], 20, 5, 5), pose_from_angles([30, -20, 700], -80, 0, 10)):
        image, truth = synthetic_camera(phantom, hd, Trajectory.still(T), seed=3).render_at(0.0)
        assert image.shape == (1080, 1920, 3)
        pose = Tracker(phantom, hd, smoothing=False).track(image, 0.0)
        et, er = errors(pose.T_webcam_from_phantom, truth)
        assert pose.ok and et < 0.5 and er < 0.2
