"""What photon statistics give a uniform slab's pixel SNR on a fluoroscope profile.

Worked from the profile's dose rates, the inverse-square law and spekpy's fluence per air
kerma, never from the detector model's own code: `fluorosim bench image` and the image-chain
tests hold the rendered noise against it.
"""

from __future__ import annotations

import math

import numpy as np

from ...config.fluoroscope import FluoroscopeProfile


def gaussian_noise_gain(sigma_px: float) -> float:
    """Sum of squared weights of the normalised sampled Gaussian of `sigma_px` (the factor a
    blur multiplies white noise's variance by), from its closed-form 1-D samples."""
    if sigma_px <= 0.3:
        return 1.0          # the detector skips blurs this small
    r = int(math.ceil(4 * sigma_px))
    x = np.arange(-r, r + 1, dtype=float)
    k = np.exp(-x * x / (2 * sigma_px * sigma_px))
    k /= k.sum()
    return float((k * k).sum() ** 2)


def expected_slab_snr(fl: FluoroscopeProfile, zoom: int, transmission: float, factor: float, mu_water_per_mm: float,
                      psf_sigma_px: float, settled: bool, kvp: float | None = None) -> float:
    """Pixel SNR that photon statistics give a uniform slab: sqrt(N) with N the photons per
    pixel per frame (profile rate -> air kerma per frame at the reference point -> inverse
    square to the detector -> spekpy fluence per air kerma behind the reference patient ->
    pixel area -> slab transmission x exposure factor), N raised by (1 + w)/(1 - w) for the
    settled recursive filter, the noise lowered by the point-spread and by glare's (1 - g).
    `kvp`: the tube voltage the exposure control set (None: tube.kvp); spekpy's own spectrum
    there gives the fluence per air kerma."""
    import spekpy

    mode = fl.tube.modes[0]
    rate = fl.zoom_levels[zoom - 1].air_kerma_rate_mgy_per_min[mode.name]
    fps = getattr(mode, "pulse_rate_per_s", None) or fl.image.frame_rate_per_s
    d_ref = fl.geometry.source_to_isocentre_mm - fl.dose.reference_point_from_isocentre_mm
    kerma_ugy = rate * 1000.0 / 60.0 / fps * (d_ref / fl.geometry.source_to_image_mm) ** 2
    s = spekpy.Spek(kvp=fl.tube.kvp if kvp is None else kvp, th=12.0, dk=0.5)
    s.filter("Al", fl.tube.filtration_mm_al)
    s.filter("Water, Liquid", fl.abc.reference_attenuation / mu_water_per_mm)
    per_mm2_per_ugy = s.get_flu() / s.get_kerma() / 100.0
    fovs = [z.fov_mm for z in fl.zoom_levels]
    pitch = fl.detector.pixel_pitch_mm * fovs[zoom - 1] / fovs[0]
    n = kerma_ugy * per_mm2_per_ugy * pitch * pitch * transmission * factor
    w = fl.image.recursive_weight
    if settled:
        n *= (1 + w) / (1 - w)
    g = fl.image.veiling_glare
    return math.sqrt(n) / math.sqrt(gaussian_noise_gain(psf_sigma_px)) / (1.0 - g)
