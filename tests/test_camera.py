"""Camera sources: the synthetic webcam's geometry, the capture thread contract, file and V4L2 sources."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.camera import CameraSource, FileCamera, SyntheticCamera, V4L2Camera
from drivers.camera_scene import RenderSettings, SceneRenderer, TexturedQuad, box_marker_quads

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
SIZE = 50.0
DICT = "DICT_4X4_50"


def _pose(rx_deg, ry_deg, t):
    R = cv2.Rodrigues(np.radians([rx_deg, ry_deg, 0.0]))[0] @ np.diag([1.0, -1.0, -1.0])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _single_marker_camera(T, dist=(0.0,) * 5, settings=None, clock=time.monotonic, fps=30.0):
    return SyntheticCamera([7], [np.eye(4)], SIZE, DICT, None, K, dist, 1280, 720,
                           lambda t: T, clock=clock, fps=fps, settings=settings, seed=3)


def _detect(image):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    corners, ids, _ = det.detectMarkers(image)
    return {int(i): c.reshape(4, 2) for c, i in zip(corners, ids.ravel())} if ids is not None else {}


def _truth_corners(T, dist):
    h = SIZE / 2
    obj = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    img, _ = cv2.projectPoints(obj, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, np.asarray(dist, float))
    return img.reshape(4, 2)


@pytest.mark.parametrize("dist", [(0.0,) * 5, (-0.25, 0.08, 0.001, -0.0005, 0.0)])
def test_synthetic_marker_lands_where_opencv_projects_it(dist):
    # The marker is placed off-centre so that the distortion moves it by several pixels.
    T = _pose(15, -20, [120.0, 80.0, 500.0])
    image, _ = _single_marker_camera(T, dist).render_at(0.0)     # (the truth of a moving pose: the thread test)
    assert image.shape == (720, 1280, 3) and image.dtype == np.uint8
    found = _detect(image)
    assert list(found) == [7]
    err = np.linalg.norm(found[7] - _truth_corners(T, dist), axis=1)
    # OpenCV's subpixel corners are good to a few tenths of a pixel (they lean a little inward).
    assert err.mean() < 0.35 and err.max() < 0.6, err
    if dist[0]:
        shift = np.linalg.norm(_truth_corners(T, dist) - _truth_corners(T, (0.0,) * 5), axis=1)
        assert shift.min() > 2.0         # the distortion really is rendered


def test_markers_facing_away_are_not_drawn():
    T = _pose(0, 0, [0.0, 0.0, 500.0])
    back = T @ np.diag([1.0, -1.0, -1.0, 1.0])       # marker normal turned away from the camera
    assert _detect(_single_marker_camera(T).render_at(0.0)[0])
    assert not _detect(_single_marker_camera(back).render_at(0.0)[0])


def test_motion_blur_smears_along_the_motion_only():
    # A white 100 mm square at 600 mm (150 px) moving 20 mm along x during the exposure: 30 px of smear.
    quad = TexturedQuad(np.eye(4), 50.0, 50.0, [np.ones((16, 16), np.float32)])
    r = SceneRenderer(K, (0.0,) * 5, 1280, 720, None, [quad],
                      RenderSettings(noise_sigma=0.0, blur_sigma_px=0.0, background=0.0, antialias_px=0.0))
    T = _pose(0, 0, [0.0, 0.0, 600.0])
    shifted = lambda dx: T @ np.array([[1, 0, 0, dx], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    still = r.render(T)
    moving = r.render(T, exposure=(shifted(-10.0), shifted(10.0)))

    def extent(img, axis):
        lit = np.nonzero(img.max(axis=axis) > 5)[0]
        return lit.max() - lit.min() + 1

    assert extent(still, 0) == pytest.approx(150, abs=5) and extent(still, 1) == pytest.approx(150, abs=5)
    assert extent(moving, 0) - extent(still, 0) == pytest.approx(30, abs=4)     # smeared along x (ramp ends below threshold)
    assert extent(moving, 1) == extent(still, 1)                                # not along y
    # A centred smear keeps the square's centre where the mid-exposure pose puts it.
    cols = moving.sum(axis=0).astype(float)
    assert (cols * np.arange(cols.size)).sum() / cols.sum() == pytest.approx(639.5, abs=0.5)


def test_synthetic_camera_reports_the_mid_exposure_pose():
    T0 = _pose(0, 0, [0.0, 0.0, 500.0])
    cam = SyntheticCamera([7], [np.eye(4)], SIZE, DICT, None, K, (0.0,) * 5, 1280, 720,
                          lambda t: T0 @ np.array([[1, 0, 0, 1000 * t], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
                          settings=RenderSettings(exposure_s=0.02))
    _, truth = cam.render_at(1.0)
    np.testing.assert_allclose(truth[:3, 3], T0[:3, 3] + T0[:3, 0] * 1000 * (1.0 - 0.01), atol=1e-6)


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        self.t += 0.01
        return self.t


def test_synthetic_camera_thread_contract():
    # The box recedes 20 mm/s, so each frame's truth is the trajectory at its own time, not a constant.
    T0 = _pose(0, 0, [0.0, 0.0, 500.0])
    exposure = RenderSettings().exposure_s
    away = lambda t: T0 @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -20.0 * t], [0, 0, 0, 1.0]])
    cam = SyntheticCamera([7], [np.eye(4)], SIZE, DICT, None, K, (0.0,) * 5, 1280, 720, away, fps=200.0, seed=3)
    assert cam.latest() is None and cam.state == "starting"
    with cam:
        first = cam.wait(-1, 5.0)
        assert first is not None and cam.state == "ok"
        second = cam.wait(first.seq, 5.0)
        assert second.seq > first.seq and second.t_monotonic >= first.t_monotonic
        assert cam.latest(after_seq=second.seq + 10**6) is None          # nothing newer: None at once
        assert second.image.shape == (720, 1280, 3)
    closes = []
    for frame in (first, second):
        # The truth is the path at mid-exposure of the frame: 500 mm + 20 mm/s x that time. The
        # path's time is read when the frame is drawn and the frame stamped once it is drawn, so
        # the shutter closed between the camera's start and the stamp.
        np.testing.assert_allclose(frame.truth[:3, :3], T0[:3, :3], atol=1e-12)
        shutter_closed = (frame.truth[2, 3] - 500.0) / 20.0 + exposure / 2
        assert 0.0 <= shutter_closed <= frame.t_monotonic - cam.t0 + 1e-9
        closes.append(shutter_closed)
    assert closes[1] > closes[0]                      # the second frame shows the box further along


def test_synthetic_camera_uses_its_clock_for_the_trajectory():
    clock = FakeClock()
    seen = []
    cam = SyntheticCamera([7], [np.eye(4)], SIZE, DICT, None, K, (0.0,) * 5, 320, 240,
                          lambda t: (seen.append(t), _pose(0, 0, [0.0, 0.0, 500.0 + t]))[1], clock=clock, fps=100.0,
                          settings=RenderSettings(exposure_s=0.0))
    with cam:
        frame = cam.wait(-1, 5.0)
    # The trajectory is asked for times since start on the given clock, not on time.monotonic().
    assert frame is not None and all(0 <= t < 1.0 for t in seen)
    assert any(frame.truth[2, 3] == pytest.approx(500.0 + t, abs=1e-9) for t in seen)


def test_file_camera_reads_a_folder_in_order_and_plays_it(tmp_path):
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k:02d}.png"), np.full((40, 60, 3), 10 * (k + 1), np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    cam = FileCamera(tmp_path, fps=200.0, loop=False)
    frames = list(cam.frames())
    assert [Path(n).name for n, _ in frames] == ["f00.png", "f01.png", "f02.png"]
    assert [int(im[0, 0, 0]) for _, im in frames] == [10, 20, 30]
    with cam:
        deadline = time.monotonic() + 5
        while not cam.finished and time.monotonic() < deadline:
            time.sleep(0.01)
    assert cam.finished and cam.frames_captured == 3 and cam.latest().seq == 3


def test_file_camera_reads_a_video(tmp_path):
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    assert w.isOpened()
    for k in range(5):
        w.write(np.full((48, 64, 3), 40 * k, np.uint8))
    w.release()
    frames = list(FileCamera(path).frames())
    assert len(frames) == 5
    assert abs(int(frames[3][1].mean()) - 120) < 8


def test_missing_file_source_is_reported_not_raised(tmp_path):
    cam = FileCamera(tmp_path / "absent", fps=30.0)
    with cam:
        deadline = time.monotonic() + 5
        while cam.state != "camera lost" and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.state == "camera lost" and "absent" in cam.message
        assert cam.latest() is None


def test_v4l2_missing_device_keeps_retrying_without_raising(tmp_path):
    device = str(tmp_path / "video-gone")
    cam = V4L2Camera(device, retry_interval_s=0.05)
    t0 = time.monotonic()
    cam.start()
    assert time.monotonic() - t0 < 0.5                     # start() never blocks on the device
    try:
        deadline = time.monotonic() + 5
        while cam.open_attempts < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.open_attempts >= 3
        assert cam.state == "camera lost"
        assert device in cam.message and "no such device" in cam.message
        assert cam.latest() is None
    finally:
        t0 = time.monotonic()
        cam.stop()
        assert time.monotonic() - t0 < 1.0


def test_v4l2_on_a_node_that_is_not_a_camera_is_reported(tmp_path):
    node = tmp_path / "video0"
    node.write_bytes(b"\0" * 16)
    cam = V4L2Camera(str(node), retry_interval_s=0.05)
    with cam:
        deadline = time.monotonic() + 5
        while cam.open_attempts < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.state == "camera lost" and "cannot be opened" in cam.message


def test_a_crashing_capture_thread_reports_camera_lost():
    class Broken(CameraSource):
        def _run(self):
            raise RuntimeError("boom")

    cam = Broken()
    with cam:
        deadline = time.monotonic() + 5
        while cam.state != "camera lost" and time.monotonic() < deadline:
            time.sleep(0.01)
    assert cam.state == "camera lost" and "boom" in cam.message


def test_board_quad_renders_a_rectangular_print():
    # A 2:1 white print on black: its rendered width/height ratio is 2 when seen head-on.
    tex = [np.ones((16, 32), np.float32)]
    T = _pose(0, 0, [0.0, 0.0, 600.0])
    r = SceneRenderer(K, (0.0,) * 5, 1280, 720, None, [TexturedQuad(np.eye(4), 100.0, 50.0, tex)],
                      RenderSettings(noise_sigma=0.0, blur_sigma_px=0.0, background=0.0))
    img = r.render(T)
    ys, xs = np.nonzero(img > 100)
    assert (xs.max() - xs.min() + 1) == pytest.approx(2 * 100 * 900 / 600, abs=2)
    assert (ys.max() - ys.min() + 1) == pytest.approx(2 * 50 * 900 / 600, abs=2)


def test_box_marker_quads_include_the_white_margin():
    q = box_marker_quads([3], [np.eye(4)], 60.0, DICT)[0]
    # DICT_4X4: 6 cells across the black square, plus one white cell on each side.
    assert q.half_w_mm == pytest.approx(30.0 * 8 / 6)


def test_a_stalled_source_is_reported_while_its_thread_hangs():
    hang = threading.Event()

    class Hanging(CameraSource):
        stall_timeout_s = 1.0

        def _run(self):
            self._publish(np.zeros((4, 4), np.uint8), time.monotonic())
            self._set_state("ok")
            hang.wait(10)            # stuck inside a driver call: the thread cannot report anything

    cam = Hanging()
    cam.start()
    try:
        assert cam.wait(-1, 2.0) is not None and cam.state == "ok"
        deadline = time.monotonic() + 5
        while cam.state == "ok" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert cam.state == "camera lost" and "no frame for" in cam.message
        assert time.monotonic() - cam.latest().t_monotonic >= 1.0
    finally:
        hang.set()
        cam.stop()


def test_v4l2_frame_time_prefers_a_plausible_driver_stamp():
    class Cap:
        def __init__(self, ms):
            self.ms = ms

        def get(self, prop):
            assert prop == cv2.CAP_PROP_POS_MSEC
            return self.ms

    now = 1000.0
    assert V4L2Camera._capture_time(Cap(999_960.0), now) == pytest.approx(999.96)   # 40 ms in the queue
    assert V4L2Camera._capture_time(Cap(0.0), now) == now                           # no stamp
    assert V4L2Camera._capture_time(Cap(1_000_100.0), now) == now                   # from the future
    assert V4L2Camera._capture_time(Cap(5_000.0), now) == now                       # another clock


def test_a_source_that_comes_back_is_picked_up_again(tmp_path):
    folder = tmp_path / "later"
    cam = FileCamera(folder, fps=100.0)
    with cam:
        deadline = time.monotonic() + 5
        while cam.state != "camera lost" and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.state == "camera lost"
        folder.mkdir()
        cv2.imwrite(str(folder / "a.png"), np.full((8, 8, 3), 77, np.uint8))
        frame = cam.wait(-1, 5.0)
        assert frame is not None and int(frame.image[0, 0, 0]) == 77 and cam.state == "ok"


def test_v4l2_reevaluates_the_device_on_every_retry(tmp_path):
    node = tmp_path / "video3"
    cam = V4L2Camera(str(node), retry_interval_s=0.05)
    with cam:
        deadline = time.monotonic() + 5
        while "no such device" not in cam.message and time.monotonic() < deadline:
            time.sleep(0.01)
        assert "no such device" in cam.message
        node.write_bytes(b"\0" * 16)              # something appears there, but not a camera
        while "cannot be opened" not in cam.message and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.state == "camera lost" and "cannot be opened" in cam.message
