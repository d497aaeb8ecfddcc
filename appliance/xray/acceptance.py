"""`fluorosim bench image`: a physicist's acceptance figures of the displayed image.

Each figure is measured on images the renderer makes of patients and test objects, against
ground truth computed here independently of the image chain:

- clipping and grey range of the display inside the field (8-bit grey 0 or 255 is clipped);
- detail: correlation of the band-passed display (Gaussian sigma 1 px minus sigma 6 px)
  with the band-passed exact (Siddon) line integral of the same view; at zoom 4 on the
  adult also against the exact line integral of the patient's anatomy itself (the same
  patient on a 0.2 mm grid, `anatomy_reference`), which tells a chain that loses detail
  from a CT whose voxels never held it;
- noise: the pixel SNR of a uniform water slab against the photon statistics the profile
  implies (spekpy's fluence per air kerma, the inverse-square law, the slab's transmission,
  the recursive filter's and point-spread's variance reduction), and its spread across zooms;
- lag: the recursive filter's step response against w^k.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError
from ..geometry import make_transform
from ..patient.materials import mass_attenuation
from ..patient.volume import Volume
from .bar_pattern import resolution_per_zoom, undistorted
from .truth.photon_statistics import expected_slab_snr

if TYPE_CHECKING:
    from .renderer import Frame

#: Clipped: the 8-bit grey the monitor shows is 0 or 255.
CLIP_LOW, CLIP_HIGH = 0, 255


def ap_pose(source_to_isocentre_mm: float, centre_ct=(0.0, 0.0, 0.0)) -> np.ndarray:
    """T_xray_from_ct of an antero-posterior beam with `centre_ct` (LPS mm) at the isocentre,
    shown the radiological way: superior up, the patient's right on the viewer's left."""
    # xray x = patient's left (+x ct), xray y (down the image) = inferior (-z ct), beam along +y ct.
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return make_transform(R, -R @ np.asarray(centre_ct, float) + [0.0, 0.0, source_to_isocentre_mm])


def interior(mask: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """Pixels fully inside the field: in the beam and past the soft field edge."""
    return mask & (edge >= 0.999)


def grey8(display: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(display, 0.0, 1.0) * 255.0).astype(np.uint8)


def clipped_fraction(display: np.ndarray, inside: np.ndarray) -> float:
    """Fraction of `inside` pixels the monitor shows as pure black or pure white."""
    g = grey8(display)[inside]
    return float(np.mean((g == CLIP_LOW) | (g == CLIP_HIGH))) if g.size else 0.0


def grey_span(display: np.ndarray, inside: np.ndarray) -> float:
    """2nd to 98th percentile of the in-field grey, as a fraction of the scale."""
    v = display[inside]
    if not v.size:
        return 0.0
    lo, hi = np.percentile(v, (2.0, 98.0))
    return float(hi - lo)


def band_pass(image: np.ndarray) -> np.ndarray:
    import cv2

    img = image.astype(np.float32)
    return cv2.GaussianBlur(img, (0, 0), 1.0) - cv2.GaussianBlur(img, (0, 0), 6.0)


def detail_correlation(display: np.ndarray, truth: np.ndarray, inside: np.ndarray, pre_blur_px: float = 0.0) -> float:
    """|Pearson correlation| of the band-passed display and band-passed truth over `inside`
    shrunk by 18 px (three of the wide Gaussian's sigmas), so the field edge does not count."""
    import cv2

    d: np.ndarray = display.astype(np.float32)
    if pre_blur_px > 0:
        d = cv2.GaussianBlur(d, (0, 0), pre_blur_px)
    core = cv2.erode(inside.astype(np.uint8), np.ones((37, 37), np.uint8)).astype(bool)
    if core.sum() < 100:
        return float("nan")
    a, b = band_pass(d)[core], band_pass(truth)[core]
    return abs(float(np.corrcoef(a, b)[0, 1]))


@dataclass
class Row:
    patient: str
    where: str
    zoom: int
    clipped: float
    span: float
    detail: float           # noise-free display against the exact (Siddon) line integral
    detail_chain: float     # noise-free display against the renderer's own line integral of the same rays
    detail_noisy: float     # with noise, after a 0.7 px blur, against the exact line integral
    ceiling: float          # the renderer's own line integral against the exact one (the CT's sampling)
    factor: float
    anatomy: float = float("nan")       # noise-free display against the anatomy's exact line integral
    ct_anatomy: float = float("nan")    # the CT's exact line integral against the anatomy's
    fine_voxels: bool = True            # the CT's voxels are a thin-slice CT's (none over 1 mm)


def _report(rows: list[Row]) -> None:
    print(f"{'patient':<18} {'view':<12} {'zoom':>4} {'clipped':>8} {'grey 2-98':>9} {'detail':>7} {'chain':>6} "
          f"{'noisy':>6} {'ceiling':>7} {'anatomy':>7} {'CT~anat':>7} {'tube x':>7}")
    for r in rows:
        print(f"{r.patient:<18} {r.where:<12} {r.zoom:>4} {100 * r.clipped:7.2f}% {100 * r.span:8.1f}% "
              f"{r.detail:7.3f} {r.detail_chain:6.3f} {r.detail_noisy:6.3f} {r.ceiling:7.3f} {_blank(r.anatomy):>7} "
              f"{_blank(r.ct_anatomy):>7} {r.factor:7.2f}")


def _blank(x: float) -> str:
    return "" if math.isnan(x) else f"{x:.3f}"


def patients(adult_size: str, thin: bool = True):
    """(name, volume, [(view name, centre in ct mm)], materials, contrast, fine voxels) of the
    built-in child (with its case's contrast-filled bladder, 1.5 mm voxels), the adult chest
    and the adult abdomen-pelvis on a clinical grid (2.5 mm slices of 0.8 mm pixels, or the
    small grid) and, with `thin`,
    the same adult as a thin-slice CT (0.8 mm voxels). Fine voxels: a thin-slice CT's, a
    voxel no bigger than 1 mm in any direction."""
    from ..config.case import CaseProfile, Materials
    from ..config.commands import default_config_dir
    from ..config.loading import load_profile
    from ..patient import adult_pelvis, builtin
    from ..patient.adult_chest import SIZES, build_adult_chest
    from .anatomy_reference import thin_slice_chest

    child_case = load_profile(default_config_dir() / "cases" / "child-torso-vcug.yaml", CaseProfile)

    b = builtin.Builder()
    child = Volume(hu=b.phase(builtin.PhaseSpec(12.0, 3, 0.0)), T_ct_from_voxel=builtin.grid().T_ct_from_voxel,
                   source="built-in child, bladder full")
    hu, spacing, origin = build_adult_chest(*SIZES[adult_size])
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    T[:3, 3] = origin
    adult = Volume(hu=hu, T_ct_from_voxel=T, source=f"adult chest ({adult_size})")
    del hu
    adult_views = [("mediastinum", (0.0, 0.0, 30.0)), ("r lung", (-90.0, 0.0, 60.0)), ("upper abdo", (0.0, 0.0, -90.0))]
    child_views = [("chest", (0.0, 0.0, 90.0)), ("abdomen", (0.0, 0.0, -30.0)), ("bladder", (0.0, 0.0, -140.0))]
    out: list[tuple] = [("child", child, child_views, child_case.materials, child_case.contrast, False),
                        ("adult chest", adult, adult_views, Materials(), None, False)]
    # The abdomen-pelvis CT as a scanner writes it: the couch in the beam, -3024 HU padding
    # outside the reconstruction circle, arms cut by the circle.
    hu, spacing, origin = adult_pelvis.build_adult_pelvis(*adult_pelvis.SIZES[adult_size])
    T = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    T[:3, 3] = origin
    pelvis = Volume(hu=hu, T_ct_from_voxel=T, source=f"adult abdomen-pelvis ({adult_size})")
    del hu
    pelvis_views = [("lumbar/bowel", (0.0, 0.0, 60.0)), ("pelvis", (0.0, 0.0, -100.0))]
    out.append(("adult abdo-pelvis", pelvis, pelvis_views, Materials(), None, False))
    if thin:
        out.append(("adult thin-slice", thin_slice_chest, adult_views, Materials(), None, True))
    return out


def run(args) -> int:
    from ..config.case import Materials
    from ..config.loading import load_profile
    from .renderer import Renderer, View, at_resolution

    fl_full = load_profile(args.fluoroscope, FluoroscopeProfile)
    fl = at_resolution(fl_full, args.size, args.size)
    # The detail figure compares with the undistorted line integral: the same machine without pincushion.
    straight = undistorted(fl)
    started = time.perf_counter()
    sod = fl.geometry.source_to_isocentre_mm
    zooms = [int(z) for z in args.zooms.split(",")]
    rows: list[Row] = []
    fails: list[str] = []
    timings: dict[str, tuple[float, float]] = {}
    anatomies: dict[str, np.ndarray] = {}       # the anatomy's exact line integral per adult view at zoom 4
    for name, volume, views, materials, contrast, fine_voxels in patients(args.adult, args.thin):
        renderer = Renderer(straight, materials, contrast, device=args.device)
        mu_rho = mass_attenuation([renderer.spectrum.effective_kev], contrast)[0]
        prepared = renderer.prepare(volume() if callable(volume) else volume)
        del volume
        for where, centre in views:
            T = ap_pose(sod, centre)
            for zoom in zooms:
                clean = renderer.render(prepared, T, View(zoom=zoom, noise=False))
                noisy = renderer.render(prepared, T, View(zoom=zoom, noise=True, seed=zoom))
                mask = renderer.field_mask(zoom, None, fl.detector.kind == "image_intensifier")
                inside = interior(mask, renderer.detector.edge(mask, zoom))
                line = renderer.line_integral(prepared, T, zoom)
                # The same rays' attenuation at the effective energy: each material's density
                # integral times its mass attenuation (cm^2/g x g/cm^3 x mm / 10 = ln units).
                joseph = renderer.material_integrals(prepared, T, View(zoom=zoom), distorted=False) @ mu_rho / 10.0
                row = Row(name, where, zoom, clipped_fraction(noisy.image, inside), grey_span(noisy.image, inside),
                          detail_correlation(clean.image, line, inside), detail_correlation(clean.image, joseph, inside),
                          detail_correlation(noisy.image, line, inside, pre_blur_px=0.7),
                          detail_correlation(joseph, line, inside), noisy.exposure_factor, fine_voxels=fine_voxels)
                if args.anatomy and name.startswith("adult") and zoom == 4:
                    truth = anatomies.get(where)
                    if truth is None:
                        truth = anatomies[where] = _anatomy_line_integral(renderer, T, centre, zoom)
                    row.anatomy = detail_correlation(clean.image, truth, inside)
                    row.ct_anatomy = detail_correlation(line, truth, inside)
                rows.append(row)
            if where == views[0][0]:
                timings[name] = _timing(renderer, prepared, T)
        del prepared
    print(f"Display on {fl.name} at {args.size}x{args.size}, {time.perf_counter() - started:.0f} s. AP views; detail = "
          "|correlation| of band-passed (sigma 1 - 6 px) images inside the field: 'detail' noise-free display vs the exact "
          "Siddon line integral of the CT it was rendered from, 'chain' vs the renderer's own (Joseph) attenuation of the same "
          "rays at the effective energy, 'noisy' with the profile's noise after a 0.7 px blur vs Siddon, 'ceiling' Joseph vs "
          "Siddon (what the CT's voxels allow); at zoom 4 on the adult, 'anatomy' the display vs the exact line integral of "
          "the patient's anatomy (the same patient on a 0.2 mm grid, no CT noise) and 'CT~anat' the CT's own exact line "
          "integral vs the anatomy's; tube x = the exposure control's output factor")
    _report(rows)
    for name, (chain_ms, physics_ms) in timings.items():
        print(f"time per frame, {name}, zoom 1 (median of 5): whole chain {chain_ms:.0f} ms, the physics alone "
              f"(rays and spectrum, no detector or display) {physics_ms:.0f} ms: the chain adds {chain_ms - physics_ms:.0f} ms")
    for r in rows:
        if r.clipped > 0.01:
            fails.append(f"{r.patient} {r.where} zoom {r.zoom}: {100 * r.clipped:.2f} % clipped (limit 1 %)")
        if r.span < 0.5:
            fails.append(f"{r.patient} {r.where} zoom {r.zoom}: grey range {100 * r.span:.0f} % (at least 50 %)")
        if r.detail_chain < 0.8:
            fails.append(f"{r.patient} {r.where} zoom {r.zoom}: detail {r.detail_chain:.2f} through the chain (at least 0.80)")
        # Every CT counts, the clinical grid's 2.5 mm slices and the child's 1.5 mm voxels too:
        # the renderer samples voxels larger than the pixel as the blocks they are
        # (fluoroscope.ct_sampling), as their exact line integral does.
        if not r.detail >= 0.8:
            fails.append(f"{r.patient} {r.where} zoom {r.zoom}: detail {r.detail:.2f} vs the exact line integral (at least 0.80)")
    for r in rows:
        if r.patient.startswith("adult") and r.where == "mediastinum" and r.zoom in (1, 4):
            need = 0.5 if r.zoom == 1 else 0.3
            if not r.detail_noisy >= need:
                fails.append(f"adult mediastinum zoom {r.zoom}: noisy detail {r.detail_noisy:.2f} (at least {need})")

    renderer = Renderer(straight, Materials(), device=args.device)
    # Noise: a 150 mm water slab filling the beam, with the exposure control on.
    slab = _water_slab(150.0)
    prepared = renderer.prepare(slab)
    T = ap_pose(sod)
    print("\nNoise in a 150 mm water slab (central disc of a quarter of the field's radius), settled recursive filter:")
    print(f"{'zoom':>4} {'SNR measured':>12} {'photon stats':>12} {'ratio':>6} {'tube x':>7}")
    snrs = []
    for zoom in (1, 2, 3, 4):
        roi = _disc(renderer.shape, 0.25)
        # The noise is the signal over its noise-free self (vignetting and the slab's own
        # obliquity divide out), on the detector signal the display LUT is given. The slab's
        # transmission is read from that signal: at the kV the exposure control set.
        clean_frame = _signal(renderer.render(prepared, T, View(zoom=zoom, noise=False)))
        transmission = float(np.median(clean_frame[_disc(renderer.shape, 0.1)]))
        clean = clean_frame[roi]
        measured = []
        for seed in range(3):
            frame = renderer.render(prepared, T, View(zoom=zoom, noise=True, seed=100 + seed))
            measured.append(1.0 / float(np.std(_signal(frame)[roi] / clean)))
        vig = renderer.detector.gain(zoom)
        transmission_at_detector = transmission / (1.0 if vig is None else float(np.median(vig[_disc(renderer.shape, 0.1)])))
        expected = expected_slab_snr(renderer.fluoroscope, zoom, transmission_at_detector, frame.exposure_factor,
                                     renderer.mu_water_per_mm, renderer.detector.psf_sigma_px(zoom), settled=True,
                                     kvp=frame.kvp)
        snr = statistics.median(measured)
        snrs.append(snr)
        print(f"{zoom:>4} {snr:12.1f} {expected:12.1f} {snr / expected:6.3f} {frame.exposure_factor:7.2f}")
        if abs(snr / expected - 1) > 0.10:
            fails.append(f"water slab zoom {zoom}: SNR {snr:.1f} vs photon statistics {expected:.1f} (within 10 %)")
    spread = max(snrs) / min(snrs) - 1
    print(f"SNR spread across zooms: {100 * spread:.1f} % (limit 25 %)")
    if spread >= 0.25:
        fails.append(f"SNR varies {100 * spread:.0f} % across zooms (under 25 %)")

    # Lag: step from the slab to open air, the recursive filter live.
    air = _water_slab(0.0)
    air_prepared = renderer.prepare(air)
    w = renderer.fluoroscope.image.recursive_weight
    renderer.lag.reset()
    for _ in range(30):
        before = renderer.render(prepared, T, View(noise=False, temporal="live", quantity="display"))
    steps = [renderer.render(air_prepared, T, View(noise=False, temporal="live")) for _ in range(6)]
    # The filter runs on the detector signal: read it back through the frames' log windows.
    roi = _disc(renderer.shape, 0.1)
    s_before = _signal(before)[roi].mean()
    s_after = float(np.median(renderer.render(air_prepared, T, View(quantity="intensity", noise=False)).image[roi]))
    print(f"\nLag: step from the slab to air, recursive weight {w}: fraction of the step still to come after k frames")
    print(f"{'k':>3} {'measured':>9} {'w^k':>7}")
    for k, frame in enumerate(steps, start=1):
        remaining = (s_after - _signal(frame)[roi].mean()) / (s_after - s_before)
        print(f"{k:>3} {remaining:9.4f} {w ** k:7.4f}")
        if abs(remaining - w ** k) > 0.02:
            fails.append(f"lag after {k} frames: {remaining:.3f} of the step left, w^k = {w ** k:.3f}")
    print(f"\nLimiting resolution of the bar pattern (configs/cases/bar-pattern.yaml) on the input face, "
          f"{fl_full.detector.columns}x{fl_full.detector.rows} native matrix, where the bars' modulation falls to 4 %:")
    print(f"{'zoom':>4} {'measured lp/mm':>15} {'profile lp/mm':>14} {'ratio':>6}")
    last = 0.0
    for zoom, lp_mm, stated in resolution_per_zoom(fl_full, args.device):
        print(f"{zoom:>4} {lp_mm:15.2f} {stated:14.2f} {lp_mm / stated:6.3f}")
        if abs(lp_mm / stated - 1) > 0.2:
            fails.append(f"resolution at zoom {zoom}: {lp_mm:.2f} lp/mm vs the profile's {stated:.2f} (within 20 %)")
        if not lp_mm > last:
            fails.append(f"resolution at zoom {zoom} ({lp_mm:.2f} lp/mm) does not rise with zoom")
        last = lp_mm
    print(f"\n{len(fails)} figure(s) outside the acceptance limits" + (":" if fails else ""))
    for f in fails:
        print(f"  {f}", file=sys.stderr)
    return 1 if fails else 0


def _anatomy_line_integral(renderer, T, centre, zoom: int) -> np.ndarray:
    """The exact (Siddon) line integral of the adult's anatomy about `centre` (anatomy_reference)
    in the view `T` at `zoom`, through `renderer`'s rays."""
    from .anatomy_reference import anatomy_around

    prepared = renderer.prepare(anatomy_around(centre))
    try:
        return renderer.line_integral(prepared, T, zoom)
    finally:
        del prepared


def _timing(renderer, prepared, T) -> tuple[float, float]:
    """Median ms per frame of the displayed image and of the detector signal without its chain."""
    from .renderer import View

    out = []
    for view in (View(temporal="live"), View(quantity="intensity", noise=False)):
        renderer.render(prepared, T, view)
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            renderer.render(prepared, T, view)
            times.append(time.perf_counter() - t0)
        out.append(1000.0 * statistics.median(times))
    return out[0], out[1]


def _signal(frame: Frame) -> np.ndarray:
    """The detector signal a display frame carries (only display frames are asked for it)."""
    if frame.signal is None:
        raise FluorosimError("the renderer returned a display frame without its detector signal")
    return frame.signal


def _disc(shape, fraction: float) -> np.ndarray:
    rows, cols = shape
    v, u = np.ogrid[:rows, :cols]
    r = fraction * min(rows, cols) / 2
    return (v - (rows - 1) / 2) ** 2 + (u - (cols - 1) / 2) ** 2 <= r * r


def _water_slab(thickness_mm: float) -> Volume:
    """A 500 x 500 mm water slab `thickness_mm` thick (0: one voxel of air), centred at the origin, y its thin axis."""
    n = max(2, int(round(thickness_mm / 5.0)))
    hu = np.full((8, n, 100), 0 if thickness_mm > 0 else -1000, np.int16)
    T = np.diag([5.0, thickness_mm / n if thickness_mm > 0 else 5.0, 62.5, 1.0])
    T[:3, 3] = [-247.5, -(n - 1) / 2 * T[1, 1], -218.75]
    return Volume(hu=hu, T_ct_from_voxel=T, source=f"water slab {thickness_mm:g} mm")


def register(benches) -> None:
    b = benches.add_parser("image", help="acceptance figures of the displayed image (clipping, detail, noise, lag)",
                           description="Render the built-in child, a synthetic adult chest (on a clinical grid and "
                                       "as a thin-slice CT) and an adult abdomen-pelvis CT (couch, padding) at zooms and "
                                       "positions, a water slab and a step; print "
                                       "clipping, grey range, detail correlation, SNR against photon statistics and the "
                                       "lag step response. Exit 1 if a figure misses the issue's limits, the detail bar "
                                       "against the exact line integral on every CT, thin-slice or clinical grid.")
    b.add_argument("--fluoroscope", default=None, metavar="PROFILE.yaml",
                   help="fluoroscope profile (default: the shipped image-intensifier C-arm)")
    b.add_argument("--size", type=int, default=256, help="render matrix (pixels, default 256)")
    b.add_argument("--zooms", default="1,4", help="zoom levels for the patient figures (default 1,4)")
    b.add_argument("--adult", choices=("small", "full"), default="full", help="adult chest and abdomen-pelvis grid (default full)")
    b.add_argument("--no-thin", dest="thin", action="store_false",
                   help="leave out the adult as a thin-slice CT (0.8 mm voxels), the CT the detail bar is held on")
    b.add_argument("--no-anatomy", dest="anatomy", action="store_false",
                   help="leave out the zoom-4 detail against the adult's anatomy on a 0.2 mm grid (about 30 s a view)")
    b.add_argument("--device", default="auto", choices=("auto", "cpu", "gpu"))
    b.set_defaults(run=_run_with_default)


def _run_with_default(args) -> int:
    if args.fluoroscope is None:
        from ..config.commands import default_config_dir
        args.fluoroscope = str(default_config_dir() / "fluoroscopes" / "generic-ii-carm.yaml")
    return run(args)
