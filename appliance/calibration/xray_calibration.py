"""The whole X-ray calibration: images of the sphere phantom in, intrinsics, distortion and
`T_xray_from_webcam` out, with a report and a pass/fail verdict against the phantom's
acceptance bar.

    images --field of view--> mask --blobs--> shadows --identify--> ball pairs
           --fit (all images jointly)--> K, distortion, poses --Eq. 3 + marker poses--> webcam

An image whose phantom cannot be identified is rejected with a one-line reason and the
others go on; the verdict says whether the result may be written into a profile.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.stats import f as f_distribution

from ..config.calibration_phantom import CalibrationPhantomProfile
from ..config.fluoroscope import FluoroscopeProfile
from ..errors import FluorosimError
from .blobs import detect_blobs
from .crowding import crowding_advice
from .field_of_view import FieldOfView, find_field_of_view, whole_image
from .fit import INTRINSIC_NAMES, Fit, View, fit_views
from .identification import identify
from .webcam_transform import AveragedTransform, average_rigid, webcam_in_xray


@dataclass
class ImageOutcome:
    name: str
    blobs: int = 0
    identified: int = 0
    fov: FieldOfView | None = None
    reason: str | None = None  # why the image was left out, None when it took part


@dataclass
class CalibrationResult:
    images: list[ImageOutcome]
    fit: Fit | None
    webcam: AveragedTransform | None
    failures: list[str] = field(default_factory=list)  # acceptance-bar failures; empty means pass
    timings_s: dict[str, list[float]] = field(default_factory=dict)  # stage -> seconds per image (fit: once)

    @property
    def passed(self) -> bool:
        return self.fit is not None and not self.failures


def read_image(path: str | Path) -> np.ndarray:
    """One X-ray frame as float32 (rows, cols): PNG/TIFF of any bit depth, or a .npy array."""
    path = Path(path)
    if not path.is_file():
        raise FluorosimError(f"{path}: no such image")
    if path.suffix.lower() == ".npy":
        try:
            image = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise FluorosimError(f"{path}: not a readable NumPy array ({e})") from None
    else:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise FluorosimError(f"{path}: not an image OpenCV can read; save the frame grab as PNG or TIFF")
        if image.ndim == 3:
            image = cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or min(image.shape) < 64:
        raise FluorosimError(f"{path}: expected a single-channel image of at least 64x64 pixels, got shape {image.shape}")
    return image.astype(np.float32)


def calibrate(images: list[tuple[str, np.ndarray]], phantom: CalibrationPhantomProfile, fluoroscope: FluoroscopeProfile,
              marker_poses: list[np.ndarray] | None = None) -> CalibrationResult:
    """Run the pipeline on (name, image) pairs; `marker_poses[i]` is T_webcam_from_marker of image i."""
    if marker_poses is not None and len(marker_poses) != len(images):
        raise FluorosimError(f"{len(marker_poses)} marker pose file(s) for {len(images)} image(s); "
                             f"give one --marker-pose per image, in the same order")
    K0 = fluoroscope.intrinsics.K()
    dist0 = fluoroscope.intrinsics.distortion.coefficients()
    acceptance = phantom.acceptance
    outcomes: list[ImageOutcome] = []
    views: list[View] = []
    timings: dict[str, list[float]] = defaultdict(list)
    for name, image in images:
        outcome = ImageOutcome(name)
        outcomes.append(outcome)
        try:
            t0 = time.perf_counter()
            if fluoroscope.detector.kind == "image_intensifier":
                fov = find_field_of_view(image, name)
            else:
                fov = whole_image(image.shape)
            outcome.fov = fov
            t1 = time.perf_counter()
            blobs = detect_blobs(image, fov, phantom.detection)
            outcome.blobs = len(blobs)
            t2 = time.perf_counter()
            found = identify(blobs, phantom, K0, dist0, name, fov)
            t3 = time.perf_counter()
            timings["field of view"].append(t1 - t0)
            timings["blobs"].append(t2 - t1)
            timings["identification"].append(t3 - t2)
        except FluorosimError as e:
            outcome.reason = str(e)
            continue
        outcome.identified = len(found.sphere_index)
        if outcome.identified < acceptance.min_spheres_per_image:
            outcome.reason = (f"{name}: only {outcome.identified} of {len(phantom.spheres)} balls identified "
                              f"(need {acceptance.min_spheres_per_image}); "
                              + (crowding_advice(len(blobs), blobs.crowded, phantom) or "center the phantom in the field"))
            continue
        views.append(View(name, phantom.centres()[found.sphere_index], found.uv, found.sphere_index, found.T_xray_from_phantom,
                          phantom.diameters()[found.sphere_index] / 2))
    if not views:
        return CalibrationResult(outcomes, None, None, ["no image could be used"], dict(timings))
    t0 = time.perf_counter()
    fit, free = _fit_with_tangential_choice(views, K0, dist0, phantom)
    _honest_principal_point_sigma(fit, free)
    timings["fit"].append(time.perf_counter() - t0)
    by_name = {o.name: o for o in outcomes}
    for name, reason in fit.rejected:
        by_name[name].reason = f"{name}: {reason}"
    webcam = None
    if marker_poses is not None and fit.views:
        pose_of = {name: T for (name, _), T in zip(images, marker_poses)}
        estimates = [webcam_in_xray(v.T_xray_from_phantom, phantom.T_phantom_from_marker(), pose_of[v.name]) for v in fit.views]
        webcam = average_rigid(estimates)
    result = CalibrationResult(outcomes, fit if fit.views else None, webcam, timings_s=dict(timings))
    result.failures = acceptance_failures(result, phantom)
    return result


def _fit_with_tangential_choice(views: list[View], K0: np.ndarray, dist0: np.ndarray,
                                phantom: CalibrationPhantomProfile) -> tuple[Fit, Fit | None]:
    """(the fit to report, the fit with p1 and p2 free or None when it failed).

    The first has p1 = p2 = 0 and/or free, as `phantom.fit.tangential` says; 'auto' keeps the
    free fit only when an F-test finds its lower residuals significant. The free fit is made
    in every mode, as the principal point's honest uncertainty comes from it.
    """
    gate, need = phantom.detection.final_gate_px, phantom.acceptance.min_spheres_per_image
    mode = phantom.fit.tangential
    start = np.asarray(dist0, float).copy()
    if mode == "fit":
        free = fit_views(views, K0, start, gate, need)
        return free, (free if free.views else None)
    start[2:4] = 0.0
    plain = fit_views(views, K0, start, gate, need, fixed=frozenset({"p1", "p2"}))
    if not plain.views:
        return plain, None
    free = fit_views(views, K0, plain.dist, gate, need)
    if not free.views:
        return plain, None
    if mode == "zero" or free.n_residuals != plain.n_residuals or free.ssr >= plain.ssr:
        return plain, free
    q = free.n_params - plain.n_params
    dof = free.n_residuals - free.n_params
    F = ((plain.ssr - free.ssr) / q) / (free.ssr / dof)
    p_value = float(f_distribution.sf(F, q, dof))
    return (free if p_value < phantom.fit.tangential_significance else plain), free


def _honest_principal_point_sigma(fit: Fit, free: Fit | None) -> None:
    """Widen the reported one-sigma of cx and cy to what the data support.

    With p1, p2 held at zero the principal point is tied to the centre of the radial
    distortion, which the balls pin to hundredths of a pixel; but a real decentring shifts
    that centre, and the held fit then puts the principal point pixels away while its own
    covariance still claims hundredths. The fit with p1, p2 free says how well the images
    fix the principal point itself; its sigma, and the distance between the two answers,
    are the honest uncertainty.
    """
    if free is None or not fit.sigma:
        if fit.sigma and {"p1", "p2"} & fit.fixed:
            fit.sigma["cx"] = fit.sigma["cy"] = float("inf")
        return
    for name, i in (("cx", 0), ("cy", 1)):
        shift = abs(float(free.K[i, 2] - fit.K[i, 2]))
        fit.sigma[name] = float(max(fit.sigma.get(name, 0.0), free.sigma.get(name, 0.0), shift))


def principal_point_sigma_px(fit: Fit) -> float:
    """Root sum of squares of cx's and cy's one-sigma (pixels)."""
    return float(np.hypot(fit.sigma.get("cx", float("inf")), fit.sigma.get("cy", float("inf"))))


#: The phantom that fills the field, named when the images at hand would need too many more.
FIELD_FILLING_PHANTOM = "configs/calibration-phantoms/two-plane-grid-332.yaml"


def principal_point_refusal(sigma_px: float, bar_px: float, images: int) -> str:
    """Why the principal point is refused and what fixes it, in one line.

    Through a narrow beam a shift of the principal point looks like a turn of the machine
    except for a pattern growing as the square of the angle off the axis, which the
    decentring terms p1, p2 partly mimic: only balls near the field's edge tell them apart,
    and tilting the phantom adds nothing. The one-sigma then falls as one over the square
    root of the number of such balls, so the images needed are images * (sigma / bar)^2.
    """
    head = f"principal point uncertain to +-{sigma_px:.2f} px (bar {bar_px} px): "
    if not np.isfinite(sigma_px):
        return head + ("the fit with decentring free failed; take more images with balls out to the field's edge, "
                       f"or use a phantom that fills the field ({FIELD_FILLING_PHANTOM})")
    # A tenth more than the square-root law asks, so the new set clears the bar and not just on average.
    needed = int(np.ceil(images * (sigma_px / bar_px) ** 2 * 1.1))
    advice = (f"about {needed} images like these would fix it (it narrows as one over the square root of their "
              "number; tilting the phantom does not help, balls near the field's edge do)")
    if needed > max(2 * images, 32):
        advice += f"; with this phantom that is too many, use one that fills the field ({FIELD_FILLING_PHANTOM})"
    return head + advice


def acceptance_failures(result: CalibrationResult, phantom: CalibrationPhantomProfile) -> list[str]:
    bar = phantom.acceptance
    fit = result.fit
    if fit is None:
        return ["no image survived the fit"]
    failures = []
    if len(fit.views) < bar.min_images:
        failures.append(f"{len(fit.views)} usable image(s), the bar is {bar.min_images}: "
                        f"take more images of the phantom at different tilts")
    if fit.rms_px > bar.max_rms_px:
        failures.append(f"reprojection RMS {fit.rms_px:.3f} px exceeds {bar.max_rms_px} px")
    if fit.worst_px > bar.max_residual_px:
        failures.append(f"worst residual {fit.worst_px:.3f} px exceeds {bar.max_residual_px} px")
    if result.webcam is not None:
        for view, mm, deg in zip(fit.views, result.webcam.translation_spread_mm, result.webcam.rotation_spread_deg):
            if mm > bar.max_webcam_spread_mm or deg > bar.max_webcam_spread_deg:
                failures.append(f"{view.name}: its T_xray_from_webcam lies {mm:.1f} mm / {deg:.2f} deg from the average "
                                f"(bar {bar.max_webcam_spread_mm} mm / {bar.max_webcam_spread_deg} deg); "
                                "check that its --marker-pose file belongs to this image")
    pp = principal_point_sigma_px(fit)
    if not pp <= bar.max_principal_point_uncertainty_px:
        failures.append(principal_point_refusal(pp, bar.max_principal_point_uncertainty_px, len(fit.views)))
    for name, f in (("fx", fit.K[0, 0]), ("fy", fit.K[1, 1])):
        pct = 100.0 * fit.sigma.get(name, float("inf")) / f
        if not pct <= bar.max_focal_uncertainty_percent:
            failures.append(f"{name} uncertainty {pct:.3f} % exceeds {bar.max_focal_uncertainty_percent} %: "
                            "add images with the phantom tilted")
    return failures


def report(result: CalibrationResult) -> str:
    """The text printed after a calibration: per image, the fit, the webcam transform, the verdict."""
    lines = ["image                          blobs  balls  used  dropped  rms px  worst px"]
    per_view = {v.name: v for v in (result.fit.views if result.fit else [])}
    for o in result.images:
        v = per_view.get(o.name)
        if v is not None:
            lines.append(f"{o.name[-30:]:30s} {o.blobs:5d}  {o.identified:5d}  {v.used:4d}  {v.dropped:7d}  "
                         f"{v.rms_px:6.3f}  {v.worst_px:8.3f}")
        else:
            lines.append(f"{o.name[-30:]:30s} {o.blobs:5d}  {o.identified:5d}  rejected: {o.reason}")
    fit = result.fit
    if fit is not None:
        values = [fit.K[0, 0], fit.K[1, 1], fit.K[0, 2], fit.K[1, 2], *fit.dist]
        lines.append("")
        lines.append("parameter        value     one-sigma")
        for name, value in zip(INTRINSIC_NAMES, values):
            lines.append(f"{name:>9s} {value:14.6g} {fit.sigma.get(name, float('nan')):12.3g}")
        if fit.fixed:
            lines.append(f"held at their starting value: {', '.join(sorted(fit.fixed))} (the images do not call for them)")
        lines.append(f"principal point one-sigma {principal_point_sigma_px(fit):.2f} px (cx, cy above: from the fit "
                     "with p1, p2 free and its distance to this one)")
        lines.append(f"reprojection RMS {fit.rms_px:.3f} px, worst residual {fit.worst_px:.3f} px over {len(fit.views)} image(s)")
    if result.webcam is not None:
        w = result.webcam
        t = w.T[:3, 3]
        lines.append(f"T_xray_from_webcam translation [{t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}] mm; spread over images: "
                     f"median {np.median(w.translation_spread_mm):.2f} mm, {np.median(w.rotation_spread_deg):.3f} deg")
    lines.append("PASSED the acceptance bar" if result.passed else "FAILED the acceptance bar: " + "; ".join(result.failures))
    return "\n".join(lines)
