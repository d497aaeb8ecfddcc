"""`fluorosim bench tracking`: accuracy, jitter, lag, calibration and speed on synthetic frames.

Every figure is measured against the pose each frame was rendered at (the synthetic webcam
renders the shipped phantom through the shipped webcam intrinsics, 1280x720, with blur,
motion blur and sensor noise), so nothing here compares the code with itself.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from drivers.camera_scene import RenderSettings, SceneRenderer, TexturedQuad

from ..config.loading import load_profile
from ..config.phantom import PhantomProfile
from ..config.webcam import WebcamProfile
from ..errors import FluorosimError
from ..geometry import make_transform, rotation_about, rotation_angle_deg
from .composite import CompositeCalibration
from .markers import MarkerDetector
from .scene import markers_stuck_by_hand, synthetic_camera
from .sources import DEMO_TRAJECTORY
from .tracker import Tracker
from .trajectory import R_HOME, Trajectory, load_trajectory, pose_from_angles, random_poses
from .webcam_calibration import BoardDetector, BoardSpec, calibrate_webcam

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _errors(T, truth):
    return float(np.linalg.norm(T[:3, 3] - truth[:3, 3])), rotation_angle_deg(T, truth)


def _moving(rng: np.random.Generator, T: np.ndarray, speed_mm_s: float, spin_deg_s: float) -> Trajectory:
    """A 1 s straight path through T at `speed_mm_s`, turning at `spin_deg_s` about a random axis."""
    v = rng.normal(size=3)
    v[2] *= 0.3
    v *= speed_mm_s / np.linalg.norm(v)
    axis = rng.normal(size=3)
    poses = []
    for dt in (-0.5, 0.5):
        R = rotation_about(axis, np.radians(spin_deg_s * dt)) @ T[:3, :3]
        poses.append(make_transform(R, T[:3, 3] + v * dt))
    return Trajectory.from_poses([-0.5, 0.5], poses, loop=False)


#: A worse webcam than the default synthetic one: more noise and blur, and MJPG compression.
HARSH = RenderSettings(noise_sigma=5.0, blur_sigma_px=1.2, jpeg_quality=70, exposure_s=1.0 / 30.0)


def bench_accuracy(phantom, webcam, rng, frames: int, settings: RenderSettings | None = None) -> dict:
    settings = settings or RenderSettings()
    # Unrelated frames: nothing to gain from searching where the markers were in the last one.
    trackers = {m: Tracker(phantom, webcam, m, smoothing=False, window=False) for m in ("joint", "marker")}
    errs: dict[str, list[tuple[float, float]]] = {m: [] for m in trackers}
    found = {m: 0 for m in trackers}
    for T in random_poses(rng, frames):
        cam = synthetic_camera(phantom, webcam, _moving(rng, T, rng.uniform(0, 150), rng.uniform(0, 45)),
                               seed=int(rng.integers(2**31)), settings=settings)
        image, truth = cam.render_at(0.0)
        for m, tr in trackers.items():
            pose = tr.track(image, 0.0)
            if pose.ok:
                found[m] += 1
                errs[m].append(_errors(pose.T_webcam_from_phantom, truth))
    print(f"accuracy: {frames} random 1280x720 frames, phantom 400-700 mm, roll +-90 deg, tilt +-20 deg, "
          f"moving 0-150 mm/s and 0-45 deg/s (motion blur over {settings.exposure_s * 1e3:.0f} ms), noise sigma "
          f"{settings.noise_sigma:g} grey levels, blur sigma {settings.blur_sigma_px:g} px"
          + (f", JPEG quality {settings.jpeg_quality}" if settings.jpeg_quality else ""))
    out = {}
    for m in trackers:
        e = np.array(errs[m]) if errs[m] else np.full((1, 2), np.nan)
        out[m] = (np.median(e[:, 0]), np.median(e[:, 1]))
        print(f"  {m:6s}: found {found[m]}/{frames}; translation error median {np.median(e[:, 0]):.3f} mm, "
              f"p95 {np.percentile(e[:, 0], 95):.3f} mm; rotation error median {np.median(e[:, 1]):.3f} deg, "
              f"p95 {np.percentile(e[:, 1], 95):.3f} deg")
    return out


def bench_intrinsics(phantom, webcam, rng, frames: int) -> None:
    """How much a webcam calibration error costs: frames rendered with the true K, tracked with K off."""
    print(f"sensitivity to the webcam calibration: {frames} still frames, tracked with fx and fy 0.5 % too large "
          "and cx, cy 2 px off")
    K = webcam.camera_matrix().copy()
    K[0, 0] *= 1.005
    K[1, 1] *= 1.005
    K[0, 2] += 2.0
    K[1, 2] -= 2.0
    off = webcam.model_copy(update={"K": K.tolist()})
    tracker = Tracker(phantom, off, "joint", smoothing=False, window=False)
    et, er = [], []
    for T in random_poses(rng, frames):
        image, truth = synthetic_camera(phantom, webcam, Trajectory.still(T), seed=int(rng.integers(2**31))).render_at(0.0)
        pose = tracker.track(image, 0.0)
        if pose.ok:
            e = _errors(pose.T_webcam_from_phantom, truth)
            et.append(e[0])
            er.append(e[1])
    print(f"  joint : translation error median {np.median(et):.3f} mm, rotation error median {np.median(er):.3f} deg")


def bench_roll(phantom, webcam, rng) -> None:
    print("roll sweep: roll about the box's long axis from -90 to +90 deg in 5 deg steps, tilt 0, at 300 (a patient "
          "at the isocentre), 400, 550, 700 mm")
    tracker = Tracker(phantom, webcam, "joint", smoothing=False, window=False)
    for z in (300.0, 400.0, 550.0, 700.0):
        n, ok, worst_t, worst_r = 0, 0, 0.0, 0.0
        for roll in np.arange(-90.0, 90.1, 5.0):
            T = pose_from_angles([0.0, 0.0, z], roll)
            image, truth = synthetic_camera(phantom, webcam, Trajectory.still(T), seed=int(rng.integers(2**31))).render_at(0.0)
            pose = tracker.track(image, 0.0)
            n += 1
            if pose.ok:
                ok += 1
                et, er = _errors(pose.T_webcam_from_phantom, truth)
                worst_t, worst_r = max(worst_t, et), max(worst_r, er)
        print(f"  {z:.0f} mm: pose found at {ok}/{n} roll angles; worst translation error {worst_t:.3f} mm, "
              f"worst rotation error {worst_r:.3f} deg")


def bench_jitter(phantom, webcam, rng, frames: int) -> None:
    print(f"standstill jitter: {frames} frames at 30 fps of a still phantom (new sensor noise each frame); "
          "RMS distance of the phantom origin from its mean")
    for z, roll, settings in ((550.0, 0.0, None), (700.0, 0.0, None), (700.0, 90.0, None), (700.0, 90.0, HARSH)):
        T = pose_from_angles([15.0, -10.0, z], roll, 8.0, 12.0)
        cam = synthetic_camera(phantom, webcam, Trajectory.still(T), seed=int(rng.integers(2**31)), settings=settings)
        raw_t: list[np.ndarray] = []
        smooth_t: list[np.ndarray] = []
        trackers = {"raw": Tracker(phantom, webcam, "joint", smoothing=False),
                    "smoothed": Tracker(phantom, webcam, "joint", smoothing=True)}
        for k in range(frames):
            image, _ = cam.render_at(k / 30.0)
            for name, tr in trackers.items():
                pose = tr.track(image, k / 30.0)
                if pose.ok and pose.T_webcam_from_phantom is not None:
                    (raw_t if name == "raw" else smooth_t).append(pose.T_webcam_from_phantom[:3, 3])
        # The smoother starts from the first frame; judge it after a second of settling.
        raw, smooth = np.array(raw_t), np.array(smooth_t[30:])
        rms = lambda p: float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))
        print(f"  {z:.0f} mm, roll {roll:.0f} deg{', poor MJPG webcam' if settings else ''}: raw {rms(raw):.4f} mm RMS, "
              f"smoothed {rms(smooth):.4f} mm RMS")


def bench_lag(phantom, webcam, rng) -> None:
    print("smoothing lag: phantom crossing the view at constant speed, 30 fps; lag = along-track error of the "
          "smoothed pose / speed, after 0.5 s")
    for speed in (20.0, 100.0, 300.0):
        v = np.array([speed, 0.3 * speed, 0.0])
        start = pose_from_angles([-60.0, -20.0, 550.0], 10.0, 5.0, 0.0)
        end = make_transform(start[:3, :3], start[:3, 3] + v * 1.5)
        traj = Trajectory.from_poses([0.0, 1.5], [start, end], loop=False)
        cam = synthetic_camera(phantom, webcam, traj, seed=int(rng.integers(2**31)))
        tracker = Tracker(phantom, webcam, "joint", smoothing=True)
        lags, behind = [], []
        vn = float(np.linalg.norm(v))
        for k in range(45):
            t = k / 30.0
            image, truth = cam.render_at(t)
            pose = tracker.track(image, t)
            if pose.ok and pose.T_webcam_from_phantom is not None and t >= 0.5:
                along = -(pose.T_webcam_from_phantom[:3, 3] - truth[:3, 3]) @ v / vn
                behind.append(along)
                lags.append(along / vn)
        print(f"  {vn:.0f} mm/s: lag median {np.median(lags) * 1e3:.1f} ms ({np.median(behind):.2f} mm behind)")


def bench_calibration(phantom, webcam, rng, frames: int) -> None:
    print(f"composite-marker calibration: {frames} random frames (roll +-120, tilt +-50, yaw +-180 deg, 400-700 mm) of a "
          "box whose markers sit up to 8 mm and 10 deg off the drawing; error of every T_phantom_from_marker")
    true = markers_stuck_by_hand(phantom, rng)
    poses = random_poses(rng, frames, roll_deg=(-120, 120), tilt_deg=(-50, 50), yaw_deg=(-180, 180))
    cam = synthetic_camera(phantom, webcam, lambda t: poses[int(t)], seed=int(rng.integers(2**31)),
                           T_phantom_from_marker=true)
    K, dist = webcam.camera_matrix(), webcam.distortion()
    detector = MarkerDetector(phantom.aruco_dictionary, K, dist)
    cal = CompositeCalibration([m.id for m in phantom.markers], phantom.root_marker_id,
                               phantom.marker(phantom.root_marker_id).T(), phantom.marker_size_mm, K, dist)
    connected_at = None
    for k in range(frames):
        image, _ = cam.render_at(k + 0.5)
        cal.add(detector.detect(image))
        if connected_at is None and cal.connected():
            connected_at = k + 1
    t0 = time.perf_counter()
    refined, rms = cal.refine()
    t_refine = time.perf_counter() - t0
    for name, layout in (("graph (paper, Dijkstra)", cal.layout()), ("graph + bundle adjustment", refined)):
        et = [np.linalg.norm(layout[i][:3, 3] - true[i][:3, 3]) for i in layout]
        er = [rotation_angle_deg(layout[i], true[i]) for i in layout]
        print(f"  {name}: {len(layout)}/{len(true)} markers; worst {max(et):.3f} mm, {max(er):.3f} deg; "
              f"median {np.median(et):.3f} mm, {np.median(er):.3f} deg")
    print(f"  graph connected after {connected_at} frames; {cal.frames_used} frames with 2+ markers; "
          f"bundle adjustment {t_refine:.1f} s, corner RMS {rms:.3f} px")


def bench_webcam_calibration(rng, views: int) -> None:
    """Intrinsics measured from rendered ChArUco views against the ones they were rendered with."""
    spec = BoardSpec()
    K_true = np.array([[1010.0, 0.0, 652.0], [0.0, 1006.0, 371.0], [0.0, 0.0, 1.0]])
    dist_true = np.array([-0.12, 0.09, 0.0, 0.0, 0.0])
    textures = [spec.image(ppm).astype(np.float32) / 255.0 for ppm in (2.0, 4.0, 8.0)]
    board = TexturedQuad(np.eye(4), spec.squares_x * spec.square_mm / 2, spec.squares_y * spec.square_mm / 2, textures)
    renderer = SceneRenderer(K_true, dist_true, 1280, 720, None, [board], RenderSettings(background=40.0),
                             seed=int(rng.integers(2**31)))
    detector = BoardDetector(spec)
    found = []
    for _ in range(views):
        R = (R_HOME @ rotation_about((1, 0, 0), np.radians(rng.uniform(-35, 35)))
             @ rotation_about((0, 1, 0), np.radians(rng.uniform(-35, 35)))
             @ rotation_about((0, 0, 1), np.radians(rng.uniform(-20, 20))))
        # Spread over the whole image, corners included, as a careful calibration is done.
        T = make_transform(R, [rng.uniform(-150, 150), rng.uniform(-90, 90), rng.uniform(330, 450)])
        view = detector.detect(renderer.render(T))
        if view:
            found.append(view)
    cal = calibrate_webcam(found, 1280, 720)
    print(f"webcam calibration: {len(found)} ChArUco views ({spec.squares_x}x{spec.squares_y}, {spec.square_mm:g} mm) "
          f"rendered with fx 1010, fy 1006, cx 652, cy 371, k1 -0.12, k2 0.09")
    print(f"  measured fx {cal.K[0, 0]:.2f}, fy {cal.K[1, 1]:.2f}, cx {cal.K[0, 2]:.2f}, cy {cal.K[1, 2]:.2f}, "
          f"k1 {cal.dist[0]:.4f}, k2 {cal.dist[1]:.4f}; RMS reprojection {cal.rms_px:.3f} px")


def bench_speed(phantom, webcam, rng, frames: int) -> None:
    cv2.setNumThreads(1)
    segments = 6
    per = frames // segments
    print(f"speed: detection + pose per 1280x720 frame on one core (cv2.setNumThreads(1)); {segments} stretches of "
          f"{per} frames at 30 fps along the demo path")
    path = load_trajectory(DEMO_TRAJECTORY)
    cam = synthetic_camera(phantom, webcam, path, seed=int(rng.integers(2**31)))
    cam.render_at(0.0)                  # the first frame also draws the sensor's noise pool: not counted
    images, render, render_cpu = [], [], []
    for s in range(segments):
        for k in range(per):
            t = s * path.duration / segments + k / 30.0
            t0, c0 = time.perf_counter(), time.thread_time()
            images.append((t, cam.render_at(t)[0]))
            render.append(time.perf_counter() - t0)
            render_cpu.append(time.thread_time() - c0)
    for method, window in (("joint", True), ("joint", False), ("marker", True)):
        tr = Tracker(phantom, webcam, method, smoothing=True, window=window)
        ts, cpu = [], []
        for t, image in images:
            t0, c0 = time.perf_counter(), time.thread_time()
            tr.track(image, t)
            ts.append(time.perf_counter() - t0)
            cpu.append(time.thread_time() - c0)
        # CPU time of this thread is what one core spends; wall time also counts waiting for a shared core.
        where = (f"search window ({tr.window_searches} windowed, {tr.full_searches} whole-image searches)" if window
                 else "whole image")
        print(f"  {method:6s}, {where}: wall median {np.median(ts) * 1e3:.2f} ms (p95 {np.percentile(ts, 95) * 1e3:.2f}); "
              f"CPU median {np.median(cpu) * 1e3:.2f} ms (p95 {np.percentile(cpu, 95) * 1e3:.2f})")
    print(f"  synthetic camera rendering: wall median {np.median(render) * 1e3:.2f} ms per frame; "
          f"CPU median {np.median(render_cpu) * 1e3:.2f} ms (p95 {np.percentile(render_cpu, 95) * 1e3:.2f})")


def run_bench(args) -> int:
    phantom = load_profile(args.phantom, PhantomProfile)
    webcam = load_profile(args.webcam, WebcamProfile)
    rng = np.random.default_rng(args.seed)
    parts: dict[str, Callable[[], object]] = {
        "accuracy": lambda: (bench_accuracy(phantom, webcam, rng, args.frames),
                             bench_accuracy(phantom, webcam, rng, args.frames, HARSH)),
        "intrinsics": lambda: bench_intrinsics(phantom, webcam, rng, args.frames // 2),
        "roll": lambda: bench_roll(phantom, webcam, rng),
        "jitter": lambda: bench_jitter(phantom, webcam, rng, 120),
        "lag": lambda: bench_lag(phantom, webcam, rng),
        "calibration": lambda: bench_calibration(phantom, webcam, rng, args.calibration_frames),
        "webcam-calibration": lambda: bench_webcam_calibration(rng, 15),
        "speed": lambda: bench_speed(phantom, webcam, rng, 60),
    }
    wanted = list(parts) if args.parts == "all" else [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = [p for p in wanted if p not in parts]
    if unknown:
        raise FluorosimError(f"bench tracking --parts: no part {', '.join(unknown)}; the parts are {', '.join(parts)}")
    print(f"phantom {args.phantom}, webcam {args.webcam} ({webcam.width}x{webcam.height}), seed {args.seed}; "
          f"synthetic frames: {RenderSettings()}")
    for name in wanted:
        parts[name]()
    return 0


def register_bench(benches) -> None:
    b = benches.add_parser("tracking", help="tracking accuracy, jitter, lag, composite calibration and speed",
                           description="Synthetic 1280x720 frames with known poses; prints medians.")
    b.add_argument("--phantom", default=str(CONFIGS / "phantoms" / "box-v1.yaml"), metavar="PHANTOM.yaml")
    b.add_argument("--webcam", default=str(CONFIGS / "webcams" / "generic-720p.yaml"), metavar="WEBCAM.yaml")
    b.add_argument("--frames", type=int, default=100, help="random frames for the accuracy figures")
    b.add_argument("--calibration-frames", type=int, default=200, help="random frames for the composite calibration")
    b.add_argument("--seed", type=int, default=1)
    b.add_argument("--parts", default="all", metavar="PART,...",
                   help="comma-separated parts to run: accuracy, intrinsics, roll, jitter, lag, calibration, "
                        "webcam-calibration, speed (default: all)")
    b.set_defaults(run=run_bench)
