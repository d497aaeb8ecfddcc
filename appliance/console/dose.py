"""Dose model of the simulated fluoroscope: reference air kerma and dose-area product.

The profile gives the reference air-kerma rate (mGy/min) at the patient entrance reference
point for each zoom level and mode (IEC 60601-2-43: 15 cm from the isocentre toward the
source). Continuous fluoroscopy accrues that rate over time; a pulsed mode delivers the same
mean rate as equal pulses, rate / 60 / pulse_rate mGy each. The dose-area product is the
air kerma times the collimated field area at the reference point: the blades are set at the
detector plane, so the area scales by (d_ref / SID)^2, and on an image intensifier the field
is the collimator rectangle clipped by the circular input field.
"""

from __future__ import annotations

import math

from ..config.fluoroscope import FluoroscopeProfile


def reference_distance_mm(fl: FluoroscopeProfile) -> float:
    """Focal spot to the reference point (mm)."""
    return fl.geometry.source_to_isocentre_mm - fl.dose.reference_point_from_isocentre_mm


def _circle_strip(x: float, r: float) -> float:
    """Integral of sqrt(r^2 - u^2) du from 0 to x, for 0 <= x <= r."""
    return 0.5 * (x * math.sqrt(max(r * r - x * x, 0.0)) + r * r * math.asin(min(x / r, 1.0)))


def rectangle_in_circle_area(width: float, height: float, diameter: float) -> float:
    """Area of a centred width x height rectangle clipped by a centred circle (same units squared)."""
    r = diameter / 2.0
    a, b = min(width / 2.0, r), min(height / 2.0, r)
    # For |x| < xb the circle is taller than the rectangle, so the rectangle's edge bounds it.
    xb = math.sqrt(r * r - b * b)
    inner = min(a, xb)
    quarter = b * inner + (_circle_strip(a, r) - _circle_strip(inner, r) if a > xb else 0.0)
    return 4.0 * quarter


def field_area_detector_mm2(fl: FluoroscopeProfile, zoom: int, collimation_mm: tuple[float, float]) -> float:
    """Irradiated field at the detector plane (mm^2) for zoom level 1..4 and blade openings (h, v)."""
    fov = fl.zoom_levels[zoom - 1].fov_mm
    h, v = min(collimation_mm[0], fov), min(collimation_mm[1], fov)
    if fl.detector.kind == "image_intensifier":
        return rectangle_in_circle_area(h, v, fov)
    return h * v


def field_area_reference_cm2(fl: FluoroscopeProfile, zoom: int, collimation_mm: tuple[float, float]) -> float:
    """Collimated field area at the reference point (cm^2)."""
    scale = reference_distance_mm(fl) / fl.geometry.source_to_image_mm
    return field_area_detector_mm2(fl, zoom, collimation_mm) * scale * scale / 100.0


def air_kerma_rate_mgy_per_min(fl: FluoroscopeProfile, zoom: int, mode: str) -> float:
    return fl.zoom_levels[zoom - 1].air_kerma_rate_mgy_per_min[mode]


def kerma_per_pulse_mgy(rate_mgy_per_min: float, pulse_rate_per_s: float) -> float:
    """Air kerma of one pulse when pulses at `pulse_rate_per_s` deliver `rate_mgy_per_min` (mGy)."""
    return rate_mgy_per_min / 60.0 / pulse_rate_per_s


def dap_gy_cm2(air_kerma_mgy: float, area_cm2: float) -> float:
    """Dose-area product (Gy cm^2) of an air kerma (mGy) over a field (cm^2)."""
    return air_kerma_mgy / 1000.0 * area_cm2
