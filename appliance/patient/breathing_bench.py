"""`fluorosim bench breathing`: what controllable breathing costs per frame, and to set up.

On the benchmark torso of `bench drr` (512 x 512 x 136 voxels, the seed's clinical CT size)
it times, in one run and on one device: a plain frame of the still CT (the peer), a frame of
the breathing patient (two precomputed depth states blended by the renderer), and a frame
re-voxelised from the CT for each breath (the approach not taken), each cast anew as at a
new pose; then the still CT and the breathing patient with the C-arm still, through the
projection cache the daemon renders with (each depth state cast once, the breath blended
in projection space), the figures `bench drr` gives as "unchanged pose, breathing +
contrast" for a two-phase 4D CT. Medians of `--frames` frames each, wall and the process's
CPU time (a shared machine's wall time is above an idle one's); ratios against the still CT
measured in the same run.
"""

from __future__ import annotations

import os
import statistics
import time


def _median_ms(fn, frames: int) -> tuple[float, float]:
    """(wall, cpu) medians in ms of `frames` calls after one untimed call (kernels, ray tables)."""
    fn()
    walls, cpus = [], []
    for _ in range(frames):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return 1000.0 * statistics.median(walls), 1000.0 * statistics.median(cpus)


def run(args) -> int:
    import numpy as np

    from ..config.case import Materials, Respiration
    from ..xray.bench import flat_profile, pa_pose, synthetic_torso
    from ..xray.projection_cache import ProjectionCache
    from ..xray.renderer import Renderer, View
    from .breathing_motion import BreathingAnatomy
    from .breathing_timeline import BreathingTimeline
    from .respiration import BreathingControl

    size = args.size
    print(f"fluorosim bench breathing: {os.cpu_count()} CPU(s) visible, load average {os.getloadavg()[0]:.2f}")
    t0 = time.perf_counter()
    ct = synthetic_torso()
    print(f"CT: {ct.source}, drawn in {time.perf_counter() - t0:.1f} s; image {size}x{size}, display quantity "
          f"with noise; {args.frames} frames each, medians")
    params = Respiration()
    materials = Materials()
    renderer = Renderer(flat_profile(size), materials, device=args.device)
    T = pa_pose(renderer.fluoroscope.geometry.source_to_isocentre_mm)
    view = View()

    t0, c0 = time.perf_counter(), time.process_time()
    anatomy = BreathingAnatomy(ct, params, materials)
    split_s, split_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    # The peer: the same split without the plate rule (respiration.rib_max_height_mm), so its cost reads apart.
    c0 = time.process_time()
    without_plates = BreathingAnatomy(ct, params.model_copy(update={"rib_max_height_mm": None}), materials)
    plain_cpu_s = time.process_time() - c0
    del without_plates
    control = BreathingControl(params)
    states = [control.at(t) for t in np.linspace(0.0, 4.0, 9)]
    build = []
    for s in states[:3]:
        t0 = time.perf_counter()
        anatomy.volume_at(s)
        build.append(time.perf_counter() - t0)
    print(f"Setup: split into still bone, {len(anatomy.ribs)} rigid rib pieces and soft tissue in {split_s:.2f} s "
          f"(cpu {split_cpu_s:.2f} s; without the plate rule cpu {plain_cpu_s:.2f} s, "
          f"x{split_cpu_s / max(plain_cpu_s, 1e-9):.2f}); "
          f"one moved CT in {1000 * statistics.median(build):.0f} ms (median of {len(build)})")

    t0 = time.perf_counter()
    timeline = BreathingTimeline(lambda: ct, params, materials, renderer, control=control)
    timeline.wait_ready(600, all_phases=True)
    print(f"Depth states: {params.depth_states} prepared in {time.perf_counter() - t0:.1f} s "
          f"(excursion 0 to {params.depth_max:g} of the breath, {sum(p.nbytes for p in timeline._prepared) / 1e6:.0f} MB)")

    still = renderer.prepare(ct)
    clock = iter(np.arange(0.0, 1e6, 0.37))

    def plain():
        renderer.render(still, T, view)

    def breathing():
        a, b, w = timeline.at(next(clock))
        renderer.render(a, T, view, blend=None if b is None else (b, w))

    def revoxelised():
        s = control.at(next(clock))
        renderer.render(renderer.prepare(anatomy.volume_at(s)), T, view)

    lookups = []
    for _ in range(200):
        t0 = time.perf_counter()
        timeline.at(next(clock))
        lookups.append(time.perf_counter() - t0)
    cache = ProjectionCache(renderer)

    def still_cached():
        cache.render(still, T, view)

    def breathing_cached():
        a, b, w = timeline.at(next(clock))
        cache.render(a, T, view, blend=None if b is None else (b, w))

    rows = [("still CT (no breathing)", _median_ms(plain, args.frames)),
            ("breathing: two depth states blended", _median_ms(breathing, args.frames)),
            ("breathing: CT re-voxelised each frame", _median_ms(revoxelised, max(3, args.frames // 3)))]
    for a in timeline._prepared:           # each depth state cast once at this pose, as a still C-arm does
        cache.render(a, T, view)
    rows += [("still CT, unchanged pose (cache)", _median_ms(still_cached, 3 * args.frames)),
             ("breathing, unchanged pose (cache)", _median_ms(breathing_cached, 3 * args.frames))]
    wall0, cpu0 = rows[0][1]
    print(f"{'frame':<44} {'ms/frame':>9} {'cpu ms':>8} {'vs still':>9}")
    for name, (wall, cpu) in rows:
        peer = rows[3][1] if "cache" in name else (wall0, cpu0)
        print(f"{name:<44} {wall:9.1f} {cpu:8.1f} {cpu / peer[1]:9.2f}")
    print("(ratios of CPU time; the cached rows against the cached still CT)")
    print(f"timeline lookup: median {1e6 * statistics.median(lookups):.0f} us, max {1e6 * max(lookups):.0f} us")
    print(f"OpenCL device: {renderer.device.name.strip()}")
    timeline.close()
    return 0


def register(benches) -> None:
    b = benches.add_parser("breathing", help="frame cost of controllable breathing",
                           description="Median ms per frame of the benchmark torso still, breathing (blended depth "
                                       "states) and re-voxelised per frame, in one run; set-up times.")
    b.add_argument("--frames", type=int, default=9, help="frames per timing (median reported)")
    b.add_argument("--size", type=int, default=512, help="image size (pixels)")
    b.add_argument("--device", default="auto", choices=("auto", "cpu", "gpu"))
    b.set_defaults(run=run)
