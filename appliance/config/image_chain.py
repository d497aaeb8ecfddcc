"""The fluoroscope's image chain after the X-ray physics: detector blur and glare, exposure
control, temporal filter and the display characteristic. Defaults are those of a typical
23 cm image-intensifier C-arm; the flat-detector profile sets its own."""

from __future__ import annotations

from pydantic import Field

from .base import Section


class ImageChain(Section):
    limiting_resolution_lp_per_mm: list[float] = Field(
        [1.4, 1.8, 2.3, 2.8], min_length=4, max_length=4,
        description="Limiting resolution at the detector's input plane for each zoom level, widest first (line pairs "
                    "per mm; where the detector's MTF falls to 4 %, the contrast at which bar patterns vanish). "
                    "The detector's point-spread is the Gaussian with that MTF.")
    veiling_glare: float = Field(
        0.10, ge=0, lt=1, description="Fraction of the signal scattered into a broad halo by the intensifier's "
                                      "output window and optics (dimensionless; 0 for a flat panel).")
    glare_sigma_mm: float = Field(
        25.0, gt=0, le=500, description="Spread of the veiling-glare halo, Gaussian sigma at the input plane (mm).")
    field_edge_mm: float = Field(
        3.0, ge=0, le=50, description="Width over which the image fades to black at the edge of the circular "
                                      "field or the collimator blades (mm at the input plane).")
    recursive_weight: float = Field(
        0.5, ge=0, lt=1, description="Recursive (temporal) filter: each shown frame is this fraction of the previous "
                                     "shown frame plus the rest of the new one (dimensionless; 0 = off).")
    frame_rate_per_s: float = Field(
        30.0, gt=0, le=120, description="Frames per second in continuous fluoroscopy (pulsed modes use their pulse "
                                        "rate) (1/s); sets the air kerma, hence the photons, in each frame.")
    unsharp_amount: float = Field(
        0.0, ge=0, le=5, description="Edge enhancement: weight of (image - blurred image) added back on the log "
                                     "image (dimensionless; 0 = off).")
    unsharp_sigma_mm: float = Field(
        2.0, gt=0, le=50, description="Blur of the edge enhancement's unsharp mask, Gaussian sigma at the input plane (mm).")
    dose_rate_limit_mgy_per_min: float = Field(
        88.0, gt=0, le=176, description="Highest air-kerma rate at the reference point the exposure control may set "
                                        "(mGy/min; 88 in normal mode, 176 with high-level control, 21 CFR 1020.32).")
    display_latitude: float = Field(
        1.15, ge=1, le=4, description="The display's window spans the in-field log signal between its 1st and 99th "
                                      "percentile times this (dimensionless): the video chain's latitude.")
    display_min_window: float = Field(
        1.0, gt=0, le=20, description="Narrowest automatic window on the log signal (dimensionless, ln units): the "
                                      "video chain's highest contrast gain, so a nearly uniform field is not "
                                      "stretched until its quantum mottle fills the grey scale.")
    display_knee: float = Field(
        0.15, ge=0, lt=0.5, description="Grey values within this of black or white are reached through a soft knee "
                                        "that never clips (fraction of the grey scale).")
    window_step: float = Field(
        1.25, gt=1, le=4, description="The window keys widen or narrow the display window by this ratio per press "
                                      "(dimensionless).")
    level_step: float = Field(
        0.05, gt=0, le=0.5, description="The level keys move the window centre by this fraction of its width per "
                                        "press (dimensionless).")
