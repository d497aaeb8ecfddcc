"""`fluorosim build-patient` and `fluorosim bench builtin-patient`."""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..command_options import add_command
from ..config.appliance import ApplianceProfile
from ..config.commands import default_config_dir
from ..config.loading import load_profile, resolve
from ..errors import FluorosimError
from .builtin import NAMES, STAGES, builtin_phases, timeline
from .volume import Volume


def default_cache_dir() -> Path:
    """`<data_dir>/cache` of the shipped appliance profile (configs/appliance.yaml)."""
    path = default_config_dir() / "appliance.yaml"
    profile = load_profile(path, ApplianceProfile)
    return resolve(path.parent, profile.data_dir) / "cache"


def _window(hu: np.ndarray, lo: float = -1000.0, hi: float = 1000.0) -> np.ndarray:
    return (np.clip((hu.astype(np.float32) - lo) / (hi - lo), 0, 1) * 255).astype(np.uint8)


def write_previews(volume: Volume, out_dir: Path, stem: str) -> list[Path]:
    """Axial, coronal and sagittal slices through the centre and an antero-posterior sum projection, as PNG.

    Slices are shown the radiological way (the patient's right on the viewer's left,
    superior up). The projection is a poor man's radiograph: exp(-sum of a rough mu) along
    y, for checking anatomy by eye, not the renderer's physics.
    """
    from PIL import Image
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FluorosimError(f"{out_dir}: cannot create the preview folder ({e.strerror or e}); choose another --previews") from None
    hu = volume.hu
    nz, ny, nx = hu.shape
    T = np.linalg.inv(volume.T_ct_from_voxel)

    def index(point):
        return np.rint(T @ [*point, 1.0])[:3].astype(int)
    written = []

    def save(img: np.ndarray, name: str) -> None:
        path = out_dir / f"{stem}-{name}.png"
        try:
            Image.fromarray(img).save(path)
        except OSError as e:
            raise FluorosimError(f"{path}: cannot write the preview ({e.strerror or e}); check the folder and free space") from None
        written.append(path)
    for z in (120.0, 30.0, -30.0, -120.0):
        save(_window(hu[index((0, 0, z))[2]]), f"axial{z:+.0f}")
    save(_window(hu[::-1, index((0, 0, 0))[1], :]), "coronal")
    save(_window(hu[::-1, :, index((0, 0, 0))[0]]), "sagittal")
    # Water-relative attenuation at about 60 keV; iodine voxels as water plus iodine.
    mu_water = 0.02     # 1/mm
    rel = np.clip(hu.astype(np.float32), -1000, 2000) / 1000.0 + 1.0
    iodine = np.maximum(hu.astype(np.float32) - 2500.0, 0) / 10.0
    rel = np.where(hu >= 2500, 1.0 + iodine * 0.03, rel)
    line = (rel.sum(axis=1) * volume.spacing_mm[1] * mu_water)[::-1]
    # Log-domain display as a fluoroscope shows it: bone and contrast bright, lung dark.
    body = line[line > 0.5]
    lo, hi = (np.percentile(body, 1), np.percentile(body, 99.7)) if body.size else (0.0, 1.0)
    save((255 * np.clip((line - lo) / (hi - lo + 1e-9), 0, 1)).astype(np.uint8), "ap-projection")
    return written


def run_build(args) -> int:
    cache = Path(args.cache) if args.cache else default_cache_dir()
    started = time.perf_counter()
    phases = builtin_phases(args.name, cache, progress=lambda m: print(m, flush=True))
    print(f"{args.name}: {len(phases)} phases over {phases[-1][0] + 1:.0f} s, ready in {time.perf_counter() - started:.1f} s")
    if args.previews:
        specs = timeline()
        shown = set()
        for (t, load), spec in zip(phases, specs):
            key = (spec.stage, spec.breath)
            if spec.breath not in (0.0, 1.0) or key in shown:
                continue
            shown.add(key)
            state = "expiration" if spec.breath == 0 else "inspiration"
            for path in write_previews(load(), Path(args.previews), f"t{t:04.1f}s-{state}"):
                print(path)
    return 0


def run_bench(args) -> int:
    times = []
    for i in range(args.repeat):
        with tempfile.TemporaryDirectory(prefix="fluorosim-patient-") as tmp:
            started = time.perf_counter()
            builtin_phases(args.name, Path(tmp))
            times.append(time.perf_counter() - started)
            if i == 0:
                started = time.perf_counter()
                phases = builtin_phases(args.name, Path(tmp))
                cached = time.perf_counter() - started
                started = time.perf_counter()
                loads = [phases[k][1]() for k in range(4)]
                load_s = (time.perf_counter() - started) / len(loads)
        print(f"build {i + 1}/{args.repeat}: {times[-1]:.2f} s", flush=True)
    unique = len({(s.stage, s.breath) for s in timeline()})
    print(f"builtin-patient {args.name}: {len(timeline())} phases ({unique} distinct volumes, "
          f"{len(STAGES)} VCUG stages), grid {loads[0].shape_xyz} at {loads[0].spacing_mm[0]:.2f} mm")
    print(f"  build (all phases, written to cache): median {statistics.median(times):.2f} s "
          f"(min {min(times):.2f}, max {max(times):.2f}, n={len(times)}); limit 30 s")
    print(f"  second call (cache hit): {cached * 1000:.1f} ms; load one phase: {load_s * 1000:.0f} ms")
    if statistics.median(times) > 30.0:
        print("  OVER the 30 s limit", file=sys.stderr)
        return 1
    return 0


def run_adult_chest(args) -> int:
    from .adult_chest import write_adult_chest

    started = time.perf_counter()
    profile = write_adult_chest(args.out, args.size, args.seed, args.format)
    print(f"{profile}: case profile of the synthetic adult chest ({args.size} grid), "
          f"CT written beside it in {time.perf_counter() - started:.1f} s")
    return 0


def run_bar_pattern(args) -> int:
    from ..xray.bar_pattern import write_bar_pattern

    print(write_bar_pattern(args.out))
    return 0


def register(commands, benches) -> None:
    from ..cli import command_group

    case = command_group(commands, "case", "make and inspect training cases")
    a = add_command(case, "adult-chest", run_adult_chest, "write a synthetic adult chest CT and its case profile",
                    "Draw a synthetic adult chest and upper abdomen CT (ribs with a cortical shell, spine, lungs with "
                    "branching vessels, heart, diaphragm domes, liver, bowel gas) and write it with a case profile "
                    "into --out.")
    a.add_argument("--out", required=True, metavar="DIR", help="folder for adult-chest.mha and adult-chest.yaml")
    a.add_argument("--size", choices=("full", "small"), default="full",
                   help="full: 136x512x512 voxels of 2.5x0.8x0.8 mm (about 30 s); small: 68x128x128 for quick tests")
    a.add_argument("--seed", type=int, default=0, help="vessel branching, bowel gas and CT noise (default 0)")
    a.add_argument("--format", choices=(".mha", ".nii.gz", ".nii"), default=".mha", help="volume file format")
    b = add_command(case, "bar-pattern", run_bar_pattern,
                    "write the bar-pattern resolution test object and its case profile",
                    "Write a TOR 18FG-like bar pattern (0.5-5 lp/mm, 1 mm plate) as bar-pattern.mha with its case "
                    "profile bar-pattern.yaml into --out (configs/cases ships one).")
    b.add_argument("--out", required=True, metavar="DIR")

    p = add_command(commands, "build-patient", run_build, "build (or reuse) the built-in 4D patient and show it",
                    "Build the phases of a built-in patient into the cache (once per machine), report the time, and "
                    "optionally write PNG previews of each stage.")
    p.add_argument("--name", default=NAMES[0], choices=NAMES, help=f"built-in patient (default {NAMES[0]})")
    p.add_argument("--cache", metavar="DIR", help="cache folder (default: <data_dir>/cache of configs/appliance.yaml)")
    p.add_argument("--previews", metavar="DIR", help="write axial/coronal/sagittal PNGs and an AP projection per stage here")

    b = add_command(benches, "builtin-patient", run_bench, "time building every phase of the built-in patient",
                    "Build the built-in patient from scratch into a temporary folder REPEAT times; print the median "
                    "build time, the cache-hit time and the load time of a phase.")
    b.add_argument("--name", default=NAMES[0], choices=NAMES)
    b.add_argument("--repeat", type=int, default=3, help="builds to take the median of (default 3)")

    from .breathing_bench import register as register_breathing_bench
    register_breathing_bench(benches)
