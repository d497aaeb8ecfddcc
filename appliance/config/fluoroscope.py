"""The profile of one fluoroscope: detector, geometry, intrinsics, zoom, tube, dose, display.

A service technician edits this file (`fluorosim profile edit`); `fluorosim calibrate xray`
rewrites the intrinsics, distortion and `T_xray_from_webcam` in place.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..geometry import camera_matrix
from . import limits
from .base import IDENTITY, Findings, RigidTransform, Section, matrix
from .ct_sampling import CtSampling
from .energy_nodes import EnergyNodes
from .image_chain import ImageChain


class Detector(Section):
    kind: Literal["image_intensifier", "flat_panel"] = Field(
        description="An image intensifier has a circular field of view and vignetting; a flat panel is rectangular.")
    columns: int = Field(gt=0, le=8192, description="Image width (pixels).")
    rows: int = Field(gt=0, le=8192, description="Image height (pixels).")
    pixel_pitch_mm: float = Field(gt=0, le=5, description="Pixel size at the detector (input phosphor) plane at the "
                                                          "widest field of view (mm).")
    vignetting: float = Field(0.0, ge=0, lt=1,
                              description="Image intensifier brightness lost at the edge of the circular field "
                                          "relative to its centre (fraction, falls off as radius squared); 0 for "
                                          "flat panels.")


class Geometry(Section):
    source_to_image_mm: float = Field(gt=100, le=3000, description="Focal spot to detector plane distance, SID (mm).")
    source_to_isocentre_mm: float = Field(gt=50, le=3000, description="Focal spot to the C-arm's isocentre (mm).")


class Distortion(Section):
    """OpenCV's radial-tangential model, the one `cv2.calibrateCamera` estimates."""

    k1: float = Field(0.0, description="Radial coefficient (dimensionless).")
    k2: float = Field(0.0, description="Radial coefficient (dimensionless).")
    p1: float = Field(0.0, description="Tangential coefficient (dimensionless).")
    p2: float = Field(0.0, description="Tangential coefficient (dimensionless).")
    k3: float = Field(0.0, description="Radial coefficient (dimensionless).")

    def coefficients(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])


class Intrinsics(Section):
    status: Literal["nominal", "calibrated"] = Field(
        description="'nominal' until `fluorosim calibrate xray` has measured this machine.")
    fx: float = Field(gt=0, description="Focal length along columns: SID / pixel pitch (pixels).")
    fy: float = Field(gt=0, description="Focal length along rows (pixels).")
    cx: float = Field(description="Principal point column (pixels).")
    cy: float = Field(description="Principal point row (pixels).")
    distortion: Distortion = Field(default_factory=Distortion, description="Intensifier pincushion distortion.")
    calibrated_on: str | None = Field(None, description="Date of the calibration that produced these numbers (ISO 8601).")
    rms_px: float | None = Field(None, ge=0, description="Reprojection RMS of that calibration (pixels).")

    def K(self) -> np.ndarray:
        return camera_matrix(self.fx, self.fy, self.cx, self.cy)


class ZoomLevel(Section):
    fov_mm: float = Field(gt=0, le=600, description="Field-of-view diameter at the detector plane (mm).")
    air_kerma_rate_mgy_per_min: dict[str, float] = Field(
        description="Reference air-kerma rate for each mode named in tube.modes (mGy/min).")

    @model_validator(mode="after")
    def _positive_rates(self) -> ZoomLevel:
        for mode, rate in self.air_kerma_rate_mgy_per_min.items():
            if not rate > 0:
                raise ValueError(f"air_kerma_rate_mgy_per_min.{mode} must be greater than 0")
        return self


class Collimator(Section):
    min_opening_mm: float = Field(gt=0, description="Smallest blade opening, at the detector plane (mm).")
    step_mm: float = Field(gt=0, description="How far one open/close key press moves each blade pair, at the detector plane (mm).")


class Mode(Section):
    name: str = Field(min_length=1, description="Shown on screen and used as a key in the dose table, e.g. 'continuous', 'pulsed-15'.")
    pulse_rate_per_s: float | None = Field(None, gt=0, le=60, description="Pulses per second; omit for continuous fluoroscopy (1/s).")
    high_level_control: bool = Field(False, description="A high-level (boost) mode the operator holds a separate control "
                                     "for; its air-kerma rate may reach 176 mGy/min instead of 88 (21 CFR 1020.32(d)).")


class Tube(Section):
    kvp: float = Field(ge=40, le=150, description="Tube peak voltage (kV).")
    ma: float = Field(gt=0, le=100, description="Tube current during fluoroscopy (mA).")
    filtration_mm_al: float = Field(ge=0, le=20, description="Total filtration in aluminium equivalent (mm Al).")
    focal_spot_mm: float = Field(gt=0, le=3, description="Nominal focal spot size (mm).")
    pulse_width_ms: float = Field(gt=0, le=100, description="Exposure per pulse in pulsed modes (ms).")
    modes: list[Mode] = Field(min_length=1, description="Fluoroscopy modes offered by the console, first is the default.")

    @model_validator(mode="after")
    def _unique_modes(self) -> Tube:
        names = [m.name for m in self.modes]
        if len(set(names)) != len(names):
            raise ValueError(f"modes: names must be unique, got {names}")
        return self


class Dose(Section):
    reference_point_from_isocentre_mm: float = Field(
        150.0, ge=0, description="Patient entrance reference point, toward the source from the isocentre (mm; IEC 60601-2-43 uses 150).")
    alarm_period_s: float = Field(300.0, ge=limits.MIN_ALARM_PERIOD_S, le=limits.MAX_ALARM_PERIOD_S,
                                  description="Cumulative fluoroscopy time between audible alarms (s; 21 CFR 1020.32 "
                                              "allows at most 300; below 10 s the alarm would never stop).")


class Display(Section):
    window: float = Field(gt=0, description="Display window width on the log-attenuation image (dimensionless, line-integral units).")
    level: float = Field(description="Display window centre on the log-attenuation image (dimensionless); "
                                     "while abc is enabled the measured attenuation takes its place.")
    invert: bool = Field(False, description="Start with bone dark instead of bright.")
    noise: bool = Field(True, description="Add quantum noise set by mA and pulse width.")


class CurvePoint(Section):
    """One operating point of the exposure control's kV-mA curve."""

    kvp: float = Field(ge=40, le=150, description="Tube peak voltage at this point (kV).")
    ma: float = Field(gt=0, le=100, description="Tube current at this point (mA); in pulsed modes the current during "
                                                "the pulse, scaled like the reference technique's.")


class AutomaticBrightness(Section):
    """Automatic brightness (dose-rate) control. The unit measures the detector signal over the
    central half of the beam and sets the technique so that the image there is as bright as for
    the reference patient at the reference technique (tube.kvp, tube.ma): a thicker or denser
    part (a lateral view, contrast in the field) costs more dose, a thinner one less.

    Without a `curve` only the tube current follows the patient (the tube voltage stays at
    tube.kvp). With one, the generator moves along it as a real unit's does: from its first point
    (low kV, low mA: the most contrast for thin parts) toward its last, kV and mA rising together,
    to the first point that gives the reference signal; the dose-rate limit stops it earlier."""

    enabled: bool = Field(False, description="Off: fixed technique at the reference rates and the display's fixed level.")
    reference_attenuation: float = Field(3.0, gt=0, le=20, description="Median log-attenuation -ln(I/I0) over the "
                                         "measuring field at which the zoom levels' reference air-kerma rates apply "
                                         "(dimensionless; 3 is about 13 cm of water at 75 kVp).")
    min_factor: float = Field(0.1, gt=0, le=1, description="Lowest tube output the control can set, relative to the "
                              "reference (dimensionless).")
    max_factor: float = Field(8.0, ge=1, le=100, description="Highest tube output the control can set, relative to the "
                              "reference; keep max_factor x the highest reference rate within the unit's legal limit "
                              "(88 mGy/min in normal mode, 21 CFR 1020.32) (dimensionless).")
    curve: list[CurvePoint] = Field(default_factory=list, description="The generator's kV-mA operating curve, lowest "
                                    "point first (kV and mA each rising along it); empty: kV fixed at tube.kvp. With a "
                                    "curve, its ends bound the output instead of min_factor and max_factor.")



class Webcam(Section):
    T_xray_from_webcam: RigidTransform = Field(IDENTITY, description="Pose of the webcam in the X-ray frame "
                                                                     "(4x4, mm), from `fluorosim calibrate xray`.")
    status: Literal["nominal", "calibrated"] = Field("nominal", description="'nominal' until measured.")


class FluoroscopeProfile(Section):
    name: str = Field(min_length=1, description="Shown on screen and recorded with each session.")
    manufacturer: str = Field("", description="Recorded in DICOM exports.")
    model: str = Field("", description="Recorded in DICOM exports.")
    detector: Detector
    geometry: Geometry
    intrinsics: Intrinsics
    zoom_levels: list[ZoomLevel] = Field(min_length=4, max_length=4, description="Four fields of view, widest first.")
    collimator: Collimator
    tube: Tube
    dose: Dose = Field(default_factory=Dose)
    display: Display
    abc: AutomaticBrightness = Field(default_factory=AutomaticBrightness)
    image: ImageChain = Field(default_factory=ImageChain, description="Detector blur, glare, lag and display characteristic.")
    ct_sampling: CtSampling = Field(default_factory=CtSampling, description="How rays sample the CT's voxels.")
    energy_nodes: EnergyNodes = Field(default_factory=EnergyNodes, description="The energies the spectrum sum is "
                                      "evaluated at, fitted to the whole spectrum within a stated error.")
    webcam: Webcam = Field(default_factory=Webcam)

    def problems(self) -> Findings:
        """Checks across fields, as (location, message) pairs so errors point at the right line."""
        yield from self._physical_problems()
        fovs = [z.fov_mm for z in self.zoom_levels]
        for i in range(1, len(fovs)):
            if not fovs[i] < fovs[i - 1]:
                yield (("zoom_levels", i, "fov_mm"),
                       f"must be less than zoom_levels[{i - 1}].fov_mm ({fovs[i - 1]} mm): zoom levels go from widest "
                       f"to narrowest")
        widest = max(self.detector.columns, self.detector.rows) * self.detector.pixel_pitch_mm
        if fovs[0] > widest * 1.0001:
            yield ("zoom_levels", 0, "fov_mm"), f"{fovs[0]} mm exceeds the detector ({widest:.1f} mm = pixels x pixel_pitch_mm)"
        modes = {m.name for m in self.tube.modes}
        for i, z in enumerate(self.zoom_levels):
            if set(z.air_kerma_rate_mgy_per_min) != modes:
                yield (("zoom_levels", i, "air_kerma_rate_mgy_per_min"),
                       f"must give a rate for each of tube.modes {sorted(modes)}, got {sorted(z.air_kerma_rate_mgy_per_min)}")
        if self.dose.reference_point_from_isocentre_mm >= self.geometry.source_to_isocentre_mm:
            yield (("dose", "reference_point_from_isocentre_mm"),
                   "must be less than geometry.source_to_isocentre_mm: the reference point lies between source and isocentre")
        curve = self.abc.curve
        if len(curve) == 1:
            yield ("abc", "curve"), "give at least two points (kV and mA at its low and high ends), or none"
        for i in range(1, len(curve)):
            a, b = curve[i - 1], curve[i]
            if not (b.kvp >= a.kvp and b.ma >= a.ma and (b.kvp > a.kvp or b.ma > a.ma)):
                yield (("abc", "curve", i),
                       f"{b.kvp:g} kV {b.ma:g} mA falls below the point before it ({a.kvp:g} kV {a.ma:g} mA): the "
                       "curve rises in kV and mA from its first point")
        if self.collimator.min_opening_mm >= fovs[0]:
            yield ("collimator", "min_opening_mm"), "must be smaller than the widest field of view"

    def _physical_problems(self) -> Findings:
        """What no real machine can be: checked so a typo is refused, not simulated and recorded."""
        g, d, k = self.geometry, self.detector, self.intrinsics
        margin = g.source_to_image_mm - g.source_to_isocentre_mm
        if margin < limits.MIN_ISOCENTRE_TO_IMAGE_MM:
            yield (("geometry", "source_to_isocentre_mm"),
                   f"must be at least {limits.MIN_ISOCENTRE_TO_IMAGE_MM:g} mm less than source_to_image_mm "
                   f"({limits.fmt(g.source_to_image_mm)} mm): the patient lies between isocentre and detector")
        nominal = g.source_to_image_mm / d.pixel_pitch_mm
        r = limits.MAX_FOCAL_LENGTH_RATIO
        focal_ok = True
        for name, f in (("fx", k.fx), ("fy", k.fy)):
            if not nominal / r <= f <= nominal * r:
                focal_ok = False
                yield (("intrinsics", name),
                       f"{limits.fmt(f)} px is not a focal length this machine can have: SID / pixel pitch is "
                       f"{nominal:.0f} px, and a calibration stays within {nominal / r:.0f}..{nominal * r:.0f} px")
        for name, c, n in (("cx", k.cx, d.columns), ("cy", k.cy, d.rows)):
            if not -0.5 <= c <= n - 0.5:
                yield ("intrinsics", name), f"{limits.fmt(c)} px lies outside the detector (0..{n - 1} px)"
        if focal_ok:  # the corner's normalised radius needs a real focal length
            corner = float(np.hypot(d.columns / 2 / k.fx, d.rows / 2 / k.fy))
            dist = k.distortion
            radial = limits.corner_distortion(dist.k1, dist.k2, dist.k3, corner)
            if abs(radial) > limits.MAX_CORNER_DISTORTION:
                yield (("intrinsics", "distortion"),
                       f"k1, k2, k3 move the detector corner by {radial:+.0%}; a real intensifier's pincushion stays "
                       f"within {limits.MAX_CORNER_DISTORTION:.0%} (are these in OpenCV's normalised units?)")
            tangential = 2 * (abs(dist.p1) + abs(dist.p2)) * corner
            if tangential > limits.MAX_CORNER_TANGENTIAL:
                yield (("intrinsics", "distortion"),
                       f"p1, p2 move the detector corner by {tangential:.0%} of its radius; a real lens stays "
                       f"within {limits.MAX_CORNER_TANGENTIAL:.0%}")
        reach = g.source_to_image_mm + limits.WEBCAM_HOUSING_REACH_MM
        offset = float(np.linalg.norm(np.asarray(self.webcam.T_xray_from_webcam)[:3, 3]))
        if offset > reach:
            yield (("webcam", "T_xray_from_webcam"),
                   f"puts the webcam {limits.fmt(offset)} mm from the focal spot; on the intensifier housing it is "
                   f"within {reach:g} mm (SID + {limits.WEBCAM_HOUSING_REACH_MM:g} mm)")
        high = {m.name for m in self.tube.modes if m.high_level_control}
        boost = self.abc.max_factor if self.abc.enabled else 1.0
        # The exposure control never sets more than the image chain's dose-rate limit, so a
        # zoom's rate times max_factor may exceed the law where that limit keeps within it.
        ceiling = self.image.dose_rate_limit_mgy_per_min if self.abc.enabled else float("inf")
        limit_refused = self.abc.enabled and not high and ceiling > limits.MAX_AIR_KERMA_RATE_MGY_PER_MIN
        if limit_refused:
            yield (("image", "dose_rate_limit_mgy_per_min"),
                   f"{limits.fmt(ceiling)} mGy/min exceeds the federal limit of 88 mGy/min in normal mode "
                   "(21 CFR 1020.32(d)); 176 needs a mode with high_level_control")
        for i, z in enumerate(self.zoom_levels):
            for mode, rate in z.air_kerma_rate_mgy_per_min.items():
                cap = (limits.MAX_HIGH_LEVEL_AIR_KERMA_RATE_MGY_PER_MIN if mode in high
                       else limits.MAX_AIR_KERMA_RATE_MGY_PER_MIN)
                law = "176 mGy/min with high-level control" if mode in high else "88 mGy/min in normal mode"
                # (a refused limit is the one problem; each zoom's rate is then checked on its own)
                if rate > cap or (not limit_refused and min(rate * boost, ceiling) > cap):
                    why = f" x abc.max_factor {boost:g} = {rate * boost:g} mGy/min" if boost != 1.0 else " mGy/min"
                    yield (("zoom_levels", i, "air_kerma_rate_mgy_per_min", mode),
                           f"{limits.fmt(rate)}{why} exceeds the federal limit of {law} (21 CFR 1020.32(d))")

    def T_xray_from_webcam(self) -> np.ndarray:
        return matrix(self.webcam.T_xray_from_webcam)
