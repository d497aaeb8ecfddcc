"""Hounsfield units -> materials and densities; X-ray spectra and mass attenuation.

Four materials, decided per sample from the CT number (thresholds from the case profile):

    air          HU <= air_max_hu          density (1 + HU/1000) * water, at least 0
    soft tissue  air_max_hu < HU < bone_min_hu    the same line, (1 + HU/1000) * water
    bone         bone_min_hu <= HU (< contrast_min_hu)   linear from the soft-tissue value at
                 bone_min_hu to `bone_density_at_1000_hu_g_per_cm3` at 1000 HU
    contrast     HU >= contrast_min_hu     1 g/cm^3 of water carrying the case's iodine

Air and soft tissue share one density line, so interpolating HU across a skin or lung
boundary never creates a density step; only the mass attenuation changes at the threshold.

Mass attenuation coefficients (cm^2/g, total with coherent scattering) come from xraylib's
NIST compound tables; the tube spectrum from spekpy (kVp and aluminium filtration of the
fluoroscope profile). Nothing here is a hand-typed table.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..config.case import Contrast, Materials
from ..config.fluoroscope import Tube
from ..errors import FluorosimError
from .spekpy_beam import beam

#: Material order everywhere: kernel accumulators, attenuation tables.
MATERIAL_NAMES = ("air", "soft tissue", "bone", "contrast")
#: xraylib NIST compound names of the first three materials.
NIST_COMPOUNDS = ("Air, Dry (near sea level)", "Tissue, Soft (ICRP)", "Bone, Cortical (ICRP)")
WATER = "Water, Liquid"
IODINE_Z = 53
#: A threshold above any CT number, used when a case has no contrast.
NO_CONTRAST_HU = 32767.0
#: spekpy's default anode angle (degrees); fluoroscopy tubes sit at 10-12 degrees.
ANODE_ANGLE_DEG = 12.0
#: spekpy reports fluence at this distance from the focal spot (mm).
SPEKPY_DISTANCE_MM = 1000.0


@dataclass(frozen=True)
class DensityModel:
    """Piecewise-linear HU -> density (g/cm^3) per material, as the kernel evaluates it.

    density = offset[m] + slope[m] * HU for the material m that the thresholds pick.
    """

    air_max_hu: float
    bone_min_hu: float
    contrast_min_hu: float
    offset: tuple[float, float, float, float]
    slope: tuple[float, float, float, float]

    def material(self, hu: np.ndarray) -> np.ndarray:
        """Material index (see MATERIAL_NAMES) of each CT number."""
        hu = np.asarray(hu, dtype=np.float64)
        m = np.where(hu <= self.air_max_hu, 0, np.where(hu < self.bone_min_hu, 1, 2))
        return np.where(hu >= self.contrast_min_hu, 3, m)

    def density(self, hu: np.ndarray) -> np.ndarray:
        """Density (g/cm^3) of each CT number, never negative."""
        hu = np.asarray(hu, dtype=np.float64)
        m = self.material(hu)
        rho = np.asarray(self.offset)[m] + np.asarray(self.slope)[m] * hu
        return np.maximum(rho, 0.0)


def density_model(materials: Materials) -> DensityModel:
    water = 1.0
    soft_at_bone_min = water * (1.0 + materials.bone_min_hu / 1000.0)
    bone_slope = (materials.bone_density_at_1000_hu_g_per_cm3 - soft_at_bone_min) / (1000.0 - materials.bone_min_hu)
    bone_offset = soft_at_bone_min - bone_slope * materials.bone_min_hu
    contrast_min = NO_CONTRAST_HU if materials.contrast_min_hu is None else materials.contrast_min_hu
    return DensityModel(
        air_max_hu=materials.air_max_hu, bone_min_hu=materials.bone_min_hu, contrast_min_hu=contrast_min,
        offset=(water, water, bone_offset, water), slope=(water / 1000.0, water / 1000.0, bone_slope, 0.0))


def mass_attenuation(energies_kev, contrast: Contrast | None) -> np.ndarray:
    """(n_energies, 4) mass attenuation coefficients (cm^2/g) of MATERIAL_NAMES.

    The contrast column is per gram of the water that carries the iodine: water's own
    coefficient plus the iodine concentration (g/cm^3) times iodine's coefficient.
    """
    import xraylib

    out = np.zeros((len(energies_kev), 4))
    iodine_g_per_cm3 = 0.0 if contrast is None else contrast.concentration_mg_per_ml / 1000.0
    for i, e in enumerate(np.asarray(energies_kev, dtype=float)):
        for m, name in enumerate(NIST_COMPOUNDS):
            out[i, m] = xraylib.CS_Total_CP(name, float(e))
        out[i, 3] = xraylib.CS_Total_CP(WATER, float(e)) + iodine_g_per_cm3 * xraylib.CS_Total(IODINE_Z, float(e))
    return out


def water_mu_per_mm(energy_kev: float) -> float:
    """Linear attenuation of liquid water (1/mm) at one energy."""
    import xraylib

    return xraylib.CS_Total_CP(WATER, float(energy_kev)) * 1.0 / 10.0


@dataclass(frozen=True)
class Spectrum:
    """A tube spectrum in energy bins.

    `energies_kev` are bin centres; `photons_per_mm2_per_mas` the fluence of each bin at
    1 m from the focal spot (photons / mm^2 / mAs). `effective_kev` is the energy of the
    monoenergetic beam with the same aluminium half-value layer (spekpy's definition);
    `air_kerma_ugy_per_mas` the beam's air kerma at 1 m (uGy / mAs, spekpy's), which sets the
    dose rate of a technique.
    """

    kvp: float
    filtration_mm_al: float
    energies_kev: np.ndarray
    photons_per_mm2_per_mas: np.ndarray
    effective_kev: float
    mean_kev: float
    air_kerma_ugy_per_mas: float = float("nan")

    def detector_signal_per_mas(self) -> float:
        """An energy-integrating detector's open-field signal per mAs at 1 m (keV / mm^2 / mAs):
        what tells one kV's image brightness from another's at the same current."""
        return float(np.sum(self.photons_per_mm2_per_mas * self.energies_kev))

    def energy_weights(self) -> np.ndarray:
        """N0(E)*E normalised to sum 1: each bin's share of an energy-integrating detector's open-field signal."""
        w = self.photons_per_mm2_per_mas * self.energies_kev
        return w / w.sum()


@functools.lru_cache(maxsize=16)
def _fine_spectrum(kvp: float, filtration_mm_al: float) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """spekpy's spectrum in 0.5 keV steps (kept on disk by spekpy_beam): (keV, photons / mm^2 /
    mAs per step at 1 m, air kerma uGy / mAs at 1 m, effective keV, mean keV)."""
    b = beam(kvp, ANODE_ANGLE_DEG, 0.5, (("Al", filtration_mm_al),))
    k, phi = b.energies_kev, b.photons_per_cm2_per_mas_per_kev   # keV, photons / cm^2 / mAs / keV at 1 m
    dk = float(k[1] - k[0])
    return np.asarray(k, float), np.asarray(phi, float) * dk / 100.0, b.air_kerma_ugy_per_mas, b.effective_kev, b.mean_kev


def _binned(k: np.ndarray, counts: np.ndarray, kvp: float, filtration_mm_al: float, n_bins: int, eff: float,
            mean: float, kerma: float) -> Spectrum:
    """Equal-width coarse bins from the lowest energy carrying fluence to kVp, each at its
    fluence-weighted mean energy."""
    dk = float(k[1] - k[0])
    lo = float(k[np.argmax(counts > counts.max() * 1e-6)] - dk / 2)
    edges = np.linspace(lo, kvp, n_bins + 1)
    which = np.clip(np.searchsorted(edges, k, side="right") - 1, 0, n_bins - 1)
    n = np.bincount(which, weights=counts, minlength=n_bins)
    e_sum = np.bincount(which, weights=counts * k, minlength=n_bins)
    centres = np.where(n > 0, e_sum / np.maximum(n, 1e-300), (edges[:-1] + edges[1:]) / 2)
    keep = n > 0
    return Spectrum(kvp=kvp, filtration_mm_al=filtration_mm_al, energies_kev=centres[keep],
                    photons_per_mm2_per_mas=n[keep], effective_kev=eff, mean_kev=mean, air_kerma_ugy_per_mas=kerma)


@functools.lru_cache(maxsize=16)
def _spectrum(kvp: float, filtration_mm_al: float, n_bins: int) -> Spectrum:
    k, counts, kerma, eff, mean = _fine_spectrum(kvp, filtration_mm_al)
    return _binned(k, counts, kvp, filtration_mm_al, n_bins, eff, mean, kerma)


@functools.lru_cache(maxsize=8)
def _air_energy_absorption(energies_kev: tuple[float, ...]) -> np.ndarray:
    import xraylib

    return np.array([xraylib.CS_Energy_CP(NIST_COMPOUNDS[0], float(e)) for e in energies_kev])


@functools.lru_cache(maxsize=512)   # an exposure control's curve visits many kV values
def curve_spectrum(kvp: float, anchors_kvp: tuple[float, ...], filtration_mm_al: float, n_bins: int = 24) -> Spectrum:
    """The tube's spectrum at any `kvp` within `anchors_kvp` (the kV values of an exposure
    control's curve, where spekpy computes it: a second or more each, too slow for every kV of a
    control loop). Between two anchors a < kV <= b the shape is spekpy's at b scaled down by
    Kramers' law (a thick target's photons at energy E scale as kV - E, the filtration acting
    alike), and the air kerma per mAs is interpolated between spekpy's at a and b in log-log
    (a tube's output follows a power of kV), the fluence scaled to match. At each anchor the
    spectrum is spekpy's own. The effective energy (for monochromatic frames only) keeps b's
    ratio to the mean energy."""
    anchors = sorted(float(a) for a in anchors_kvp)
    if not anchors[0] <= kvp <= anchors[-1]:
        raise FluorosimError(f"{kvp:g} kV lies outside the exposure control's curve ({anchors[0]:g}-{anchors[-1]:g} kV)")
    b = next(x for x in anchors if x >= kvp)
    k, counts, kerma_b, eff, mean = _fine_spectrum(b, float(filtration_mm_al))
    if kvp == b:
        return _binned(k, counts, b, filtration_mm_al, n_bins, eff, mean, kerma_b)
    a = max(x for x in anchors if x < kvp)
    kerma_a = _fine_spectrum(a, float(filtration_mm_al))[2]
    t = math.log(kvp / a) / math.log(b / a)
    kerma = math.exp((1.0 - t) * math.log(kerma_a) + t * math.log(kerma_b))
    scaled = counts * np.where(k < kvp, (kvp - k) / np.maximum(b - k, 1e-9), 0.0)
    mu_en = _air_energy_absorption(tuple(k))
    scaled *= kerma / (kerma_b * float(np.sum(scaled * k * mu_en) / np.sum(counts * k * mu_en)))
    mean_kv = float(np.sum(scaled * k) / np.sum(scaled))
    return _binned(k, scaled, float(kvp), filtration_mm_al, n_bins, eff * mean_kv / mean, mean_kv, kerma)


def spectrum_at(kvp: float, filtration_mm_al: float, n_bins: int = 24) -> Spectrum:
    """spekpy's spectrum of a tube at `kvp` with that filtration, binned as tube_spectrum's."""
    return _spectrum(float(kvp), float(filtration_mm_al), int(n_bins))


def tube_spectrum(tube: Tube, n_bins: int = 24) -> Spectrum:
    """The fluoroscope's spectrum in `n_bins` (>= 16) bins, each bin's energy its fluence-weighted mean."""
    return _spectrum(float(tube.kvp), float(tube.filtration_mm_al), int(n_bins))
