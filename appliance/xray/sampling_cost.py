"""`fluorosim bench drr`'s figure for the CT sampling (fluoroscope `ct_sampling`, drr.cl's
VOXEL_WEIGHT): what sampling voxels larger than the pixel as blocks costs a frame.

Its peer is the same kernel built with plain linear weights (LINEAR_SAMPLES: the per-sample
arithmetic left out, as before the sampling existed), in the same renderer on the same CT,
the two swapped frame by frame so that the machine's other load falls on both alike.
"""

from __future__ import annotations

import time

import numpy as np


def sampling_side_by_side(fluoroscope, materials, contrast, volume, pose, rounds: int, frames: int,
                          device: str = "auto") -> list[str]:
    """Lines of the report: median ms per display frame (noise on, the pose moving 0-6 degrees
    between frames, as `bench drr`'s speed figure) and per cast alone, block sampling against
    linear, `frames` poses a round, each pose rendered by both in turn."""
    from .renderer import Renderer, View

    renderer = Renderer(fluoroscope, materials, contrast, device=device)
    dev, caster = renderer.dev, renderer.caster
    program = dev.cl.Program(dev.ctx, dev.source).build(options=[*dev.options, "-DLINEAR_SAMPLES"])
    kernels = {"blocks": caster._joseph, "linear": dev.cl.Kernel(program, caster._joseph_name)}
    prepared = renderer.prepare(volume)
    frame_s: dict[str, list[float]] = {k: [] for k in kernels}
    cast_s: dict[str, list[float]] = {k: [] for k in kernels}
    view = View(seed=0)
    renderer.render(prepared, pose(0.0), view)          # per-view caches built before timing
    order = list(kernels)
    for _ in range(rounds):
        for f in range(frames):
            T = pose((f * 1.7) % 6.0)
            # Frame by frame, the two in turns, the first of each pair alternating.
            order.reverse()
            for name in order:
                caster._joseph = kernels[name]
                t0 = time.perf_counter()
                renderer.render(prepared, T, view)
                frame_s[name].append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                renderer.material_integrals(prepared, T, view, distorted=True)
                cast_s[name].append(time.perf_counter() - t0)
    med = {k: (1000 * float(np.median(frame_s[k])), 1000 * float(np.median(cast_s[k]))) for k in kernels}
    caster._joseph = kernels["blocks"]
    rows, cols = renderer.shape
    out = [f"{'sampling':>8} {'ms/frame':>9} {'cast ms':>8}   ({cols}x{rows}, {rounds} rounds of {frames} frames, medians)"]
    for k, (fm, cm) in med.items():
        out.append(f"{k:>8} {fm:9.1f} {cm:8.1f}")
    out.append(f"blocks / linear: frame {med['blocks'][0] / med['linear'][0]:.3f}, cast {med['blocks'][1] / med['linear'][1]:.3f}")
    return out
