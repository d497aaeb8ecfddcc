"""`fluorosim bench drr`'s figures of what a frame costs beyond one cast: frames at an unchanged
pose from the projection cache, and the side-by-side against plastimatch's `drr`.

The plastimatch runs alternate with this renderer's frames in one loop, so the machine's
other load falls on both alike; each round gives its own ratio, and the medians are quoted.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..errors import FluorosimError
from ..patient.volume import Volume


def bench_ct(name: str) -> Volume:
    """The benchmark's real-size CT: "chest", the adult chest of appliance/patient/adult_chest.py
    (512 x 512 x 136 voxels of 0.8 x 0.8 x 2.5 mm), or "torso", the quicker synthetic torso
    of the same size (0.98 x 0.98 x 2.5 mm)."""
    from .bench import synthetic_torso

    if name == "torso":
        return synthetic_torso()
    from ..patient.adult_chest import build_adult_chest

    hu, spacing, origin = build_adult_chest()
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    T[:3, 3] = origin
    return Volume(hu=hu, T_ct_from_voxel=T, source="adult chest 512x512x136")


def centred(volume: Volume) -> Volume:
    """The volume moved so that its grid's centre is the ct origin (the benchmark's isocentre)."""
    nz, ny, nx = volume.hu.shape
    T = np.array(volume.T_ct_from_voxel, dtype=np.float64)
    centre = T[:3, :3] @ ((np.array([nx, ny, nz]) - 1) / 2.0) + T[:3, 3]
    T[:3, 3] -= centre
    return Volume(hu=volume.hu, T_ct_from_voxel=T, source=volume.source)


def next_phase(volume: Volume, shift_slices: int = 4) -> Volume:
    """A second phase: the CT's content moved `shift_slices` slices caudally (10 mm at 2.5 mm),
    a diaphragm's excursion, on the same grid."""
    hu = np.full_like(volume.hu, -1000)
    hu[:-shift_slices] = volume.hu[shift_slices:]
    return Volume(hu=hu, T_ct_from_voxel=volume.T_ct_from_voxel, source=volume.source + " (next phase)")


def cached_frames(renderer, volume: Volume, frames: int, pose) -> list[str]:
    """Lines of the cache figures at the renderer's matrix: the first frame at a new pose
    (both phases cast in one pass) against one blended cast, and frames at that pose with
    breathing and contrast changing."""
    from .projection_cache import ProjectionCache
    from .renderer import View

    a, b = renderer.prepare(volume), renderer.prepare(next_phase(volume))
    cache = ProjectionCache(renderer)
    view = View()
    renderer.render(a, pose(0.0), view, blend=(b, 0.5))
    cache.render(a, pose(0.3), view, blend=(b, 0.5))      # builds the two-phase kernel
    direct: list[float] = []
    miss: list[float] = []
    hit: list[float] = []

    def timed(out, render, *args, **kwargs):
        t0, c0 = time.perf_counter(), time.process_time()
        render(*args, **kwargs)
        out.append((time.perf_counter() - t0, time.process_time() - c0))

    for f in range(frames):
        T = pose(1.0 + f * 1.7 % 6.0)
        timed(direct, renderer.render, a, T, view, blend=(b, 0.4))
        timed(miss, cache.render, a, T, view, blend=(b, 0.4))
    T = pose(3.0)
    cache.render(a, T, view, blend=(b, 0.5))
    casts = cache.counts.casts
    on_host: list[float] = []
    chain = renderer.chain
    for f in range(3 * frames):
        changing = dict(blend=(b, (f % 10) / 10.0), concentration_factor=0.2 + 0.8 * (f % 7) / 6)
        timed(hit, cache.render, a, T, view, **changing)
        if chain is not None:       # a GPU's: the same frame with the detector on the host, alternating
            renderer.chain = None
            try:
                timed(on_host, cache.render, a, T, view, **changing)
            finally:
                renderer.chain = chain
    rows, cols = renderer.shape
    last = cache.render(a, T, view, blend=(b, 0.5))
    tables = renderer.caster.tables(last.kvp, 1.0, True)
    quad = tables.quadrature
    nodes = (f"the spectrum summed at {tables.device_bins} of {len(tables.weights)} energies at {last.kvp:g} kV, "
             f"within {100 * quad.max_error:.2f} % of every bin's sum (energy_nodes)") if quad is not None else \
        f"the spectrum summed at all {tables.device_bins} energies"

    def med(xs):
        wall, cpu = np.median(np.array(xs), axis=0) * 1000
        return f"{wall:.1f} ms ({cpu:.1f} cpu ms)"
    return [f"{cols}x{rows}: blended cast (HU blend, one pass) {med(direct)}; first frame at a new pose (both "
            f"phases' integrals, one pass) {med(miss)}; frame at an unchanged pose with breathing and contrast "
            f"changing {med(hit)}, {cache.counts.casts - casts} casts in {len(hit) + len(on_host)} frames"
            f"{f' (with the detector on the host, alternating: {med(on_host)})' if on_host else ''}; {nodes}"]


def slab_frames(renderer, volume: Volume, frames: int, pose, label: str) -> str:
    """A line of moving frames at the renderer's matrix (a new pose each, two phases blended in
    the cast, display quantity with noise): through the full volume and through pre-integrated
    slabs (slabs.py), alternating frame by frame; medians and their ratio, and the in-slab shift."""
    from .renderer import View, zoomed_K
    from .slabs import SlabCache, dominant_axis, in_slab_shift_px, slab_cast

    a, b = renderer.prepare(volume), renderer.prepare(next_phase(volume))
    slabs = SlabCache(renderer.dev, 2)
    view = View()
    first = pose(0.0)
    renderer.render(a, first, view, blend=(b, 0.5),
                    cast=slab_cast(renderer.caster, slabs, a, first, 1, (b, 0.5), np.inf))     # makes the slabs
    full: list[float] = []
    slab: list[float] = []
    for f in range(frames):
        for out, through in ((full, False), (slab, True)):
            T = pose(1.0 + (2 * f + through) * 1.7 % 6.0)
            c0 = time.process_time()
            cast = slab_cast(renderer.caster, slabs, a, T, 1, (b, 0.4), np.inf) if through else None
            renderer.render(a, T, view, blend=(b, 0.4), cast=cast)
            out.append(time.process_time() - c0)
    rows, cols = renderer.shape
    shift = in_slab_shift_px(zoomed_K(renderer.fluoroscope, 1), renderer.shape, a, first, dominant_axis(a, first))
    f_ms, s_ms = 1000 * float(np.median(full)), 1000 * float(np.median(slab))
    return (f"{cols}x{rows} {label}: moving frame through the full volume {f_ms:.1f} cpu ms, through slabs "
            f"{s_ms:.1f} cpu ms ({f_ms / s_ms:.2f}x); steepest ray's shift within a slab {shift:.2f} px")


def layout_copy_line(renderer, prepared, copies: int) -> str:
    """A line of what a copy of `prepared` laid out for rays along x costs (slabs.py's one-slice
    slabs, Caster.laid_out): made anew `copies` times, medians; a lateral view pays it once per
    phase, when breathing brings the next phase into the blended pair."""
    from .slabs import SlabCache

    cache = SlabCache(renderer.dev, 1, thickness=1)
    cache.get(prepared, 0)                                   # builds the kernel
    walls, cpus = [], []
    for _ in range(copies):
        cache.clear()
        renderer.dev.queue.finish()
        t0, c0 = time.perf_counter(), time.process_time()
        cache.get(prepared, 0)
        renderer.dev.queue.finish()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return (f"copy of the phase laid out for rays along x ({prepared.nbytes / 1e6:.0f} MB, made once per phase "
            f"entering a lateral view's blend): {1000 * float(np.median(walls)):.1f} ms "
            f"({1000 * float(np.median(cpus)):.1f} cpu ms)")


def outline_lines(renderer, prepared, frames: int, pose) -> list[str]:
    """Lines of what clipping the rays to the content's outline (outline.py) saves the cast: the
    material integrals alone, with the outline and with the box alone, alternating, `frames` each,
    cpu ms medians, for PA and lateral views (`pose(deg)`) of the middle and with the field moved
    to the body's side, where its rays meet the corners the outline cuts off."""
    import dataclasses

    from .renderer import View

    box_only = dataclasses.replace(prepared, outline=None)
    lines = []
    for label, deg, side_mm in (("PA", 0.0, 0.0), ("PA, 120 mm to the side", 0.0, 120.0),
                                ("lateral", 90.0, 0.0), ("lateral, 70 mm to the front", 90.0, 70.0)):
        T = np.array(pose(deg), float)
        T[0, 3] -= side_mm                 # the field moved along the detector's columns
        cpus: dict[str, list[float]] = {"outline": [], "box": []}
        for _ in range(frames):
            for key, volume in (("outline", prepared), ("box", box_only)):
                c0 = time.process_time()
                renderer.material_integrals(volume, T, View())
                cpus[key].append(time.process_time() - c0)
        a, b = (1000 * float(np.median(cpus[k])) for k in ("outline", "box"))
        lines.append(f"cast clipped to the outline, {label}: {a:.1f} cpu ms, to the box alone {b:.1f} ({b / a:.2f}x)")
    return lines


def plastimatch_binary() -> str | None:
    """plastimatch's executable: on PATH, or beside this Python (the `bench` extra installs it)."""
    found = shutil.which("plastimatch")
    if found:
        return found
    here = Path(sys.executable).parent / "plastimatch"
    return str(here) if here.exists() else None


def _plastimatch_frame_s(exe: str, ct_path: Path, out_dir: Path, algorithm: str, fluoroscope, gantry_deg: float,
                         n: int) -> float:
    """Seconds per DRR of one `plastimatch drr` run of `n` images 1.7 degrees apart, from its
    own "Total time" (reading the CT and converting HU included, shared by the n images)."""
    det = fluoroscope.detector
    g = fluoroscope.geometry
    size = f"{det.rows * det.pixel_pitch_mm:g} {det.columns * det.pixel_pitch_mm:g}"
    cmd = [exe, "drr", "-i", algorithm, "--sad", f"{g.source_to_isocentre_mm:g}", "--sid", f"{g.source_to_image_mm:g}",
           "-z", size, "-r", f"{det.rows} {det.columns}", "-y", f"{gantry_deg:g}", "-a", str(n), "-N", "1.7",
           "-P", "preprocess", "-t", "pfm", "-O", str(out_dir / "drr"), str(ct_path)]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise FluorosimError(f"plastimatch drr failed ({done.returncode}): {(done.stderr or done.stdout).strip()[-200:]}")
    m = re.search(r"Total time:\s*([0-9.eE+-]+)", done.stdout + done.stderr)
    return (float(m.group(1)) if m else wall) / n


def plastimatch_side_by_side(renderer, volume: Volume, rounds: int, frames: int) -> list[str]:
    """Rows comparing this renderer with plastimatch's exact and uniform `drr` on one CT and
    geometry, alternating: per round, plastimatch's seconds per image and this renderer's,
    and their ratio (> 1: this renderer is faster). "display" is a frame at a new pose through
    the full volume, as a held view's first; "moving" the same frame as a moving one is cast,
    through slabs where the shift rule allows (slabs.py, the bench's SLAB_MAX_SHIFT_PX)."""
    import SimpleITK as sitk

    from .bench import SLAB_MAX_SHIFT_PX, pa_pose
    from .renderer import View
    from .slabs import SlabCache, slab_cast

    exe = plastimatch_binary()
    if exe is None:
        return ["plastimatch: not installed (pip install plastimatch, or `make setup`, which installs the bench extra); "
                "side-by-side skipped"]
    fl = renderer.fluoroscope
    sod = fl.geometry.source_to_isocentre_mm
    prepared = renderer.prepare(volume)
    display, exact = View(), View(quantity="line-integral")
    slabs = SlabCache(renderer.dev, 1, thicker=True)

    def moving_cast(T):
        return slab_cast(renderer.caster, slabs, prepared, T, 1, None, SLAB_MAX_SHIFT_PX)
    casts = (("display", display, lambda T: None), ("moving", display, moving_cast), ("exact", exact, lambda T: None))
    lines = [f"plastimatch {exe}: {fl.detector.columns}x{fl.detector.rows} pixels of {fl.detector.pixel_pitch_mm:g} mm, "
             f"SAD {sod:g} mm, SID {fl.geometry.source_to_image_mm:g} mm, {frames} images per run; "
             "its time per image includes its CT read and HU conversion shared by the run's images"]
    with tempfile.TemporaryDirectory(prefix="fluorosim-plastimatch-") as tmp:
        tmp_dir = Path(tmp)
        ct_path = tmp_dir / "ct.mha"
        image = sitk.GetImageFromArray(np.asarray(volume.hu))
        T = np.asarray(volume.T_ct_from_voxel, dtype=np.float64)
        image.SetSpacing(tuple(float(np.linalg.norm(T[:3, i])) for i in range(3)))
        image.SetOrigin(tuple(float(x) for x in T[:3, 3]))
        sitk.WriteImage(image, str(ct_path))
        for name, gantry, tilt in (("PA", 0.0, 0.0), ("lateral", 90.0, 90.0)):
            for _, view, cast in casts:                 # per-view caches and the slab copy made
                renderer.render(prepared, pa_pose(sod, tilt), view, cast=cast(pa_pose(sod, tilt)))
            ratios: dict[tuple[str, str], list[float]] = {}
            times: dict[str, list[float]] = {}
            for _ in range(rounds):
                for algorithm in ("exact", "uniform"):
                    pm = _plastimatch_frame_s(exe, ct_path, tmp_dir, algorithm, fl, gantry, frames)
                    times.setdefault(f"plastimatch {algorithm}", []).append(pm)
                    for label, view, cast in casts:
                        ts = []
                        for f in range(frames):
                            pose = pa_pose(sod, tilt + 1.7 * f)
                            t0 = time.perf_counter()
                            renderer.render(prepared, pose, view, cast=cast(pose))
                            ts.append(time.perf_counter() - t0)
                        ours = float(np.median(ts))
                        times.setdefault(f"fluorosim {label}", []).append(ours)
                        ratios.setdefault((label, algorithm), []).append(pm / ours)
            summary = ", ".join(f"{k} {1000 * float(np.median(v)):.0f} ms" for k, v in times.items())
            lines.append(f"{name}: medians {summary}")
            for (label, algorithm), rs in ratios.items():
                lines.append(f"  {name} fluorosim {label} vs plastimatch {algorithm}: "
                             f"{' '.join(f'{x:.2f}' for x in rs)} per round, median {float(np.median(rs)):.2f}x")
    return lines


def load_note() -> str:
    return f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPU(s)"
