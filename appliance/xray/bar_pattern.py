"""A bar-pattern resolution test object, like the Leeds TOR 18FG, and its limiting-resolution figure.

The object is a 1 mm plate of groups of radio-opaque bars, 0.5 to 5 line pairs per mm,
laid on the intensifier's input face (as a physicist lays the TOR 18FG). Its CT is drawn
on a grid fine along the bars' axis (0.02 mm) and coarse across it, so a few hundred
thousand voxels hold the finest group. `limiting_resolution` renders it at one zoom and
finds the frequency at which the bars' modulation, relative to the coarsest group's, falls
to the detector model's MTF_AT_LIMIT: the finest group a reader could still resolve.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError
from ..geometry import make_transform
from ..patient.volume import Volume

#: The groups' frequencies (line pairs per mm), as on a TOR 18FG.
GROUPS_LP_PER_MM = (0.50, 0.56, 0.63, 0.71, 0.80, 0.90, 1.00, 1.12, 1.25, 1.40, 1.60, 1.80, 2.00, 2.24, 2.50,
                    2.80, 3.15, 3.55, 4.00, 4.50, 5.00)
PAIRS_PER_GROUP = 5
GAP_MM = 1.5                    # between groups
BAR_HU = 3000                   # the bars: dense bone-like material (the case has no lead)
PLATE_MM = 1.0                  # thickness along the beam
STEP_MM = 0.02                  # voxel along the bars' axis (x)
BAR_LENGTH_MM = 12.0            # along y


def layout() -> list[tuple[float, float, float]]:
    """(frequency lp/mm, x start mm, x end mm) of each group, the pattern centred on x = 0."""
    out, x = [], 0.0
    for f in GROUPS_LP_PER_MM:
        length = PAIRS_PER_GROUP / f
        out.append((f, x, x + length))
        x += length + GAP_MM
    half = (x - GAP_MM) / 2
    return [(f, a - half, b - half) for f, a, b in out]


def bar_pattern_volume() -> Volume:
    """The test object's CT: bars across x in the plane z = 0, centred at the origin (LPS mm)."""
    groups = layout()
    x0, x1 = groups[0][1] - 2.0, groups[-1][2] + 2.0
    nx = int(math.ceil((x1 - x0) / STEP_MM)) + 1
    x = x0 + STEP_MM * np.arange(nx)
    row = np.full(nx, -1000, np.int16)
    for f, a, b in groups:
        inside = (x >= a) & (x < b)
        # Bar (dense) for the first half of each line pair.
        phase = ((x - a) * f) % 1.0
        row[inside & (phase < 0.5)] = BAR_HU
    ny, nz = int(BAR_LENGTH_MM), 2
    hu = np.broadcast_to(row, (nz, ny, nx)).copy()
    T = np.diag([STEP_MM, 1.0, PLATE_MM / nz, 1.0])
    T[:3, 3] = [x0, -(ny - 1) / 2.0, -(nz - 1) / 2.0 * PLATE_MM / nz]
    return Volume(hu=hu, T_ct_from_voxel=T, source="bar pattern (TOR 18FG-like)")


def write_bar_pattern(out_dir: str | Path) -> Path:
    """Write bar-pattern.mha and its case profile bar-pattern.yaml into `out_dir`; returns the profile."""
    import SimpleITK as sitk

    out = Path(out_dir)
    vol = bar_pattern_volume()
    image = sitk.GetImageFromArray(vol.hu)
    image.SetSpacing(tuple(float(s) for s in vol.spacing_mm))
    image.SetOrigin(tuple(float(o) for o in vol.T_ct_from_voxel[:3, 3]))
    try:
        out.mkdir(parents=True, exist_ok=True)
        sitk.WriteImage(image, str(out / "bar-pattern.mha"), True)
        (out / "bar-pattern.yaml").write_text(CASE_YAML)
    except (OSError, RuntimeError) as e:
        raise FluorosimError(f"{out}: cannot write the bar pattern ({str(e).strip().splitlines()[-1][:120]})") from None
    return out / "bar-pattern.yaml"


CASE_YAML = """\
# A bar-pattern resolution test object like the Leeds TOR 18FG: 21 groups of 5 line pairs,
# 0.5 to 5 lp/mm, 1 mm thick, drawn by appliance/xray/bar_pattern.py (fluorosim case bar-pattern).
# Lay it on the intensifier's input face; `fluorosim bench image` reads its limiting resolution.
title: Bar pattern - limiting resolution
description: Find the finest group of bars you can still tell apart at each zoom.
phases:
  - volume: bar-pattern.mha
    time_s: 0
at_end: hold
materials:
  air_max_hu: -800
  bone_min_hu: 300
  bone_density_at_1000_hu_g_per_cm3: 1.6
patient:
  sex: O
  age_years: 30
  weight_kg: 0.1
  height_m: 0.1
"""


def modulations(profile_line: np.ndarray, u_of_x, magnification: float,
                nyquist_lp_per_mm: float) -> list[tuple[float, float]]:
    """(frequency at the detector lp/mm, modulation of the fundamental) of each group along a
    row of the image; `u_of_x(x_mm)` gives the column of an object point, fractional. Groups
    above the matrix's Nyquist frequency alias into coarser false bars and are left out, as are
    groups not wholly inside the beam."""
    out = []
    cols = np.arange(profile_line.size, dtype=float)
    for f, a, b in layout():
        if f / magnification > nyquist_lp_per_mm:
            break
        ua, ub = sorted((u_of_x(a + 0.5 / f), u_of_x(b - 0.5 / f)))    # half a pair in from each end
        sel = (cols >= math.ceil(ua)) & (cols <= math.floor(ub))
        # A group the field cuts (zero signal beyond the beam's edge) would read the edge's step
        # as its bars' modulation: only groups wholly in the beam count.
        if sel.sum() < 6 or ua < 0 or ub > profile_line.size - 1 or not np.all(profile_line[sel] > 0):
            continue
        # Object x of each column, then a sinusoid of the group's frequency fitted to it.
        xs = np.interp(cols[sel], [u_of_x(a), u_of_x(b)], [a, b]) if u_of_x(b) > u_of_x(a) else \
            np.interp(cols[sel], [u_of_x(b), u_of_x(a)], [b, a])
        phase = 2 * np.pi * f * (xs - a)
        basis = np.stack([np.sin(phase), np.cos(phase), np.ones_like(phase)], 1)
        (s, c, mean), *_ = np.linalg.lstsq(basis, profile_line[sel], rcond=None)
        out.append((f / magnification, math.hypot(s, c) / max(abs(mean), 1e-9)))
    return out


def limiting_from(mods: list[tuple[float, float]], threshold: float, nyquist_lp_per_mm: float) -> float:
    """The frequency where the modulation relative to the coarsest group's first falls to
    `threshold` (log-linear between the groups around it); the matrix's Nyquist frequency if
    it never does below it (finer bars alias: the matrix is what limits)."""
    if not mods:
        return float("nan")
    ref = mods[0][1]
    rel = [(f, m / ref) for f, m in mods]
    for (f0, m0), (f1, m1) in zip(rel, rel[1:]):
        if m1 < threshold <= m0:
            t = (math.log(m0) - math.log(threshold)) / (math.log(m0) - math.log(max(m1, 1e-12)))
            return f0 + t * (f1 - f0)
    return nyquist_lp_per_mm


def resolution_per_zoom(fl_native: FluoroscopeProfile, device: str = "auto",
                        zooms=(1, 2, 3, 4)) -> list[tuple[int, float, float]]:
    """(zoom, measured limiting resolution lp/mm at the input plane, the profile's) of the bar
    pattern laid on the intensifier's input face (15 mm in front of it), rendered noise-free at
    the detector's native matrix in a 6 mm strip across the bars (no pincushion: straight bars)."""
    from ..config.case import Materials
    from .detector import MTF_AT_LIMIT
    from .pixel_geometry import pixel_pitch_at_zoom_mm
    from .renderer import Renderer, View, zoomed_K

    straight = undistorted(fl_native)
    renderer = Renderer(straight, Materials(), device=device)
    prepared = renderer.prepare(bar_pattern_volume())
    sid = straight.geometry.source_to_image_mm
    depth = sid - 15.0
    T = make_transform(np.eye(3), [0.0, 0.0, depth])
    out = []
    for zoom in zooms:
        fov = straight.zoom_levels[zoom - 1].fov_mm
        image = renderer.render(prepared, T, View(zoom=zoom, quantity="intensity", noise=False,
                                                  collimation_mm=(fov, 6.0))).image
        K = zoomed_K(straight, zoom)
        row = image[int(round(K[1, 2]))]
        nyquist = 0.5 / pixel_pitch_at_zoom_mm(straight, zoom)
        mods = modulations(row, lambda x, K=K: K[0, 2] + K[0, 0] * x / depth, sid / depth, nyquist)
        out.append((zoom, limiting_from(mods, MTF_AT_LIMIT, nyquist), straight.image.limiting_resolution_lp_per_mm[zoom - 1]))
    return out


def undistorted(fl: FluoroscopeProfile) -> FluoroscopeProfile:
    """The same machine without pincushion distortion."""
    d = fl.intrinsics.distortion.model_copy(update=dict(k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0))
    return fl.model_copy(update={"intrinsics": fl.intrinsics.model_copy(update={"distortion": d})})
