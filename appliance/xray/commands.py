"""`fluorosim render` and `fluorosim bench drr`."""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
from pydantic import Field

from ..atomic_file import write_atomic
from ..command_options import add_command
from ..config.base import RigidTransform, Section, matrix
from ..config.case import CaseProfile, Materials
from ..config.fluoroscope import FluoroscopeProfile
from ..config.loading import load_profile, resolve
from ..errors import FluorosimError


class PoseFile(Section):
    """A pose for `fluorosim render`."""

    T_xray_from_ct: RigidTransform = Field(description="Maps the volume's physical (header) coordinates into the xray frame (4x4, mm).")


def _volume_and_case(path: Path, phase_time_s: float | None, respiration: str | None = None):
    """The volume to render and the case's materials/contrast (defaults for a bare volume)."""
    from ..patient.breathing_case import breathing_ct, parse_overrides, respiration_for
    from ..patient.volume_io import load_volume

    overrides = parse_overrides(respiration)
    if path.suffix.lower() in (".yaml", ".yml"):
        case = load_profile(path, CaseProfile)
        breathing = respiration_for(case, overrides, str(path))
        if case.phases is None:
            raise FluorosimError(f"{path}: built-in patients are rendered by the appliance; "
                                 "give a case with `phases` or a volume file")
        if breathing is not None and len(case.phases) == 1:
            # One CT breathing under the model: the CT is end-expiration, moved to time T.
            ct = load_volume(resolve(path, case.phases[0].volume))
            return (breathing_ct(path, breathing, ct, case.materials, phase_time_s or 0.0),
                    case.materials, case.contrast)
        times = [p.time_s for p in case.phases]
        t = 0.0 if phase_time_s is None else phase_time_s
        period = times[-1] + (times[-1] - times[0]) / (len(times) - 1) - times[0] if len(times) > 1 else 0.0
        if breathing is not None:
            # A 4D CT: the breathing model's rate picks the time in the CT's own breath.
            if breathing.ct_end_expiration_s is None:
                raise FluorosimError(f"{path}: respiration.ct_end_expiration_s: is required for a 4D CT")
            t = breathing.ct_end_expiration_s + period * ((breathing.rate_per_min / 60.0 * t - 0.75) % 1.0)
        if case.at_end == "loop" and len(times) > 1:
            t = times[0] + (t - times[0]) % period
        i = max([k for k, tk in enumerate(times) if tk <= t] or [0])
        return load_volume(resolve(path, case.phases[i].volume)), case.materials, case.contrast
    if overrides:
        raise FluorosimError("--respiration needs --volume to be a case profile (.yaml)")
    if phase_time_s is not None:
        raise FluorosimError("--phase-time needs --volume to be a case profile (.yaml) listing phases")
    return load_volume(path), Materials(), None


def _encode(image: np.ndarray, suffix: str, quantity: str) -> tuple[bytes, str]:
    if suffix == ".npy":
        buf = io.BytesIO()
        np.save(buf, image.astype(np.float32))
        return buf.getvalue(), ""
    import cv2

    if quantity == "line-integral":
        top = float(image.max()) or 1.0
        ok, data = cv2.imencode(".png", np.rint(image / top * 65535).astype(np.uint16))
        note = f" (16-bit PNG, white = {top:.4g})"
    else:
        ok, data = cv2.imencode(".png", np.rint(np.clip(image, 0, 1) * 255).astype(np.uint8))
        note = ""
    if not ok:
        raise FluorosimError("cannot encode the image as PNG")
    return data.tobytes(), note


def parse_size(text: str) -> tuple[int, int]:
    """`--size 512` (square, or the detector's aspect kept by the caller) or `--size 640x480` (columns x rows)."""
    import argparse

    parts = text.lower().split("x")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (1, 2) or not all(16 <= v <= 8192 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: give PX or COLUMNSxROWS, each 16 to 8192 pixels")
    return (values[0], values[0]) if len(values) == 1 else (values[0], values[1])


def run_render(args) -> int:
    from ..xray.renderer import Renderer, View, at_resolution

    out = Path(args.output)
    suffix = out.suffix.lower()
    if suffix not in (".npy", ".png"):
        raise FluorosimError(f"{out}: output must end in .npy or .png")
    if not (out.parent if str(out.parent) else Path(".")).is_dir():
        raise FluorosimError(f"{out}: folder {out.parent} does not exist; create it or choose another output")
    fluoroscope = load_profile(args.fluoroscope, FluoroscopeProfile)
    if args.size is not None:
        fluoroscope = at_resolution(fluoroscope, *args.size)
    pose = load_profile(args.pose, PoseFile)
    started = time.perf_counter()

    def progress(what: str) -> None:
        print(f"[{time.perf_counter() - started:6.1f} s] {what}", flush=True)
    progress(f"loading {args.volume}")
    volume, materials, contrast = _volume_and_case(Path(args.volume), args.phase_time, args.respiration)
    renderer = Renderer(fluoroscope, materials, contrast, device=args.device)
    nx, ny, nz = volume.shape_xyz
    progress(f"preparing {nx} x {ny} x {nz} voxels for {renderer.device.name.strip()}")
    prepared = renderer.prepare(volume)
    progress(f"casting {fluoroscope.detector.columns} x {fluoroscope.detector.rows} rays")
    view = View(zoom=args.zoom, quantity=args.quantity, noise=fluoroscope.display.noise and not args.no_noise,
                invert=fluoroscope.display.invert, seed=args.seed, polychromatic=not args.mono)
    image = renderer.render(prepared, matrix(pose.T_xray_from_ct), view).image
    data, note = _encode(image, suffix, args.quantity)
    try:
        write_atomic(out, data)
    except OSError as e:
        raise FluorosimError(f"{out}: cannot write ({e.strerror or e}); check the folder's permissions and free space") from None
    s = renderer.spectrum
    print(f"{out}: {args.quantity} {image.shape[1]}x{image.shape[0]} zoom {args.zoom}{note}; "
          f"{s.kvp:g} kVp, {s.filtration_mm_al:g} mm Al, effective energy {s.effective_kev:.2f} keV, "
          f"mu_water = {renderer.mu_water_per_mm:.6f} /mm; device {renderer.device.name.strip()}")
    return 0


def run_bench(args) -> int:
    from .bench import run

    return run(args)


def register(commands, benches) -> None:
    p = commands.add_parser(
        "render", help="render one X-ray image of a CT",
        description="Render the image the fluoroscope would show of a CT volume at a pose. The pose file holds "
                    "T_xray_from_ct, a 4x4 rigid transform (mm) from the CT's LPS coordinates (+x the patient's left, "
                    "+y posterior, +z superior, as `fluorosim case inspect` prints them) into the xray frame: the focal "
                    "spot at the origin, +z along the principal ray toward the detector, +x along increasing detector "
                    "columns, +y along increasing rows (OpenCV's camera convention). A point at xray (0, 0, "
                    "source_to_isocentre_mm) is the isocentre and images at the principal point (cx, cy).")
    p.add_argument("--volume", required=True, metavar="PATH",
                   help="DICOM series folder, .nii/.nii.gz, .mha/.mhd or .nrrd; or a case profile (.yaml) with phases")
    p.add_argument("--fluoroscope", required=True, metavar="PROFILE.yaml")
    p.add_argument("--pose", required=True, metavar="POSE.yaml",
                   help="YAML with T_xray_from_ct: a 4x4 rigid transform (mm) from the CT's LPS frame into the xray frame "
                        "(described above)")
    p.add_argument("--quantity", required=True, choices=("line-integral", "intensity", "display"),
                   help="display: what the monitor shows once the C-arm has been still for a second (exposure "
                        "control, detector, settled recursive filter, log display); intensity: the detector signal "
                        "relative to the open beam; line-integral: exact water-equivalent line integrals")
    p.add_argument("--output", required=True, metavar="OUT.{npy,png}")
    p.add_argument("--zoom", type=int, default=1, choices=(1, 2, 3, 4))
    p.add_argument("--size", type=parse_size, default=None, metavar="PX",
                   help="render a PX x PX (or COLUMNSxROWS) matrix of the same field: pixel pitch and intrinsics "
                        "scaled (default: the detector's own matrix)")
    p.add_argument("--phase-time", type=float, default=None, metavar="SECONDS",
                   help="time in the case's 4D timeline (with a case profile as --volume)")
    p.add_argument("--respiration", default=None, metavar="KEY=VALUE[,KEY=VALUE...]",
                   help="override keys of the case's respiration: section (e.g. diaphragm_mm=7.5,rate_per_min=20)")
    p.add_argument("--mono", action="store_true", help="one energy (the spectrum's effective energy) instead of the spectrum")
    p.add_argument("--no-noise", action="store_true", help="leave out quantum noise")
    p.add_argument("--seed", type=int, default=None, help="seed of the quantum noise")
    p.add_argument("--device", default="auto", choices=("auto", "cpu", "gpu"), help="OpenCL device (default: a GPU if present)")
    p.set_defaults(run=run_render)

    b = add_command(benches, "drr", run_bench, "DRR speed, accuracy and memory figures",
                    "Median ms per frame of a 512x512x136 CT at 256, 512 and 1024 pixels, mono- and "
                    "polychromatic; accuracy against closed-form line integrals; resident memory "
                    "of a prepared 10-phase 4D CT.")
    b.add_argument("--frames", type=int, default=7, help="frames per timing (median reported)")
    b.add_argument("--sizes", default="256,512,1024", help="image sizes to time (pixels, comma-separated)")
    b.add_argument("--phases", type=int, default=10, help="phases of the 4D CT for the memory figure")
    b.add_argument("--skip", default="", help="comma-separated parts to leave out: speed, sampling, cache, plastimatch, "
                                              "accuracy, memory")
    b.add_argument("--ct", default="chest", choices=("chest", "torso"),
                   help="the real-size CT: the adult chest (default) or the quicker synthetic torso")
    b.add_argument("--rounds", type=int, default=3, help="alternating rounds of the plastimatch and CT-sampling side-by-sides")
    b.add_argument("--device", default="auto", choices=("auto", "cpu", "gpu"))

    from .acceptance import register as register_image_bench
    register_image_bench(benches)
