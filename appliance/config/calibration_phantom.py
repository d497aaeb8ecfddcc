"""The two-plane sphere phantom that calibrates the X-ray machine, and how its images are read.

Sphere centres, diameters, line labels, the plates that hold them and the ArUco marker
glued to it are data, so a workshop can build a variant and describe it here without
touching code. `detection` and `acceptance` hold the tunable numbers of the pipeline in
`appliance/calibration/` (`fluorosim calibrate xray`).
"""

from __future__ import annotations

from collections import Counter
from typing import Literal

import numpy as np
from pydantic import Field

from .base import IDENTITY, Findings, RigidTransform, Section, matrix
from .phantom import ARUCO_DICTIONARIES


class Sphere(Section):
    id: int = Field(ge=0, description="Number engraved next to the sphere on the drawing.")
    line: str = Field(min_length=1, max_length=8, description="Label of the line segment the sphere belongs to (A, B, ...).")
    centre_mm: list[float] = Field(min_length=3, max_length=3, description="Sphere centre x, y, z in the phantom frame (mm).")
    diameter_mm: float = Field(gt=0, le=20, description="Ball diameter (mm).")


class Plate(Section):
    name: str = Field(min_length=1, description="Shown on the drawing.")
    centre_z_mm: float = Field(description="Mid-plane of the plate along phantom z (mm); the spheres of a layer sit in it.")
    thickness_mm: float = Field(gt=0, le=100, description="Plate thickness along z (mm).")
    length_mm: float = Field(gt=0, le=1000, description="Plate size along phantom x (mm), centred on the phantom origin.")
    width_mm: float = Field(gt=0, le=1000, description="Plate size along phantom y (mm), centred on the phantom origin.")


class AttachedMarker(Section):
    aruco_dictionary: str = Field(description="OpenCV predefined dictionary of the marker.")
    id: int = Field(ge=0, description="ArUco id printed on the marker.")
    size_mm: float = Field(gt=0, le=500, description="Printed side length of the black square (mm).")
    T_phantom_from_marker: RigidTransform = Field(
        IDENTITY, description="Marker centre and axes in the phantom frame (4x4, mm); marker z is its outward normal.")


class Materials(Section):
    sphere_hu: int = Field(30000, ge=1000, le=32767,
                           description="CT number given to the balls when the phantom is voxelised for the renderer "
                                       "(HU); steel is denser than any CT scale, so near the int16 top.")
    plate_hu: int = Field(120, ge=-1000, le=3000, description="CT number of the plates, PMMA is about +120 (HU).")


class Detection(Section):
    """Numbers that steer reading one X-ray image of the phantom."""

    min_diameter_px: float = Field(5.0, gt=1, description="Smallest sphere shadow searched for (pixels).")
    max_diameter_px: float = Field(60.0, gt=1, description="Largest sphere shadow searched for (pixels).")
    scales_per_octave: int = Field(4, ge=2, le=16, description="Scale-space samples per doubling of the blob size.")
    threshold_noise_sigmas: float = Field(
        8.0, gt=1, description="A blob must stand out of the image noise by this many robust standard deviations of the filter response.")
    max_axis_ratio: float = Field(3.0, ge=1, description="A blob whose response curves more than this many times "
                                                         "faster one way than the other is an edge, not a ball (ratio).")
    fov_margin_px: float = Field(4.0, ge=0, description="Blobs whose rim comes this close to the field-of-view edge "
                                                        "are dropped: a cut shadow has a biased centre (pixels).")
    line_tolerance_px: float = Field(6.0, gt=0, description="RANSAC: a blob centre this close to a line belongs to it (pixels).")
    ransac_iterations: int = Field(400, ge=10, le=100000, description="RANSAC: random pairs tried per line.")
    match_gate_fraction: float = Field(
        0.3, gt=0, lt=0.5, description="A predicted sphere matches the nearest blob only within this fraction of the "
                                       "projected grid spacing.")
    max_identification_median_px: float = Field(
        1.0, gt=0, description="A pairing is refused when, fitted alone with free focal lengths and k1, its median "
                               "residual exceeds this (pixels).")
    final_gate_px: float = Field(2.0, gt=0, description="After the fit, a detection farther than this from its "
                                                        "sphere's reprojection is an outlier (pixels).")


class FitOptions(Section):
    """How the camera model is fitted."""

    tangential: Literal["auto", "fit", "zero"] = Field(
        "auto", description="Decentring coefficients p1, p2: 'fit' always, 'zero' never, 'auto' only when they lower the "
                            "residuals significantly. For a narrow X-ray beam they trade almost one for one with the "
                            "principal point, so fitting them without need costs pixels of principal point.")
    tangential_significance: float = Field(
        0.01, gt=0, lt=0.5, description="'auto': keep p1, p2 when an F-test says the improvement has less than this chance (p-value).")


class Acceptance(Section):
    """The quality bar a fit must pass before anything is written into the fluoroscope profile."""

    min_spheres_per_image: int = Field(24, ge=6, description="Identified spheres an image needs to take part in the fit.")
    min_images: int = Field(3, ge=1, description="Accepted images needed to fit intrinsics and distortion.")
    max_rms_px: float = Field(0.5, gt=0, description="Largest reprojection RMS over all images (pixels).")
    max_residual_px: float = Field(1.5, gt=0, description="Largest single reprojection residual (pixels).")
    max_focal_uncertainty_percent: float = Field(0.5, gt=0, description="Largest one-sigma uncertainty of fx or fy (percent).")
    max_webcam_spread_mm: float = Field(
        3.0, gt=0, description="Each image's T_xray_from_webcam must lie this close to the average (mm); more means a "
                               "marker pose file belongs to another image.")
    max_webcam_spread_deg: float = Field(1.0, gt=0, description="The same for rotation (degrees).")


class CalibrationPhantomProfile(Section):
    name: str = Field(min_length=1, description="Shown in reports and on the drawing.")
    plates: list[Plate] = Field(min_length=1, description="The PMMA plates, one per sphere layer.")
    spheres: list[Sphere] = Field(min_length=8, description="Every metal ball, with its line label.")
    marker: AttachedMarker
    materials: Materials = Field(default_factory=Materials)
    detection: Detection = Field(default_factory=Detection)
    fit: FitOptions = Field(default_factory=FitOptions)
    acceptance: Acceptance = Field(default_factory=Acceptance)

    def problems(self) -> Findings:
        if self.marker.aruco_dictionary not in ARUCO_DICTIONARIES:
            yield ("marker", "aruco_dictionary"), f"must be one of {', '.join(ARUCO_DICTIONARIES)}"
        elif self.marker.id >= ARUCO_DICTIONARIES[self.marker.aruco_dictionary]:
            yield ("marker", "id"), f"{self.marker.id} is not in {self.marker.aruco_dictionary}"
        seen: dict[int, int] = {}
        for i, s in enumerate(self.spheres):
            if s.id in seen:
                yield ("spheres", i, "id"), f"duplicate sphere id {s.id} (also spheres[{seen[s.id]}])"
            seen.setdefault(s.id, i)
        if self.detection.min_diameter_px >= self.detection.max_diameter_px:
            yield ("detection", "min_diameter_px"), "must be less than max_diameter_px"
        diam = np.array([s.diameter_mm for s in self.spheres])
        if len(set(np.round(diam, 3))) != 2:
            yield ("spheres",), "needs exactly two ball diameters (large balls mark the reference lines)"
            return
        large = self.large_mask()
        z_large = {round(s.centre_mm[2], 3) for s, big in zip(self.spheres, large) if big}
        if len(z_large) != 1:
            yield ("spheres",), "the large balls must all lie in one layer (same z), the reference plane"
        lines = Counter(s.line for s, big in zip(self.spheres, large) if big)
        if len(lines) < 2 or min(lines.values()) < 3:
            yield ("spheres",), "the large balls must form at least two lines of at least three balls each"
        for label in lines:
            pts = self.centres()[[s.line == label for s in self.spheres]]
            if len(pts) >= 3:
                centred = pts - pts.mean(axis=0)
                off_line = np.linalg.svd(centred, compute_uv=False)[1:]
                if off_line.max() > 1e-6 * max(1.0, np.abs(centred).max()):
                    yield ("spheres",), f"the balls of line {label} are not collinear"
        for label in set(s.line for s in self.spheres):
            kinds = {big for s, big in zip(self.spheres, large) if s.line == label}
            if len(kinds) > 1:
                yield ("spheres",), f"line {label} mixes large and small balls"

    def centres(self) -> np.ndarray:
        """(n, 3) sphere centres in the phantom frame (mm)."""
        return np.array([s.centre_mm for s in self.spheres], dtype=np.float64)

    def diameters(self) -> np.ndarray:
        """(n,) ball diameters (mm)."""
        return np.array([s.diameter_mm for s in self.spheres], dtype=np.float64)

    def large_mask(self) -> np.ndarray:
        """True for the large balls."""
        d = self.diameters()
        return np.asarray(d > (d.min() + d.max()) / 2)

    def T_phantom_from_marker(self) -> np.ndarray:
        return matrix(self.marker.T_phantom_from_marker)


class MarkerPose(Section):
    """What the webcam saw of the phantom's marker when one X-ray image was taken."""

    T_webcam_from_marker: RigidTransform = Field(description="The marker's pose in the webcam frame (4x4, mm), as the tracker reports it.")

    def T(self) -> np.ndarray:
        return matrix(self.T_webcam_from_marker)
