"""`fluorosim bench drr`: speed, accuracy and memory figures of the DRR engine.

Everything here is generated, so the benchmark needs no data files: a torso the size of the
clinical 4D CT of the seed paper (512 x 512 x 136 voxels of 0.98 x 0.98 x 2.5 mm), and small
test volumes whose line integrals are known in closed form.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..geometry import make_transform, rotation_about
from ..patient.volume import Volume

CLINICAL_SHAPE_ZYX = (136, 512, 512)
CLINICAL_SPACING_MM = (0.98, 0.98, 2.5)


def synthetic_torso(shape_zyx=CLINICAL_SHAPE_ZYX, spacing_mm=CLINICAL_SPACING_MM, breath: float = 0.0,
                    seed: int = 0) -> Volume:
    """A torso on a CT table: soft tissue with fat, two lungs, spine, ribs, a contrast-filled
    bladder, 2 % HU noise inside the body; air at -1000 HU outside it. `breath` in [0, 1]
    moves the diaphragm down by up to 20 mm (a 4D CT's phases)."""
    nz, ny, nx = shape_zyx
    sx, sy, sz = spacing_mm
    rng = np.random.default_rng(seed)
    x = (np.arange(nx) - (nx - 1) / 2) * sx
    y = (np.arange(ny) - (ny - 1) / 2) * sy
    z = (np.arange(nz) - (nz - 1) / 2) * sz
    X, Y = np.meshgrid(x, y)                     # (ny, nx) slice coordinates, mm
    body = (X / 170) ** 2 + (Y / 120) ** 2 <= 1
    fat = body & ((X / 160) ** 2 + (Y / 110) ** 2 > 1)
    lung_l = ((X - 75) / 60) ** 2 + ((Y + 5) / 75) ** 2 <= 1
    lung_r = ((X + 75) / 60) ** 2 + ((Y + 5) / 75) ** 2 <= 1
    spine = (X / 18) ** 2 + ((Y - 75) / 18) ** 2 <= 1
    rib_ring = ((X / 150) ** 2 + (Y / 102) ** 2 <= 1) & ((X / 140) ** 2 + (Y / 94) ** 2 > 1)
    table = (np.abs(X) < 230) & (Y > 130) & (Y < 142)
    bladder = ((X / 35) ** 2 + ((Y - 10) / 30) ** 2 <= 1)
    diaphragm_z = -20.0 - 20.0 * breath
    hu = np.full((nz, ny, nx), -1000, dtype=np.int16)
    base = np.where(body, 40, -1000).astype(np.int16)
    base[fat] = -90
    base[table] = 300
    for k, zk in enumerate(z):
        sl = base.copy()
        if zk > diaphragm_z:
            sl[lung_l | lung_r] = -850
            if (zk % 25.0) < 8.0:
                sl[rib_ring] = 700
        elif zk < z[0] + 80:
            sl[bladder] = 3000
        sl[spine] = 900
        hu[k] = sl
    noise = rng.normal(0, 20, size=(ny, nx)).astype(np.int16)
    inside = hu > -1000
    hu[inside] += np.broadcast_to(noise, hu.shape)[inside]
    T = np.diag([sx, sy, sz, 1.0])
    T[:3, 3] = [-(nx - 1) / 2 * sx, -(ny - 1) / 2 * sy, -(nz - 1) / 2 * sz]
    return Volume(hu=hu, T_ct_from_voxel=T, source=f"synthetic torso {nx}x{ny}x{nz}")


def pa_pose(source_to_isocentre_mm: float, tilt_deg: float = 0.0) -> np.ndarray:
    """T_xray_from_ct for a posterior-anterior beam (source under the table) with the CT's
    origin at the isocentre, tilted `tilt_deg` about the patient's long axis."""
    # xray x = patient left, xray z = anterior (-y_ct), xray y = superior.
    R = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    R = R @ rotation_about([0, 0, 1], np.radians(tilt_deg))
    return make_transform(R, [0.0, 0.0, source_to_isocentre_mm])


# -- accuracy ---------------------------------------------------------------------------
def flat_profile(size: int = 128):
    """The shipped flat-panel room read out at `size` x `size` pixels (no distortion)."""
    from pathlib import Path

    from ..config.fluoroscope import FluoroscopeProfile
    from ..config.loading import load_profile
    from .renderer import at_resolution

    path = Path(__file__).resolve().parents[2] / "configs" / "fluoroscopes" / "generic-flat-detector.yaml"
    return at_resolution(load_profile(path, FluoroscopeProfile), size, size)


def accuracy_cases():
    """(name, volume, closed-form chord function(source, dirs) -> mm, min path mm, pose)."""
    from .truth.analytic import box_chords, box_volume, ellipsoid_chords, ellipsoid_volume

    shape, sp = (48, 64, 64), (1.5, 1.25, 2.5)
    lo_i, hi_i = (9, 14, 6), (52, 47, 40)
    cases = []
    vol, lo, hi = box_volume(shape, sp, lo_i, hi_i)
    cases.append(("box, axis-aligned view", vol, lambda s, d, lo=lo, hi=hi: box_chords(s, d, lo, hi), 10.0,
                  make_transform(np.eye(3), [4.0, -3.0, 700.0])))
    T_grid = make_transform(rotation_about([0.3, 1.0, 0.2], np.radians(35)), [2.0, 1.0, -3.0])
    vol, lo, hi = box_volume(shape, sp, lo_i, hi_i, T_ct_from_grid=T_grid)
    cases.append(("box, oblique view", vol, lambda s, d, lo=lo, hi=hi, T=T_grid: box_chords(s, d, lo, hi, T), 10.0,
                  make_transform(rotation_about([1.0, 0.4, -0.3], np.radians(25)), [-5.0, 6.0, 700.0])))
    centre, axes = (3.0, -2.0, 4.0), (36.0, 28.0, 45.0)
    vol = ellipsoid_volume((48, 72, 64), (1.25, 1.0, 2.2), centre, axes)
    cases.append(("ellipsoid, partial volume", vol,
                  lambda s, d, c=centre, a=axes: ellipsoid_chords(s, d, c, a), 20.0,
                  make_transform(rotation_about([0.2, 1.0, 0.1], np.radians(40)), [0.0, 0.0, 700.0])))
    return cases


def accuracy_table(renderer, cases, with_reference: bool = True):
    """Rows of (case, method, max rel error, mean rel error, pixels) against closed form;
    and kernel vs NumPy reference (max relative) on the same voxel grid."""
    from .renderer import View, zoomed_K
    from .truth import reference
    from .truth.analytic import pixel_rays_ct

    rows_out = []
    rows, cols = renderer.shape
    K = zoomed_K(renderer.fluoroscope, 1)
    for name, vol, chords, min_mm, T in cases:
        prepared = renderer.prepare(vol)
        s, d = pixel_rays_ct(K, T, rows, cols)
        truth = chords(s, d) * renderer.mu_water_per_mm
        sel = truth > min_mm * renderer.mu_water_per_mm
        siddon = renderer.render(prepared, T, View(quantity="line-integral")).image
        joseph = renderer.material_integrals(prepared, T, View(), distorted=False, circle=False).sum(-1) * renderer.mu_water_per_mm
        moving, moving_lines = _moving_cast(renderer, prepared, T)
        for method, img in (("siddon (line-integral)", siddon), ("joseph (display)", joseph),
                            (moving, moving_lines * renderer.mu_water_per_mm)):
            rel = np.abs(img[sel] - truth[sel]) / truth[sel]
            rows_out.append((name, method, float(rel.max()), float(rel.mean()), int(sel.sum())))
        if with_reference:
            step = max(1, rows // 48)
            sub = slice(0, rows, step)
            ref = np.zeros((rows, cols))[sub, sub]
            ref = reference.line_integral_image(vol.hu, vol.T_ct_from_voxel, T, _sub_K(K, step), ref.shape[0], ref.shape[1],
                                                renderer.mu_water_per_mm)
            ker = siddon[sub, sub]
            ok = ref > 1.0 * renderer.mu_water_per_mm      # paths over 1 mm of water
            rel = np.abs(ker[ok] - ref[ok]) / ref[ok]
            rows_out.append((name, "kernel vs numpy reference", float(rel.max()), float(rel.mean()), int(ok.sum())))
    return rows_out


#: The shift within a slab up to which a moving frame is cast through slabs in the accuracy
#: table (pixels): the shipped profiles' rendering.slab_max_shift_px.
SLAB_MAX_SHIFT_PX = 1.0


def _moving_cast(renderer, prepared, T):
    """(method, image of summed material integrals) as a moving frame casts it: through the
    pre-integrated slabs where the shift rule allows them (slabs.py: the whole field, or the
    packets whose rays it allows), else the full volume."""
    from .renderer import View, zoomed_K
    from .slabs import SlabCache, dominant_axis, in_slab_shift_px, slab_cast

    shift = in_slab_shift_px(zoomed_K(renderer.fluoroscope, 1), renderer.shape, prepared, T,
                             dominant_axis(prepared, T))
    cast = slab_cast(renderer.caster, SlabCache(renderer.dev, 1, thicker=True), prepared, T, 1, None, SLAB_MAX_SHIFT_PX)
    if cast is None:
        lines = renderer.material_integrals(prepared, T, View(), distorted=False, circle=False)
        return f"moving: full ({shift:.1f} px)", lines.sum(-1)
    buf, _ = cast(prepared, T, 1, None, None, False, False)
    lines = renderer.dev.download(buf, np.empty(renderer.shape + (4,), dtype=np.float32))
    where = "slabs" if shift <= SLAB_MAX_SHIFT_PX else "slabs by packet"
    return f"moving: {where} ({shift:.1f} px)", lines.sum(-1)


def _sub_K(K, step):
    """Camera matrix whose pixel (u, v) is pixel (step*u, step*v) of K."""
    Ks = K.copy()
    Ks[0, 0] /= step
    Ks[1, 1] /= step
    Ks[0, 2] /= step
    Ks[1, 2] /= step
    return Ks


# -- the benchmark ----------------------------------------------------------------------
def _cpu_s() -> float:
    """CPU time of this process, all threads (OpenCL's worker threads included), in s."""
    return time.process_time()


def run(args) -> int:
    import psutil

    from ..config.case import Contrast, Materials
    from ..config.fluoroscope import FluoroscopeProfile
    from ..config.loading import load_profile
    from ..patient.heap import keep_large_blocks_apart
    from ..patient.timeline import PhaseTimeline
    from .renderer import Renderer, View, at_resolution

    keep_large_blocks_apart()           # the allocator as the appliance sets it, for the resident figures
    skip = {s.strip() for s in args.skip.split(",") if s.strip()}
    materials = Materials(contrast_min_hu=2500)
    contrast = Contrast(concentration_mg_per_ml=150)
    here = Path(__file__).resolve().parents[2] / "configs" / "fluoroscopes" / "generic-ii-carm.yaml"
    ii = load_profile(here, FluoroscopeProfile)
    print(f"fluorosim bench drr: {os.cpu_count()} CPU(s) visible, load average {os.getloadavg()[0]:.2f}")

    from .frame_cost import (
        bench_ct,
        cached_frames,
        centred,
        layout_copy_line,
        next_phase,
        outline_lines,
        plastimatch_side_by_side,
        slab_frames,
    )
    from .slabs import LAYOUT_PHASES, SlabCache, slab_cast

    ct = centred(bench_ct(args.ct)) if not {"speed", "sampling", "cache", "plastimatch", "memory"} <= skip else None
    # Memory first: the other parts' renderers and casts leave the allocator holding memory the
    # process no longer uses (about 0.35 GB after a run with the 1024 frames), which would count
    # against the 4D CT's figure.
    if "memory" not in skip and ct is not None:
        proc = psutil.Process()
        base = proc.memory_info().rss
        renderer = Renderer(at_resolution(ii, 512, 512), materials, contrast, device=args.device)
        n = args.phases
        # The phases of a 4D CT: the bench's CT with its content shifted 0-9 slices (up to 22 mm).
        phases = [(i * 0.4, (lambda i=i: next_phase(ct, i) if i else ct)) for i in range(n)]
        t0 = time.perf_counter()
        timeline = PhaseTimeline(phases, renderer, at_end="loop")
        timeline.wait_ready(timeout_s=600)
        # Play the timeline at 4x speed while the loader prepares the other phases.
        lookups, frames, t_start = [], [], time.perf_counter()
        while timeline.ready_count < n and time.perf_counter() - t0 < 600:
            t_case = 4.0 * (time.perf_counter() - t_start)
            f0 = time.perf_counter()
            a, b, w = timeline.at(t_case)
            lookups.append(time.perf_counter() - f0)
            renderer.render(a, pa_pose(620.0), View(), blend=(b, w) if b is not None else None)
            frames.append(time.perf_counter() - f0)
        timeline.wait_ready(timeout_s=600, all_phases=True)
        load_s = time.perf_counter() - t0
        a, b, w = timeline.at(0.2)
        renderer.render(a, pa_pose(620.0), View(), blend=(b, w) if b is not None else None)
        rss = proc.memory_info().rss
        held = sum(p.nbytes for p in timeline._prepared if p is not None)
        print(f"\nMemory: {n} phases of {ct.source} prepared in {load_s:.1f} s by the background loader; "
              f"device copies {held / 1e9:.2f} GB; process resident {rss / 1e9:.2f} GB "
              f"({(rss - base) / 1e9:.2f} GB more than before the renderer); limit 1.0 GB")
        if frames:
            print(f"While loading: {len(frames)} frames rendered, timeline lookup max {1000 * max(lookups):.2f} ms, "
                  f"frame median {1000 * float(np.median(frames)):.0f} ms, max {1000 * max(frames):.0f} ms "
                  "(the loader shares the two cores)")
        # The most the appliance holds on top: the moving frames' slab copies as the shipped profiles
        # keep them (rendering.slab_phases: 4), the phases blended now and the last two, each half a
        # phase, and the thicker slabs of the two blended (THICK_PHASES), a quarter each; and the renderer's copies of the
        # blended pair laid out for a lateral view's rays (LAYOUT_PHASES, each a whole phase), made
        # by a lateral frame between them.
        slabs = SlabCache(renderer.dev, 4, thicker=True)
        for p in [p for p in timeline._prepared if p is not None][:4]:
            slabs.get(p, 1)
            if slabs.thicker is not None:
                slabs.thicker.get(p, 1)
        a, b, w = timeline.at(0.2)
        renderer.render(a, pa_pose(620.0, 90.0), View(), blend=(b, w) if b is not None else None)
        renderer.dev.queue.finish()
        rss_slabs = proc.memory_info().rss
        layouts = renderer.caster.layouts
        laid = 0 if layouts is None else layouts.nbytes
        print(f"With 4 slab copies for moving frames (and 2 twice as thick) and {LAYOUT_PHASES} phases laid out for a lateral view's rays: "
              f"{slabs.nbytes / 1e9:.2f} + {laid / 1e9:.2f} GB more on the device; process resident "
              f"{rss_slabs / 1e9:.2f} GB; limit 1.0 GB")
        timeline.close()
        del renderer, slabs, timeline, phases

    if "speed" not in skip and ct is not None:
        torso = ct
        sp = np.linalg.norm(np.asarray(ct.T_ct_from_voxel)[:3, :3], axis=0)
        print(f"\nSpeed: {torso.source} ({sp[0]:.2f} x {sp[1]:.2f} x {sp[2]:.2f} mm), "
              f"{ii.name} profile, PA view with the pose moving 0-6 degrees between frames,\n"
              f"display quantity with noise, focal-spot blur and vignetting; {args.frames} frames each, medians.")
        print("'cpu ms' is the process's CPU time per frame (all threads): on an otherwise idle machine with N cores\n"
              "the wall time approaches cpu ms / N; 'ms/frame' is what this run measured, other load included.\n"
              f"'through slabs': the same frames, alternating with those, as the appliance casts a moving frame: the whole\n"
              f"field through slabs where its steepest ray shifts at most {SLAB_MAX_SHIFT_PX:g} px within one "
              "(rendering.slab_max_shift_px; slabs.py), else each\n16-pixel packet all of whose rays do, the others "
              "through the full volume; polychromatic with noise as the others.")
        print(f"{'image':>10} {'beam':>6} {'view':>8} {'ms/frame':>9} {'cpu ms':>8} {'fps':>6}  cast")
        for size in [int(s) for s in args.sizes.split(",") if s.strip()]:
            renderer = Renderer(at_resolution(ii, size, size), materials, contrast, device=args.device)
            prepared = renderer.prepare(torso)
            slabs = SlabCache(renderer.dev, 1, thicker=True)
            views = [(False, "PA", 0.0), (True, "PA", 0.0)] + ([(True, "lateral", 90.0)] if size == 512 else [])
            for poly, name, base_deg in views:
                view = View(polychromatic=poly, seed=0)
                first = pa_pose(620.0, base_deg)
                renderer.render(prepared, first, view)      # builds per-view caches
                if poly:                                    # and the slab copy
                    renderer.render(prepared, first, view, cast=slab_cast(renderer.caster, slabs, prepared, first, 1,
                                                                          None, np.inf))
                timings: dict[str, tuple[list, list]] = {"full volume": ([], [])}
                for f in range(args.frames):
                    T = pa_pose(620.0, tilt_deg=base_deg + (f * 1.7) % 6.0)
                    casts = {"full volume": None}
                    slab = slab_cast(renderer.caster, slabs, prepared, T, 1, None, SLAB_MAX_SHIFT_PX) if poly else None
                    if slab is not None:
                        casts["through slabs"] = slab
                    for label, cast in casts.items():
                        walls, cpus = timings.setdefault(label, ([], []))
                        t0, c0 = time.perf_counter(), _cpu_s()
                        renderer.render(prepared, T, view, cast=cast)
                        walls.append(time.perf_counter() - t0)
                        cpus.append(_cpu_s() - c0)
                for label, (walls, cpus) in timings.items():
                    ms = 1000 * float(np.median(walls))
                    share = f" ({len(walls)} of {args.frames} frames)" if len(walls) < args.frames else ""
                    print(f"{size:>5}x{size:<4} {'poly' if poly else 'mono':>6} {name:>8} {ms:9.1f} "
                          f"{1000 * float(np.median(cpus)):8.1f} {1000 / ms:6.1f}  {label}{share}")
                if name == "lateral":
                    print(f"{'':>10} {layout_copy_line(renderer, prepared, args.frames)}")
                    for line in outline_lines(renderer, prepared, args.frames, lambda deg: pa_pose(620.0, deg)):
                        print(f"{'':>10} {line}")
            del prepared, renderer, slabs
        print(f"OpenCL device: {_device_name(args.device)}")

    if "sampling" not in skip and ct is not None:
        from .sampling_cost import sampling_side_by_side

        print(f"\nCT sampling: {ct.source}, voxels larger than the pixel sampled as blocks (the profiles' ct_sampling) "
              f"against plain linear interpolation, PA display frames with noise, alternating in one run:")
        for line in sampling_side_by_side(at_resolution(ii, 512, 512), materials, contrast, ct,
                                          lambda deg: pa_pose(620.0, deg), args.rounds, args.frames, args.device):
            print(line)

    if "cache" not in skip and ct is not None:
        print(f"\nProjection cache: {ct.source} and a second phase 10 mm caudal, PA, display quantity with noise; "
              f"{args.frames} frames at new poses, {3 * args.frames} at one pose, medians:")
        for size in [int(s) for s in args.sizes.split(",") if s.strip()]:
            renderer = Renderer(at_resolution(ii, size, size), materials, contrast, device=args.device)
            for line in cached_frames(renderer, ct, args.frames, lambda deg: pa_pose(620.0, deg)):
                print(line)
            for label, base in (("PA", 0.0), ("lateral", 90.0)):
                print(slab_frames(renderer, ct, args.frames, lambda deg, base=base: pa_pose(620.0, base + deg), label))
            del renderer

    if "plastimatch" not in skip and ct is not None:
        print(f"\nSide by side with plastimatch's drr on {ct.source}, alternating in one run:")
        renderer = Renderer(at_resolution(ii, 512, 512), materials, contrast, device=args.device)
        for line in plastimatch_side_by_side(renderer, ct, args.rounds, 3):
            print(line)
        del renderer

    if "accuracy" not in skip:
        renderer = Renderer(flat_profile(128), Materials(), device=args.device)
        print(f"\nAccuracy against closed-form line integrals (128x128 image, mu_water = {renderer.mu_water_per_mm:.5f} /mm "
              f"at {renderer.spectrum.effective_kev:.2f} keV); relative errors over paths above the stated length:")
        print(f"{'volume':<28} {'method':<27} {'max rel':>9} {'mean rel':>9} {'pixels':>7}")
        for name, method, mx, mean, n in accuracy_table(renderer, accuracy_cases()):
            print(f"{name:<28} {method:<27} {100 * mx:8.4f}% {100 * mean:8.4f}% {n:7d}")
        print("(box and ellipsoid paths > 10 mm and > 20 mm; kernel vs reference over paths > 1 mm, on every 3rd pixel)")

    return 0


def _device_name(device: str) -> str:
    from .renderer import pick_device

    d = pick_device(device)
    return f"{d.name.strip()} ({d.platform.name.strip()}, {d.max_compute_units} compute units)"
