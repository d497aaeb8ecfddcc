"""The fluoroscope profile's `energy_nodes` section: the few energies the detector's spectrum
sum is evaluated at (appliance/xray/energy_nodes.py)."""

from __future__ import annotations

from pydantic import Field

from .base import Section


class EnergyNodes(Section):
    """A quadrature of the polychromatic detector signal: a subset of the spectrum's energy bins
    with weights fitted so that sum_k v_k exp(-mu(E_k) . L) matches the whole spectrum's sum
    over the material integrals L a patient presents, within max_relative_error."""

    enabled: bool = Field(
        True, description="Evaluate the spectrum sum at the fitted nodes; false: at every energy bin.")
    max_relative_error: float = Field(
        0.002, gt=0, le=0.05, description="Largest error the nodes may make in a ray's transmission I/I0, relative to "
        "the whole spectrum's sum, over the fitting ranges below (fraction). A fit that cannot reach it within "
        "max_nodes is not used: the frame sums every bin.")
    max_nodes: int = Field(
        12, ge=1, le=24, description="Most energies the quadrature may use (count; the spectrum has 24 bins).")
    min_transmission: float = Field(
        1e-5, gt=0, lt=1, description="Rays transmitting less than this fraction of the open beam are left out of the "
        "fit: a detector pixel behind them counts a few photons at most, far below the error bar (fraction).")
    air_max_g_per_cm2: float = Field(
        0.2, ge=0, le=10, description="Air (lungs, bowel gas) along a ray, as areal density, up to which the fit holds "
        "(g/cm^2; 1.6 m of air is 0.2).")
    soft_tissue_max_g_per_cm2: float = Field(
        45.0, gt=0, le=200, description="Soft tissue along a ray up to which the fit holds (g/cm^2; 45 is a large "
        "adult's lateral chest).")
    bone_max_g_per_cm2: float = Field(
        23.0, ge=0, le=100, description="Bone along a ray up to which the fit holds (g/cm^2; 23 is 12 cm of cortical "
        "bone, a lateral spine and both shoulders).")
    contrast_max_g_per_cm2: float = Field(
        4.0, ge=0, le=100, description="Iodinated contrast along a ray (grams of the water carrying the iodine) up to "
        "which the fit holds, at the case's concentration and every lower one the filling passes through (g/cm^2; 4 is "
        "a 4 cm vessel or chamber).")
