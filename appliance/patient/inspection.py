"""What a CT volume holds, in the terms a technician needs to place it: extent, spacing,
orientation and centre in the `ct` frame (DICOM LPS, mm), the HU distribution and whether
it looks like a CT stored in Hounsfield units at all, and the value at a point.

Every figure is computed from the volume's voxel grid and `T_ct_from_voxel`, the same
frame the renderer uses, so what `fluorosim case inspect` prints is where the voxels are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import apply
from .volume import Volume

#: Letters of the LPS axes, for the negative and positive direction of x, y and z.
AXIS_LETTERS = (("R", "L"), ("A", "P"), ("I", "S"))
AXIS_WORDS = ("x (right- / left+)", "y (anterior- / posterior+)", "z (inferior- / superior+)")

#: HU ranges of the tissues whose histogram peaks a CT shows (HU). Wide on purpose: a peak
#: anywhere in the range counts, the ranges only say which tissue a peak belongs to.
LANDMARK_RANGES_HU = {"air": (-1100.0, -900.0), "lung": (-900.0, -500.0), "fat": (-200.0, -50.0),
                      "soft tissue": (-50.0, 120.0)}
#: A voxel at or above this is bone or contrast (HU); at or above METAL_MIN_HU, metal or a clip.
BONE_MIN_HU = 300.0
METAL_MIN_HU = 3000.0


@dataclass(frozen=True)
class Extent:
    """Where the voxel centres lie in the ct frame."""

    first_centre: np.ndarray   # (3,) LPS mm of voxel (0, 0, 0)
    last_centre: np.ndarray    # (3,) LPS mm of voxel (nx-1, ny-1, nz-1)
    low: np.ndarray            # (3,) per LPS axis, smallest coordinate of any voxel centre (mm)
    high: np.ndarray           # (3,) largest (mm)
    centre: np.ndarray         # (3,) midpoint of the voxel-centre box (mm)


def extent(volume: Volume) -> Extent:
    nx, ny, nz = volume.shape_xyz
    corners = np.array([[i, j, k] for i in (0, nx - 1) for j in (0, ny - 1) for k in (0, nz - 1)], dtype=float)
    ct = apply(volume.T_ct_from_voxel, corners)
    low, high = ct.min(axis=0), ct.max(axis=0)
    return Extent(ct[0], ct[-1], low, high, (low + high) / 2)


def orientation_code(volume: Volume) -> str:
    """Which LPS direction each voxel index axis (i, j, k) increases toward, e.g. 'LPS' or 'RAS'.

    An oblique axis gets the letter of its largest component, as ITK's orientation codes do.
    """
    R = volume.T_ct_from_voxel[:3, :3] / volume.spacing_mm
    code = ""
    for axis in range(3):
        col = R[:, axis]
        biggest = int(np.argmax(np.abs(col)))
        code += AXIS_LETTERS[biggest][1 if col[biggest] > 0 else 0]
    return code


def obliquity_deg(volume: Volume) -> float:
    """Largest angle between a voxel axis and the LPS axis it is named for (degrees)."""
    R = volume.T_ct_from_voxel[:3, :3] / volume.spacing_mm
    return float(np.degrees(np.arccos(np.clip(np.abs(R).max(axis=0), -1, 1))).max())


@dataclass(frozen=True)
class HuSummary:
    minimum: float
    maximum: float
    percentiles: dict[int, float]       # percentile -> HU
    peaks: dict[str, float]             # tissue -> HU of its histogram peak (only the tissues found)
    bone_fraction: float                # of voxels at or above BONE_MIN_HU
    metal_fraction: float
    verdict: str                        # one sentence
    looks_like_ct: bool


def hu_summary(volume: Volume, max_samples: int = 4_000_000) -> HuSummary:
    hu = volume.hu.reshape(-1)
    if hu.size > max_samples:       # an even subsample: the histogram, not every voxel, is wanted
        hu = hu[:: int(np.ceil(hu.size / max_samples))]
    values = hu.astype(np.float32)
    pct = {p: float(v) for p, v in zip((1, 5, 50, 95, 99), np.percentile(values, [1, 5, 50, 95, 99]))}
    edges = np.arange(-1105.0, 3006.0, 10.0)    # 10 HU bins centred on multiples of 10
    counts, _ = np.histogram(values, bins=edges)
    # Smooth over 50 HU so noise does not make a peak of every bin.
    smooth = np.convolve(counts, np.ones(5) / 5, mode="same")
    centres = (edges[:-1] + edges[1:]) / 2
    peaks = {}
    for name, (lo, hi) in LANDMARK_RANGES_HU.items():
        sel = (centres >= lo) & (centres < hi)
        if not sel.any():
            continue
        i = int(np.argmax(np.where(sel, smooth, -1)))
        near = slice(max(i - 3, 0), i + 4)
        peak = near.start + int(np.argmax(counts[near]))      # the raw bin under the smoothed peak
        # A landmark is a real local peak holding at least 0.5 % of the voxels per 50 HU.
        is_peak = smooth[i] >= smooth[max(i - 5, 0)] and smooth[i] >= smooth[min(i + 5, len(smooth) - 1)]
        if is_peak and smooth[i] * 5 >= 0.005 * values.size:
            peaks[name] = float(centres[peak])
    bone = float((values >= BONE_MIN_HU).mean())
    metal = float((values >= METAL_MIN_HU).mean())
    ok, verdict = _verdict(float(values.min()), float(values.max()), pct, peaks, bone)
    return HuSummary(float(values.min()), float(values.max()), pct, peaks, bone, metal, verdict, ok)


def _verdict(lo: float, hi: float, pct: dict[int, float], peaks: dict[str, float], bone: float) -> tuple[bool, str]:
    if lo >= 0 and hi >= 900:
        # Air is -1000 HU: a CT in HU without a single negative voxel has lost its rescale intercept.
        return False, (f"no: every value is >= 0 (min {lo:.0f}, max {hi:.0f}); this looks like stored scanner "
                       "values without the rescale intercept (HU = value - 1024 on most scanners); convert to HU first")
    if hi - lo < 200:
        return False, f"no: values span only {lo:.0f} to {hi:.0f}; this is not a CT in HU (a label map or a mask?)"
    if hi <= 10 and lo >= -10:
        return False, "no: values lie within +-10; this looks like attenuation or a normalised image, not HU"
    if "air" not in peaks and pct[1] > -500:
        return False, (f"doubtful: no air around the patient (1st percentile {pct[1]:.0f} HU); "
                       "a CT in HU shows air near -1000 HU")
    if "soft tissue" not in peaks and "fat" not in peaks:
        return False, "doubtful: no soft-tissue or fat peak between -200 and 120 HU"
    body = ", ".join(sorted(peaks))
    return True, f"yes: histogram peaks at {body}; {100 * bone:.1f} % of voxels at or above {BONE_MIN_HU:.0f} HU"


def value_at(volume: Volume, point_lps) -> tuple[np.ndarray, int | None]:
    """(voxel index (i, j, k) nearest the LPS point, its HU or None when outside the volume)."""
    ijk = apply(np.linalg.inv(volume.T_ct_from_voxel), np.asarray(point_lps, dtype=float))
    idx = np.rint(ijk).astype(int)
    nx, ny, nz = volume.shape_xyz
    if np.any(idx < 0) or np.any(idx >= (nx, ny, nz)):
        return ijk, None
    return ijk, int(volume.hu[idx[2], idx[1], idx[0]])


def report(volume: Volume, at=None) -> list[str]:
    """The lines `fluorosim case inspect` prints."""
    nx, ny, nz = volume.shape_xyz
    sp = volume.spacing_mm
    e = extent(volume)
    lines = [f"volume: {volume.source}",
             f"grid: {nx} x {ny} x {nz} voxels (i, j, k); spacing {sp[0]:.3f} x {sp[1]:.3f} x {sp[2]:.3f} mm",
             f"orientation: i, j, k increase toward {', '.join(orientation_code(volume))} "
             f"(LPS letters; obliquity {obliquity_deg(volume):.1f} deg)",
             "frame: LPS mm, as ITK reads every format (a NIfTI's RAS world has x and y negated)",
             "voxel-centre bounds (LPS mm):"]
    for axis in range(3):
        lines.append(f"  {AXIS_WORDS[axis]:27s} {e.low[axis]:9.1f} to {e.high[axis]:9.1f}  "
                     f"(length {e.high[axis] - e.low[axis]:.1f} mm)")
    fmt = ", ".join
    lines.append(f"first voxel centre (0, 0, 0): ({fmt(f'{v:.1f}' for v in e.first_centre)}) mm")
    lines.append(f"last voxel centre ({nx - 1}, {ny - 1}, {nz - 1}): ({fmt(f'{v:.1f}' for v in e.last_centre)}) mm")
    lines.append(f"centre: ({fmt(f'{v:.1f}' for v in e.centre)}) mm")
    h = hu_summary(volume)
    lines.append(f"HU: min {h.minimum:.0f}, max {h.maximum:.0f}; percentiles "
                 + ", ".join(f"{p:g}%: {v:.0f}" for p, v in h.percentiles.items()))
    landmarks = ", ".join(f"{k} {v:.0f}" for k, v in h.peaks.items()) or "none"
    lines.append(f"histogram peaks (HU): {landmarks}; bone/contrast (>= {BONE_MIN_HU:.0f} HU) {100 * h.bone_fraction:.2f} %"
                 f", metal (>= {METAL_MIN_HU:.0f} HU) {100 * h.metal_fraction:.3f} %")
    lines.append(f"looks like a CT in HU: {h.verdict}")
    if at is not None:
        ijk, value = value_at(volume, at)
        where = f"({fmt(f'{v:.1f}' for v in at)}) mm"
        if value is None:
            lines.append(f"at {where}: outside the volume (voxel index ({fmt(f'{v:.1f}' for v in ijk)}))")
        else:
            lines.append(f"at {where}: {value} HU (voxel ({fmt(str(int(round(v))) for v in ijk)}))")
    return lines
