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
from dataclasses import dataclass

import numpy as np

from ..config.case import Contrast, Materials
from ..config.fluoroscope import Tube
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
    monoenergetic beam with the same aluminium half-value layer (spekpy's definition).
    """

    kvp: float
    filtration_mm_al: float
    energies_kev: np.ndarray
    photons_per_mm2_per_mas: np.ndarray
    effective_kev: float
    mean_kev: float

    def energy_weights(self) -> np.ndarray:
        """N0(E)*E normalised to sum 1: each bin's share of an energy-integrating detector's open-field signal."""
        w = self.photons_per_mm2_per_mas * self.energies_kev
        return w / w.sum()


@functools.lru_cache(maxsize=16)
def _spectrum(kvp: float, filtration_mm_al: float, n_bins: int) -> Spectrum:
    b = beam(kvp, ANODE_ANGLE_DEG, 0.5, (("Al", filtration_mm_al),))
    k, phi = b.energies_kev, b.photons_per_cm2_per_mas_per_kev   # keV, photons / cm^2 / mAs / keV at 1 m
    eff, mean = b.effective_kev, b.mean_kev
    dk = float(k[1] - k[0])
    counts = phi * dk / 100.0    # photons / mm^2 / mAs per fine bin
    # Equal-width coarse bins from the lowest energy carrying fluence to kVp.
    lo = float(k[np.argmax(counts > counts.max() * 1e-6)] - dk / 2)
    edges = np.linspace(lo, kvp, n_bins + 1)
    which = np.clip(np.searchsorted(edges, k, side="right") - 1, 0, n_bins - 1)
    n = np.bincount(which, weights=counts, minlength=n_bins)
    e_sum = np.bincount(which, weights=counts * k, minlength=n_bins)
    centres = np.where(n > 0, e_sum / np.maximum(n, 1e-300), (edges[:-1] + edges[1:]) / 2)
    keep = n > 0
    return Spectrum(kvp=kvp, filtration_mm_al=filtration_mm_al, energies_kev=centres[keep],
                    photons_per_mm2_per_mas=n[keep], effective_kev=eff, mean_kev=mean)


def tube_spectrum(tube: Tube, n_bins: int = 24) -> Spectrum:
    """The fluoroscope's spectrum in `n_bins` (>= 16) bins, each bin's energy its fluence-weighted mean."""
    return _spectrum(float(tube.kvp), float(tube.filtration_mm_al), int(n_bins))
