"""`fluorosim track`, `calibrate webcam`, `calibrate phantom`, `print-markers` and `bench tracking`."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from drivers.camera import FileCamera, V4L2Camera, list_images

from ..atomic_file import write_atomic
from ..cli import command_group
from ..command_options import add_command
from ..config.loading import load_profile
from ..config.phantom import PhantomProfile
from ..config.webcam import WebcamProfile
from ..errors import FluorosimError
from .composite import CompositeCalibration
from .markers import MarkerDetector, aruco_dictionary
from .profile_update import write_phantom_layout, write_webcam_intrinsics
from .tracker import METHODS, Tracker
from .webcam_calibration import BoardDetector, BoardSpec, calibrate_webcam

#: Live webcam calibration keeps at most one board view per this many seconds.
LIVE_VIEW_SPACING_S = 0.5
#: A live camera that delivers nothing for this long (s) ends a calibration with an error.
FIRST_FRAME_TIMEOUT_S = 5.0


def _read_image(path: str) -> np.ndarray:
    p = Path(path)
    if not p.is_file():
        raise FluorosimError(f"{path}: no such image file")
    image = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if image is None:
        raise FluorosimError(f"{path}: cannot be read as an image (PNG, JPEG, BMP, TIFF, PGM/PPM)")
    return image


def run_track(args) -> int:
    phantom = load_profile(args.phantom, PhantomProfile)
    webcam = load_profile(args.webcam, WebcamProfile)
    for path in args.images:
        if not Path(path).is_file():
            raise FluorosimError(f"{path}: no such image file")
    # Each image on its own: no smoothing, and no search window carried over from the previous one.
    tracker = Tracker(phantom, webcam, method=args.method, smoothing=False, window=False)
    for path in args.images:
        pose = tracker.track(_read_image(path), time.monotonic())
        T = pose.T_webcam_from_phantom
        if args.json:
            print(json.dumps({"image": path, "ok": pose.ok,
                              "T_webcam_from_phantom": None if T is None else np.round(T, 6).tolist(),
                              "markers": pose.markers}), flush=True)
        elif pose.ok and T is not None:
            print(f"{path}: phantom at {np.round(T[:3, 3], 2).tolist()} mm ({pose.method}, markers {pose.markers}, "
                  f"RMS {pose.rms_px:.2f} px)")
        else:
            print(f"{path}: phantom not found (markers seen: {pose.markers or 'none'})")
    return 0


def _live_frames(device: str, width: int, height: int, fps: float, seconds: float):
    """Frames from a V4L2 device for `seconds` (s), or FluorosimError if none arrive."""
    cam = V4L2Camera(device, width, height, fps)
    cam.start()
    try:
        wait_first_s = min(FIRST_FRAME_TIMEOUT_S, seconds)
        seq, deadline, first = -1, time.monotonic() + seconds, time.monotonic() + wait_first_s
        while time.monotonic() < deadline and (seq >= 0 or time.monotonic() < first):
            frame = cam.wait(seq, 0.1)
            if frame is not None:
                seq = frame.seq
                yield f"{device}#{frame.seq}", frame.image
        if seq < 0:
            why = cam.message.split(";")[0] if cam.message else f"camera {device}: no frames"
            raise FluorosimError(f"{why}; nothing captured in {wait_first_s:g} s (check the device path, the cable "
                                 "and that no other program holds the camera)")
    finally:
        cam.stop()


def _frames(args):
    if args.device:
        yield from _live_frames(args.device, args.width, args.height, args.fps, args.seconds)
        return
    src = Path(args.images)
    if not src.exists():
        raise FluorosimError(f"{src}: no such image folder or video file")
    if src.is_dir() and not list_images(src):
        raise FluorosimError(f"{src}: holds no images (.png, .jpg, ...)")
    yield from FileCamera(src).frames()


def _board(args) -> BoardSpec:
    try:
        sx, sy = (int(v) for v in args.squares.lower().split("x"))
    except ValueError:
        raise FluorosimError(f"--squares {args.squares}: write it as COLUMNSxROWS, e.g. 7x5") from None
    return BoardSpec(sx, sy, args.square_mm, args.marker_mm, args.dictionary)


def run_calibrate_webcam(args) -> int:
    load_profile(args.webcam, WebcamProfile)        # refuse to start on a profile we could not write back
    detector = BoardDetector(_board(args))
    views: list[tuple[np.ndarray, np.ndarray]] = []
    size, n, last_kept = None, 0, 0.0
    for name, image in _frames(args):
        n += 1
        if image is None:
            print(f"{name}: unreadable, skipped", file=sys.stderr)
            continue
        h, w = image.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise FluorosimError(f"{name}: is {w}x{h} but earlier images are {size[0]}x{size[1]}; "
                                 "calibrate from one resolution")
        if args.device and views and time.monotonic() - last_kept < LIVE_VIEW_SPACING_S:
            continue                 # live: consecutive frames are nearly the same view
        found = detector.detect(image)
        print(f"{name}: {'board corners ' + str(len(found[0])) if found else 'board not found'}", file=sys.stderr)
        if found:
            views.append(found)
            last_kept = time.monotonic()
            if len(views) >= args.max_views:
                break
    if size is None:
        raise FluorosimError("no frames to calibrate from")
    cal = calibrate_webcam(views, *size)
    write_webcam_intrinsics(args.webcam, cal.K, cal.dist, cal.rms_px, cal.width, cal.height)
    print(f"{args.webcam}: calibrated from {cal.views} of {n} views, RMS reprojection {cal.rms_px:.3f} px "
          f"(fx {cal.K[0, 0]:.1f}, fy {cal.K[1, 1]:.1f}, cx {cal.K[0, 2]:.1f}, cy {cal.K[1, 2]:.1f}); "
          f"previous profile kept as {Path(args.webcam).name}.bak")
    return 0


def run_calibrate_phantom(args) -> int:
    phantom = load_profile(args.phantom, PhantomProfile)
    webcam = load_profile(args.webcam, WebcamProfile)
    K, dist = webcam.camera_matrix(), webcam.distortion()
    detector = MarkerDetector(phantom.aruco_dictionary, K, dist)
    ids = [m.id for m in phantom.markers]
    cal = CompositeCalibration(ids, phantom.root_marker_id, phantom.marker(phantom.root_marker_id).T(),
                               phantom.marker_size_mm, K, dist)
    n, shown = 0, None
    for name, image in _frames(args):
        n += 1
        if image is None:
            print(f"{name}: unreadable, skipped", file=sys.stderr)
            continue
        cal.add(detector.detect(image))
        missing = cal.missing()
        progress = (len(cal.seen), tuple(missing))
        if progress != shown or n % 30 == 0:       # a line when something changes, not 30 a second
            print(f"frame {n}: markers seen {len(cal.seen)}/{len(ids)}, connected to the root: "
                  f"{'yes' if not missing else 'no (missing ' + ', '.join(map(str, missing)) + ')'}", file=sys.stderr)
            shown = progress
        if args.device and not missing and cal.frames_used >= args.min_frames:
            break
    missing = cal.missing()
    if missing:
        raise FluorosimError(f"markers {missing} were never seen together with a marker connected to root marker "
                             f"{phantom.root_marker_id}; show each of them beside a neighbour and run again")
    layout, rms = cal.refine()
    write_phantom_layout(args.phantom, layout)
    print(f"{args.phantom}: {len(layout)} markers calibrated from {cal.frames_used} frames, corner RMS {rms:.3f} px; "
          f"previous profile kept as {Path(args.phantom).name}.bak")
    return 0


def _page(image: np.ndarray, label: str, dpi: int, margin_mm: float = 10.0) -> np.ndarray:
    """The print centred on a white page with `margin_mm` around it and a label underneath."""
    m = int(round(margin_mm / 25.4 * dpi))
    text_h = int(round(6 / 25.4 * dpi))
    page = cv2.copyMakeBorder(image, m, m + text_h, m, m, cv2.BORDER_CONSTANT, value=255)
    scale = max(0.3, text_h / 40)
    cv2.putText(page, label, (m, page.shape[0] - m // 2 - text_h // 3), cv2.FONT_HERSHEY_SIMPLEX, scale, 0,
                max(1, int(scale * 2)), cv2.LINE_AA)
    return page


def _write_png(path: Path, image: np.ndarray, dpi: int) -> None:
    import io

    from PIL import Image
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG", dpi=(dpi, dpi))
    write_atomic(path, buf.getvalue())


def _write_pdf(path: Path, pages: list[np.ndarray], dpi: int) -> None:
    import io

    from PIL import Image
    images = [Image.fromarray(p).convert("L") for p in pages]
    buf = io.BytesIO()
    images[0].save(buf, format="PDF", resolution=float(dpi), save_all=True, append_images=images[1:])
    write_atomic(path, buf.getvalue())


def marker_print(dictionary: str, marker_id: int, size_mm: float, dpi: int) -> np.ndarray:
    """The black square of one marker at `dpi`, exactly `size_mm` wide (to the nearest pixel), uint8."""
    side = int(round(size_mm / 25.4 * dpi))
    return cv2.aruco.generateImageMarker(aruco_dictionary(dictionary), marker_id, side, borderBits=1)


def run_print_markers(args) -> int:
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FluorosimError(f"{out}: cannot create the output folder ({e.strerror})") from None
    if not 72 <= args.dpi <= 2400:
        raise FluorosimError(f"--dpi {args.dpi}: use a printer resolution between 72 and 2400")
    written = []
    if args.phantom:
        phantom = load_profile(args.phantom, PhantomProfile)
        pages = []
        for m in phantom.markers:
            img = marker_print(phantom.aruco_dictionary, m.id, phantom.marker_size_mm, args.dpi)
            path = out / f"marker-{m.id}.png"
            _write_png(path, img, args.dpi)
            written.append(path)
            pages.append(_page(img, f"{phantom.name}: marker {m.id}, {phantom.marker_size_mm:g} mm, "
                                    f"{phantom.aruco_dictionary}", args.dpi))
        pdf = out / "phantom-markers.pdf"
        _write_pdf(pdf, pages, args.dpi)
        written.append(pdf)
    spec = _board(args)
    board = spec.image(args.dpi / 25.4)
    _write_png(out / "charuco-board.png", board, args.dpi)
    _write_pdf(out / "charuco-board.pdf", [_page(board, f"ChArUco {spec.squares_x}x{spec.squares_y}, squares "
                                                        f"{spec.square_mm:g} mm, markers {spec.marker_mm:g} mm, "
                                                        f"{spec.dictionary}", args.dpi)], args.dpi)
    written += [out / "charuco-board.png", out / "charuco-board.pdf"]
    print(f"wrote {len(written)} files to {out} at {args.dpi} dpi; print at 100 % (no 'fit to page') and check "
          "a marker with a ruler")
    return 0


def _add_board_options(p) -> None:
    d = BoardSpec()
    p.add_argument("--squares", default=f"{d.squares_x}x{d.squares_y}", help="ChArUco squares, COLUMNSxROWS (default %(default)s)")
    p.add_argument("--square-mm", type=float, default=d.square_mm, help="printed square side (mm, default %(default)s)")
    p.add_argument("--marker-mm", type=float, default=d.marker_mm, help="printed marker side (mm, default %(default)s)")
    p.add_argument("--dictionary", default=d.dictionary, help="board's ArUco dictionary (default %(default)s)")


def _add_source_options(p) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", metavar="FOLDER_OR_VIDEO", help="a folder of images or a video file")
    src.add_argument("--device", metavar="DEV", help="a live V4L2 camera, e.g. /dev/fluorosim/camera")
    p.add_argument("--width", type=int, default=1280, help="live capture width (pixels)")
    p.add_argument("--height", type=int, default=720, help="live capture height (pixels)")
    p.add_argument("--fps", type=float, default=30.0, help="live capture rate (1/s)")
    p.add_argument("--seconds", type=float, default=60.0, help="longest live capture (s)")


def register(commands, benches) -> None:
    p = commands.add_parser("track", help="find the phantom's pose in images",
                            description="Track the box phantom in each IMAGE with the phantom's calibrated marker "
                                        "layout and the webcam's intrinsics.")
    p.add_argument("--phantom", required=True, metavar="PHANTOM.yaml")
    p.add_argument("--webcam", required=True, metavar="WEBCAM.yaml")
    p.add_argument("--method", choices=METHODS, default="auto",
                   help="joint PnP over every marker (auto), or the single most head-on marker (marker)")
    p.add_argument("--json", action="store_true", help="one JSON object per image and line")
    p.add_argument("images", nargs="+", metavar="IMAGE")
    p.set_defaults(run=run_track)

    calibrate = command_group(commands, "calibrate", "calibrate the webcam, the phantom or the X-ray machine")
    w = add_command(calibrate, "webcam", run_calibrate_webcam, "webcam intrinsics from a ChArUco board",
                    "Measure the webcam's intrinsics and distortion from views of a printed ChArUco board (fluorosim "
                    "print-markers) and write them into WEBCAM.yaml atomically, keeping the previous version as .bak.")
    w.add_argument("--webcam", required=True, metavar="WEBCAM.yaml", help="webcam profile to update")
    _add_source_options(w)
    _add_board_options(w)
    w.add_argument("--max-views", type=int, default=40, help="stop after this many board views (default %(default)s)")

    ph = add_command(calibrate, "phantom", run_calibrate_phantom, "where each marker sits on the box (composite marker)",
                     "Turn the box in front of the webcam until every marker has been seen beside a neighbour; the "
                     "marker layout relative to the root marker is written into PHANTOM.yaml atomically, keeping the "
                     "previous version as .bak.")
    ph.add_argument("--phantom", required=True, metavar="PHANTOM.yaml")
    ph.add_argument("--webcam", required=True, metavar="WEBCAM.yaml")
    ph.add_argument("--min-frames", type=int, default=100,
                    help="live: keep collecting until this many frames with two or more markers (default %(default)s)")
    _add_source_options(ph)

    pm = commands.add_parser("print-markers", help="write the phantom's markers and the ChArUco board to print",
                             description="Write each marker of PHANTOM.yaml and the ChArUco board as PNG (with the "
                                         "DPI recorded) and PDF, at exact physical size for the given DPI.")
    pm.add_argument("--phantom", metavar="PHANTOM.yaml", help="phantom whose markers to print")
    pm.add_argument("--out", required=True, metavar="FOLDER")
    pm.add_argument("--dpi", type=int, default=300, help="printer resolution (dots per inch, default %(default)s)")
    _add_board_options(pm)
    pm.set_defaults(run=run_print_markers)

    from .bench import register_bench
    register_bench(benches)
