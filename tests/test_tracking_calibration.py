"""Composite-marker calibration, webcam calibration and printing markers at scale."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from appliance.cli import main
from appliance.config import PhantomProfile, WebcamProfile, load_profile
from appliance.geometry import make_transform, rotation_about, rotation_angle_deg
from appliance.tracking.composite import CompositeCalibration
from appliance.tracking.markers import marker_corners
from appliance.tracking.scene import markers_stuck_by_hand, synthetic_camera
from appliance.tracking.trajectory import pose_from_angles, random_poses
from appliance.tracking.webcam_calibration import BoardSpec
from drivers.camera_scene import RenderSettings, SceneRenderer, TexturedQuad

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "configs" / "phantoms" / "box-v1.yaml"
WEBCAM = ROOT / "configs" / "webcams" / "generic-720p.yaml"
K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])


def project_corners(T_webcam_from_marker, size=50.0):
    img, _ = cv2.projectPoints(marker_corners(size), cv2.Rodrigues(T_webcam_from_marker[:3, :3])[0],
                               T_webcam_from_marker[:3, 3], K, np.zeros(5))
    return img.reshape(4, 2)


def facing(T_webcam_from_phantom, layout, ids):
    """Exact corners of the markers of `ids` that face the camera (no rendering: the graph logic alone)."""
    out = {}
    for i in ids:
        Tm = T_webcam_from_phantom @ layout[i]
        t, n = Tm[:3, 3], Tm[:3, 2]
        if -t @ n / np.linalg.norm(t) > 0.3:
            out[i] = project_corners(Tm)
    return out


def chain_layout():
    """Four markers in a row on a flat strip, 80 mm apart, each turned a little about its normal."""
    return {i: make_transform(rotation_about((0, 0, 1), np.radians(7 * i)), [80.0 * i, 0, 0]) for i in range(4)}


def looking_at(x_mm, z_mm=500.0, tilt_deg=0.0):
    R = np.diag([1.0, -1.0, -1.0]) @ rotation_about((0, 1, 0), np.radians(tilt_deg))
    return make_transform(R, [-x_mm, 0, z_mm])


def test_graph_connects_a_chain_and_composes_along_it():
    layout = chain_layout()
    cal = CompositeCalibration([0, 1, 2, 3], 0, np.eye(4), 50.0, K, np.zeros(5))
    # Each view shows only two neighbours, so marker 3 is reached only through 1 and 2.
    for a in range(3):
        cal.add({i: c for i, c in facing(looking_at(80 * a + 40), layout, [a, a + 1]).items()})
        assert cal.connected() == (a == 2)
    assert cal.missing() == []
    assert set(cal.edges) == {(0, 1), (1, 2), (2, 3)}
    got = cal.layout()
    for i in range(4):
        assert np.linalg.norm(got[i][:3, 3] - layout[i][:3, 3]) < 0.05
        assert rotation_angle_deg(got[i], layout[i]) < 0.05


def test_an_edge_is_replaced_only_by_a_better_view():
    layout = chain_layout()
    cal = CompositeCalibration([0, 1], 0, np.eye(4), 50.0, K, np.zeros(5))
    cal.add(facing(looking_at(40, tilt_deg=25), layout, [0, 1]))
    oblique = cal.edges[(0, 1)].quality_deg
    cal.add(facing(looking_at(40, tilt_deg=5), layout, [0, 1]))
    better = cal.edges[(0, 1)].quality_deg
    assert better < oblique
    # A worse view afterwards leaves the edge alone, even if it disagrees.
    bad = facing(looking_at(40, tilt_deg=35), layout, [0, 1])
    bad[1] = bad[1] + 3.0
    kept = cal.edges[(0, 1)].T_a_from_b.copy()
    cal.add(bad)
    assert cal.edges[(0, 1)].quality_deg == better
    np.testing.assert_array_equal(cal.edges[(0, 1)].T_a_from_b, kept)


def test_shortest_path_prefers_good_edges_over_few_hops():
    cal = CompositeCalibration([0, 1, 2], 0, np.eye(4), 50.0, K, np.zeros(5))
    from appliance.tracking.composite import Edge
    T01, T12 = make_transform(np.eye(3), [10, 0, 0]), make_transform(np.eye(3), [0, 10, 0])
    cal.edges = {(0, 1): Edge(5.0, T01), (1, 2): Edge(5.0, T12),
                 (0, 2): Edge(70.0, make_transform(np.eye(3), [99, 99, 0]))}
    np.testing.assert_allclose(cal.shortest_paths()[2], T01 @ T12)      # 2 hops at 5 deg beat 1 hop at 70 deg
    cal.edges[(0, 2)] = Edge(8.0, make_transform(np.eye(3), [10, 10, 0.5]))
    np.testing.assert_allclose(cal.shortest_paths()[2][:3, 3], [10, 10, 0.5])


def test_unconnected_markers_are_named():
    layout = chain_layout()
    cal = CompositeCalibration([0, 1, 2, 3], 0, np.eye(4), 50.0, K, np.zeros(5))
    cal.add(facing(looking_at(40), layout, [0, 1]))
    cal.add(facing(looking_at(200), layout, [2, 3]))
    assert cal.missing() == [2, 3] and not cal.connected()


@pytest.fixture(scope="module")
def profiles():
    return load_profile(PHANTOM, PhantomProfile), load_profile(WEBCAM, WebcamProfile)


def test_calibrate_phantom_command_recovers_the_layout(profiles, tmp_path, capsys):
    phantom, webcam = profiles
    rng = np.random.default_rng(5)
    true = markers_stuck_by_hand(phantom, rng)
    poses = random_poses(rng, 40, roll_deg=(-120, 120), tilt_deg=(-50, 50), yaw_deg=(-180, 180))
    cam = synthetic_camera(phantom, webcam, lambda t: poses[int(t)], seed=4, T_phantom_from_marker=true)
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(len(poses)):
        cv2.imwrite(str(frames / f"{k:03d}.bmp"), cam.render_at(k + 0.5)[0])
    profile = tmp_path / "box.yaml"
    original = PHANTOM.read_text()
    profile.write_text(original)
    rc = main(["calibrate", "phantom", "--phantom", str(profile), "--webcam", str(WEBCAM), "--images", str(frames)])
    assert rc == 0
    err = capsys.readouterr().err
    assert "markers seen" in err and "connected to the root: yes" in err
    written = load_profile(profile, PhantomProfile)
    for m in written.markers:
        assert m.calibrated
        assert np.linalg.norm(m.T()[:3, 3] - true[m.id][:3, 3]) < 1.0, m.id
        assert rotation_angle_deg(m.T(), true[m.id]) < 0.5, m.id
    text = profile.read_text()
    assert "# The box phantom" in text and "# top" in text          # comments survive
    assert (tmp_path / "box.yaml.bak").read_text() == original


def test_calibrate_phantom_refuses_when_markers_never_connect(profiles, tmp_path, capsys):
    phantom, webcam = profiles
    # Views of the top face only: the side and end markers are never seen.
    frames = tmp_path / "frames"
    frames.mkdir()
    cam = synthetic_camera(phantom, webcam, lambda t: pose_from_angles([0, 0, 550], 0, 3 * t, 5 * t), seed=2)
    for k in range(3):
        cv2.imwrite(str(frames / f"{k}.bmp"), cam.render_at(float(k))[0])
    profile = tmp_path / "box.yaml"
    profile.write_text(PHANTOM.read_text())
    before = profile.read_bytes()
    rc = main(["calibrate", "phantom", "--phantom", str(profile), "--webcam", str(WEBCAM), "--images", str(frames)])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "markers seen 6/14" in err[-2]
    assert "markers [6, 7, 8, 9, 10, 11, 12, 13] were never seen" in err[-1]
    assert profile.read_bytes() == before and not (tmp_path / "box.yaml.bak").exists()


def render_board(spec: BoardSpec, K_true, dist_true, T, seed):
    """A ChArUco board at pose T (board centre, mm) through a camera with known intrinsics."""
    textures = [spec.image(ppm).astype(np.float32) / 255.0 for ppm in (2.0, 4.0, 8.0)]
    quad = TexturedQuad(np.eye(4), spec.squares_x * spec.square_mm / 2, spec.squares_y * spec.square_mm / 2, textures)
    r = SceneRenderer(K_true, dist_true, 1280, 720, None, [quad], RenderSettings(background=40.0), seed=seed)
    return cv2.cvtColor(r.render(T), cv2.COLOR_GRAY2BGR)


def test_calibrate_webcam_command_measures_known_intrinsics(tmp_path, capsys):
    K_true = np.array([[1010.0, 0.0, 652.0], [0.0, 1006.0, 371.0], [0.0, 0.0, 1.0]])
    dist_true = np.array([-0.12, 0.09, 0.0, 0.0, 0.0])
    spec = BoardSpec(7, 5, 30.0, 22.0, "DICT_5X5_100")
    rng = np.random.default_rng(3)
    folder = tmp_path / "board"
    folder.mkdir()
    for k in range(9):
        R = (np.diag([1.0, -1.0, -1.0]) @ rotation_about((1, 0, 0), np.radians(rng.uniform(-35, 35)))
             @ rotation_about((0, 1, 0), np.radians(rng.uniform(-35, 35))) @ rotation_about((0, 0, 1), np.radians(rng.uniform(-20, 20))))
        T = make_transform(R, [rng.uniform(-60, 60), rng.uniform(-40, 40), rng.uniform(330, 450)])
        cv2.imwrite(str(folder / f"b{k:02d}.bmp"), render_board(spec, K_true, dist_true, T, k))
    profile = tmp_path / "cam.yaml"
    profile.write_text(WEBCAM.read_text())
    rc = main(["calibrate", "webcam", "--webcam", str(profile), "--images", str(folder)])
    assert rc == 0
    w = load_profile(profile, WebcamProfile)
    assert w.status == "calibrated" and w.rms_px < 0.3
    Km = w.camera_matrix()
    assert Km[0, 0] == pytest.approx(1010.0, rel=0.01) and Km[1, 1] == pytest.approx(1006.0, rel=0.01)
    assert Km[0, 2] == pytest.approx(652.0, abs=4) and Km[1, 2] == pytest.approx(371.0, abs=4)
    assert w.dist[0] == pytest.approx(-0.12, abs=0.03)
    assert "Generic 720p webcam" in profile.read_text() and (tmp_path / "cam.yaml.bak").exists()


def test_print_markers_at_exact_scale(tmp_path, profiles):
    phantom, _ = profiles
    rc = main(["print-markers", "--phantom", str(PHANTOM), "--out", str(tmp_path), "--dpi", "254"])
    assert rc == 0
    # 254 dpi is 10 px/mm: a 50 mm marker is 500 px of black square.
    for m in phantom.markers:
        png = Image.open(tmp_path / f"marker-{m.id}.png")
        assert png.size == (500, 500)
        assert png.info["dpi"][0] == pytest.approx(254, abs=0.5)
        a = np.asarray(png)
        assert a[:50, :50].max() == 0          # the black border, one cell of 500/6 px
        got = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)).detectMarkers(
            cv2.copyMakeBorder(a, 60, 60, 60, 60, cv2.BORDER_CONSTANT, value=255))[1]
        assert got is not None and got.ravel().tolist() == [m.id]
    board = Image.open(tmp_path / "charuco-board.png")
    assert board.size == (7 * 300, 5 * 300)
    # The PDF pages print at the same scale: the board's page is 210 mm plus two 10 mm margins wide.
    import re
    pdf = (tmp_path / "charuco-board.pdf").read_bytes()
    width_pt = float(re.search(rb"/MediaBox \[ 0 0 ([0-9.]+) ([0-9.]+) \]", pdf).group(1))
    assert width_pt == pytest.approx((210 + 20) / 25.4 * 72, abs=0.01)
    markers_pdf = (tmp_path / "phantom-markers.pdf").read_bytes()
    assert len(re.findall(rb"/MediaBox", markers_pdf)) == len(phantom.markers)     # one page per marker


def test_live_calibration_without_a_camera_says_so_on_one_line(tmp_path, capsys):
    profile = tmp_path / "cam.yaml"
    profile.write_text(WEBCAM.read_text())
    rc = main(["calibrate", "webcam", "--webcam", str(profile), "--device", str(tmp_path / "video7"), "--seconds", "0.3"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "video7: no such device" in err[0] and "nothing captured in 0.3 s" in err[0]
    assert profile.read_text() == WEBCAM.read_text()


def test_an_invalid_result_is_not_written(tmp_path):
    from appliance.config.yamlfile import ProfileProblems
    from appliance.tracking.profile_update import write_phantom_layout, write_webcam_intrinsics
    cam = tmp_path / "cam.yaml"
    cam.write_text(WEBCAM.read_text())
    with pytest.raises(ProfileProblems, match="focal lengths"):
        write_webcam_intrinsics(cam, np.array([[-900.0, 0, 640], [0, 900, 360], [0, 0, 1]]), np.zeros(5), 0.1, 1280, 720)
    box = tmp_path / "box.yaml"
    box.write_text(PHANTOM.read_text())
    sheared = np.eye(4)
    sheared[0, 1] = 0.2
    with pytest.raises(ProfileProblems, match="not a rigid transform"):
        write_phantom_layout(box, {3: sheared})
    assert cam.read_text() == WEBCAM.read_text() and box.read_text() == PHANTOM.read_text()
    assert not list(tmp_path.glob("*.bak")) and not list(tmp_path.glob(".*tmp"))
