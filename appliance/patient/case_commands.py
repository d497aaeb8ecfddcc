"""`fluorosim case inspect` and `fluorosim case place`: what a CT holds, and a case profile
that puts a chosen point of it at the X-ray isocentre."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from ..atomic_file import write_atomic
from ..cli import command_group
from ..command_options import add_command
from ..config.commands import default_config_dir
from ..config.loading import load_appliance
from ..errors import FluorosimError

DEFAULT_APPLIANCE = "appliance-demo.yaml"


def parse_point(text: str, option: str) -> np.ndarray:
    """Three comma-separated numbers (mm), or a one-line error naming the option."""
    parts = [p for p in text.replace(" ", "").split(",")]
    try:
        values = np.array([float(p) for p in parts])
    except ValueError:
        values = np.array([])
    if values.shape != (3,) or not np.all(np.isfinite(values)):
        raise FluorosimError(f"{option} {text!r}: give three numbers in LPS mm, e.g. {option}=12.5,-30,140")
    return values


def run_inspect(args) -> int:
    from .inspection import report
    from .volume_io import load_volume

    volume = load_volume(args.ct, hu_checked=False)   # inspect says what the values look like
    at = parse_point(args.at, "--at") if args.at else None
    print("\n".join(report(volume, at)))
    return 0


def _beam_at_home(appliance_path: Path):
    from ..tracking.trajectory import load_trajectory
    from .placement import beam_geometry

    config = load_appliance(appliance_path)
    written = config.appliance.devices.camera.trajectory
    if not written:
        raise FluorosimError(f"{appliance_path}: names no devices.camera.trajectory, so there is no home pose to place "
                             f"the patient at; give --appliance configs/{DEFAULT_APPLIANCE}")
    home = load_trajectory(config.resolve(written))(0.0)
    return config, beam_geometry(config.fluoroscope, home)


CASE_TEMPLATE = """\
# Made by `fluorosim case place` from {ct_name}: the target {target} (LPS mm){named} sits at the
# X-ray isocentre of {appliance_name} at its demo path's home pose, seen {beam}.
# Check the preview before a demo; move the patient by editing the last column (mm).
title: {title}
description: {description}
phases:
  - volume: {volume}
    time_s: 0
at_end: hold
# Maps the CT's LPS coordinates (mm) into the box phantom's frame (mm).
T_phantom_from_ct:
{matrix}
materials:
  air_max_hu: -800
  bone_min_hu: 300
  bone_density_at_1000_hu_g_per_cm3: 1.6
"""


def _yaml_string(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _target(args, volume) -> tuple[np.ndarray, str]:
    """--target as a point (LPS mm), and what names it (' (the centroid of ...)' or '')."""
    if args.label_names and not args.labels:
        raise FluorosimError("--label-names: names the labels of a label map; give the map with --labels FILE")
    numeric = all(_is_number(p) for p in args.target.split(",")) and args.target.count(",") == 2
    if numeric:
        return parse_point(args.target, "--target"), ""
    if not args.labels:
        raise FluorosimError(f"--target {args.target!r}: give three numbers in LPS mm (--target=12.5,-30,140), or a "
                             f"label's name together with the label map (--labels FILE)")
    from .label_points import label_points

    points = label_points(Path(args.labels), volume, Path(args.label_names) if args.label_names else None)
    centroid, count = points.centroid(args.target)
    return np.round(centroid, 2), f" (the centroid of label {args.target!r}, {count} voxels of {Path(points.source).name})"


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def run_place(args) -> int:
    from .placement import coverage, place
    from .placement_preview import draw_preview, write_preview
    from .volume_io import load_volume

    ct = Path(args.ct)
    appliance_path = Path(args.appliance) if args.appliance else default_config_dir() / DEFAULT_APPLIANCE
    volume = load_volume(ct)
    target, named = _target(args, volume)
    config, geometry = _beam_at_home(appliance_path)
    from .inspection import value_at

    _, hu = value_at(volume, target)
    if hu is None:
        raise FluorosimError(f"--target {args.target}: outside {ct}; "
                             f"`fluorosim case inspect {ct}` prints the volume's LPS bounds")
    T = place(target, args.beam, geometry)
    out = Path(args.out) if args.out else None
    if out is not None:
        folder = out.parent if str(out.parent) else Path(".")
        if not folder.is_dir():
            raise FluorosimError(f"{out}: folder {folder} does not exist; create it or choose another --out")
        volume_ref = os.path.relpath(ct.resolve(), folder.resolve())
    else:
        volume_ref = str(ct.resolve())
    rows = "\n".join("  - [" + ", ".join(f"{v:.6g}" if abs(v) > 1e-12 else "0" for v in row) + "]" for row in T)
    text = CASE_TEMPLATE.format(
        ct_name=ct.name, target=", ".join(f"{v:g}" for v in target), named=named, appliance_name=appliance_path.name, beam=args.beam,
        title=_yaml_string(args.title or ct.name), volume=_yaml_string(volume_ref), matrix=rows,
        description=_yaml_string(f"Own CT {ct.name}, {args.beam} beam, target ({', '.join(f'{v:g}' for v in target)}) mm"
                                 + named))
    if out is None:
        print(text, end="")
    else:
        try:
            write_atomic(out, text.encode("utf-8"), backup=out.exists())
        except OSError as e:
            raise FluorosimError(f"{out}: cannot write ({e.strerror or e}); check the folder's permissions") from None
        print(f"{out}: case profile written; target{named} at LPS ({', '.join(f'{v:g}' for v in target)}) mm, "
              f"{hu} HU, at the isocentre, phantom "
              f"({', '.join(f'{v:.1f}' for v in geometry.isocentre)}) mm, {args.beam} beam")
    short = coverage(volume, T, geometry).short_mm
    names = {"head+": "toward the head", "head-": "toward the feet", "across+": "to one side", "across-": "to the other side"}
    gaps = [f"{v:.0f} mm {names[k]}" for k, v in short.items() if v > 0.5]
    if gaps:
        print(f"note: at the isocentre the {2 * geometry.field_radius_mm:.0f} mm field runs past the CT's end by "
              + ", ".join(gaps) + "; those parts of the image will show air")
    preview = Path(args.preview) if args.preview else (out.with_name(out.stem + "-preview.png") if out else None)
    if preview is not None:
        write_preview(preview, draw_preview(volume, T, geometry, (config.phantom.box.length_mm, config.phantom.box.width_mm,
                                                                   config.phantom.box.height_mm), target))
        print(f"{preview}: preview (AP and lateral, field and box outlined)")
    return 0


def register(commands, benches) -> None:
    case = command_group(commands, "case", "inspect your own CT and place it in the box phantom")
    def ct_argument(p: argparse.ArgumentParser) -> None:
        p.add_argument("ct", metavar="CT", help="DICOM series folder, .nii/.nii.gz, .mha/.mhd or .nrrd")

    i = add_command(case, "inspect", run_inspect, "extent, spacing, orientation, centre (LPS mm) and HU of a CT",
                    "Print a CT's grid, spacing and orientation; the LPS bounds (mm) of its first and last voxel "
                    "centres along each axis and its centre; its HU range, histogram peaks and whether it looks like "
                    "a CT in HU; and with --at the value at a point. LPS: +x toward the patient's left, +y posterior, "
                    "+z superior, as ITK reads every format.", ct_argument)
    i.add_argument("--at", metavar="X,Y,Z",
                   help="also print the HU at this point (LPS mm; write --at=-12,5,30 when it starts with a minus)")
    p = add_command(case, "place", run_place, "write a case profile that puts a point of a CT at the X-ray isocentre",
                    "Compute T_phantom_from_ct so that TARGET (LPS mm, see `case inspect`) lies at the X-ray isocentre "
                    "of the appliance's fluoroscope at its demo path's home pose, with the patient's head along the "
                    "box and the beam entering PA (supine), AP (prone) or LAT (left side toward the detector). Writes "
                    "the case profile and a preview PNG.", ct_argument)
    p.add_argument("--target", required=True, metavar="X,Y,Z|NAME",
                   help="the point to centre, in the CT's LPS mm (write --target=-12,5,30 when it starts with a minus), "
                        "or with --labels the name of a label, whose centroid is centred")
    p.add_argument("--labels", metavar="FILE",
                   help="label map on the CT's grid (NIfTI, MHA, NRRD, or a folder of DICOM images), or a "
                        "case profile whose respiration.label_map and respiration.labels name it (the roles lungs, "
                        "liver, spine, ribs, diaphragm); every id N "
                        "is also called label-N")
    p.add_argument("--label-names", metavar="TABLE",
                   help="names of the label map's ids: one `ID NAME` a line (a 3D Slicer colour table) or an ITK-SNAP "
                        "label description (the name quoted last)")
    p.add_argument("--beam", default="PA", choices=("PA", "AP", "LAT"), help="how the beam sees the patient (default PA)")
    p.add_argument("--out", metavar="CASE.yaml", help="write the case profile here (default: print it)")
    p.add_argument("--preview", metavar="PNG", help="preview picture (default: CASE-preview.png beside --out)")
    p.add_argument("--title", help="the case's title (default: the CT's file name)")
    p.add_argument("--appliance", metavar="PROFILE.yaml",
                   help=f"appliance profile whose fluoroscope, phantom and demo path set the isocentre "
                        f"(default: configs/{DEFAULT_APPLIANCE})")
