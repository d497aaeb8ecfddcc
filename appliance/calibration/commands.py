"""`fluorosim calibrate xray`, `fluorosim print-calibration-phantom` and `fluorosim bench calibration`."""

from __future__ import annotations

import sys
from pathlib import Path

from ..cli import command_group
from ..command_options import add_command
from ..config.calibration_phantom import CalibrationPhantomProfile, MarkerPose
from ..config.commands import default_config_dir
from ..config.fluoroscope import FluoroscopeProfile
from ..config.loading import load_profile
from ..errors import FluorosimError

DEFAULT_PHANTOM = Path("calibration-phantoms") / "two-plane-36.yaml"
DEFAULT_FLUOROSCOPE = Path("fluoroscopes") / "generic-ii-carm.yaml"


def run_calibrate_xray(args) -> int:
    from .profile_update import write_profile
    from .xray_calibration import calibrate, read_image, report

    phantom_path = Path(args.phantom_model) if args.phantom_model else default_config_dir() / DEFAULT_PHANTOM
    phantom = load_profile(phantom_path, CalibrationPhantomProfile)
    fluoroscope = load_profile(args.fluoroscope, FluoroscopeProfile)
    if args.marker_pose and len(args.marker_pose) != len(args.images):
        raise FluorosimError(f"{len(args.marker_pose)} --marker-pose file(s) for {len(args.images)} image(s); "
                             "give one per image, in the same order, or none")
    marker_poses = [load_profile(p, MarkerPose).T() for p in args.marker_pose] if args.marker_pose else None
    images = [(str(p), read_image(p)) for p in args.images]
    result = calibrate(images, phantom, fluoroscope, marker_poses)
    for outcome in result.images:
        if outcome.reason:
            print(f"rejected {outcome.reason}", file=sys.stderr)
    print(report(result))
    if not result.passed or result.fit is None:     # passed implies a fit; said again for the type
        print(f"{args.fluoroscope}: left unchanged", file=sys.stderr)
        return 2
    if args.dry_run:
        print(f"{args.fluoroscope}: left unchanged (--dry-run)")
        return 0
    write_profile(args.fluoroscope, result.fit, result.webcam.T if result.webcam is not None else None)
    print(f"{args.fluoroscope}: calibrated intrinsics{' and T_xray_from_webcam' if result.webcam is not None else ''} "
          f"written (previous version kept as {Path(args.fluoroscope).name}.bak)")
    return 0


def run_print_phantom(args) -> int:
    from .drawing import write_drawing

    phantom_path = Path(args.phantom_model) if args.phantom_model else default_config_dir() / DEFAULT_PHANTOM
    phantom = load_profile(phantom_path, CalibrationPhantomProfile)
    written = write_drawing(phantom, Path(args.out))
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def run_bench(args) -> int:
    from .bench import run_benchmark

    return run_benchmark(args)


def register(commands, benches) -> None:
    calibrate = command_group(commands, "calibrate", "calibrate the webcam, the phantom or the X-ray machine")
    x = calibrate.add_parser(
        "xray", help="intrinsics, distortion and T_xray_from_webcam from images of the sphere phantom",
        description="Find the sphere phantom in each X-ray IMAGE (PNG/TIFF frame grabs or .npy arrays), fit the "
                    "machine's fx, fy, cx, cy and distortion (k1 k2 p1 p2 k3) to all of them, and with one "
                    "--marker-pose per image also T_xray_from_webcam. Prints a report; when the fit passes the "
                    "phantom profile's acceptance bar the fluoroscope profile is rewritten atomically, the old one "
                    "kept as PROFILE.yaml.bak. Exit 0 when written, 2 when refused.")
    x.add_argument("images", nargs="+", metavar="IMAGE")
    x.add_argument("--phantom-model", metavar="MODEL.yaml",
                   help=f"sphere phantom profile (default: configs/{DEFAULT_PHANTOM}); to fix the principal point to a "
                        "pixel use configs/calibration-phantoms/two-plane-grid-332.yaml, whose balls fill the field, "
                        "with about 30 images")
    x.add_argument("--fluoroscope", required=True, metavar="PROFILE.yaml",
                   help="fluoroscope profile: its current intrinsics start the fit, and the result is written into it")
    x.add_argument("--marker-pose", action="append", metavar="POSE.yaml",
                   help="T_webcam_from_marker seen by the webcam when the image was taken; once per IMAGE, in order")
    x.add_argument("--dry-run", action="store_true", help="report only; never write the profile")
    x.set_defaults(run=run_calibrate_xray)

    p = add_command(commands, "print-calibration-phantom", run_print_phantom, "workshop drawing of the sphere phantom (PDF, PNG, CSV)",
                    "Draw the sphere phantom with every ball's position, diameter and line, the "
                    "plates and the marker, dimensioned in mm at 1:1 on A4, as OUT.pdf (the plan, "
                    "then the ball table), OUT.png (the first page) and OUT.csv (the ball table, "
                    "for a CNC drill). A plate too large for one A4 page gets an overview page "
                    "that says its scale, then the plan at 1:1 in overlapping tiles.")
    p.add_argument("out", metavar="OUT", help="output path; .pdf, .png and .csv are written beside each other")
    p.add_argument("--phantom-model", metavar="MODEL.yaml", help=f"sphere phantom profile (default: configs/{DEFAULT_PHANTOM})")

    b = add_command(benches, "calibration", run_bench, "accuracy and speed of X-ray calibration at known geometry",
                    "Make images of the sphere phantom at known poses with a known machine, "
                    "calibrate from them, and print the errors of fx, fy, principal point, "
                    "distortion, reprojection and T_xray_from_webcam, with median stage timings.")
    b.add_argument("--images", type=int, default=8, help="images per calibration (default 8)")
    b.add_argument("--runs", type=int, default=10, help="independent calibrations, each with its own noise seed (default 10)")
    b.add_argument("--seed", type=int, default=1)
    b.add_argument("--source", choices=("shadowgraph", "renderer", "both"), default="both",
                   help="who makes the images: the analytic shadowgraph, the project's DRR renderer, or both")
    b.add_argument("--fluoroscope", metavar="PROFILE.yaml", help=f"nominal profile (default: configs/{DEFAULT_FLUOROSCOPE})")
    b.add_argument("--phantom-model", metavar="MODEL.yaml",
                   help=f"sphere phantom profile (default: configs/{DEFAULT_PHANTOM}); "
                        "configs/calibration-phantoms/two-plane-grid-332.yaml fills the field")
    b.add_argument("--jobs", type=int, default=1, metavar="N",
                   help="runs made at once in N processes (default 1); each run keeps its own seed")
    b.add_argument("--max-tilt", type=float, default=12.0, metavar="DEG",
                   help="largest phantom tilt of the drawn poses (degrees, default 12)")
