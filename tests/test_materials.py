"""HU -> materials and densities; spectra from spekpy; attenuation from xraylib."""

import math

import numpy as np
import pytest
import xraylib

from appliance.config.case import Contrast, Materials
from appliance.config.fluoroscope import Tube
from appliance.patient.materials import density_model, mass_attenuation, tube_spectrum, water_mu_per_mm


def tube(kvp=75.0, al=4.5):
    return Tube(kvp=kvp, ma=2.0, filtration_mm_al=al, focal_spot_mm=0.6, pulse_width_ms=10, modes=[{"name": "c"}])


def test_density_model_by_hand():
    m = density_model(Materials(air_max_hu=-800, bone_min_hu=300, contrast_min_hu=2500,
                                bone_density_at_1000_hu_g_per_cm3=1.6))
    hu = np.array([-1024, -1000, -850, -800, -799, 0, 40, 299, 300, 1000, 2499, 2500, 3000])
    assert m.material(hu).tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 3, 3]
    rho = m.density(hu)
    np.testing.assert_allclose(rho[:8], [0, 0, 0.15, 0.2, 0.201, 1.0, 1.04, 1.299], atol=1e-12)
    # bone: 1.3 at 300 HU (continuous with soft tissue), 1.6 at 1000 HU, linear
    np.testing.assert_allclose(rho[8:11], [1.3, 1.6, 1.3 + 0.3 / 700 * 2199], atol=1e-12)
    np.testing.assert_allclose(rho[11:], [1.0, 1.0])


def test_no_contrast_means_no_contrast_material():
    m = density_model(Materials())
    assert m.material(np.array([3000, 30000])).tolist() == [2, 2]


def test_soft_tissue_attenuation_matches_nist_at_60_kev():
    # NIST XCOM, ICRP soft tissue, total with coherent, 60 keV: 0.2040 cm^2/g
    mu = mass_attenuation([60.0], None)
    assert mu[0, 1] == pytest.approx(0.2040, rel=0.02)
    assert mu[0, 2] > mu[0, 1] > 0      # cortical bone attenuates more per gram


def test_contrast_has_the_iodine_k_edge():
    c = Contrast(concentration_mg_per_ml=150)
    below, above = mass_attenuation([33.0, 33.4], c)[:, 3]
    assert above > 3 * below
    # 150 mg/mL iodine: the contrast column is water plus 0.15 g/cm^3 x iodine's coefficient
    assert above == pytest.approx(xraylib.CS_Total_CP("Water, Liquid", 33.4) + 0.15 * xraylib.CS_Total(53, 33.4))


def test_spectrum_bins_and_effective_energy_reproduce_the_half_value_layer():
    import spekpy

    s = tube_spectrum(tube(), 24)
    assert len(s.energies_kev) >= 16
    assert s.energies_kev.max() < 75 and s.energies_kev.min() > 5
    assert s.energy_weights().sum() == pytest.approx(1.0)
    ref = spekpy.Spek(kvp=75, th=12)
    ref.filter("Al", 4.5)
    hvl_cm = ref.get_hvl1() / 10.0
    # A monoenergetic beam at the effective energy is halved by one HVL of aluminium.
    mu_al = xraylib.CS_Total(13, s.effective_kev) * 2.699
    assert math.exp(-mu_al * hvl_cm) == pytest.approx(0.5, abs=0.02)
    # fluence per mAs at 1 m agrees with spekpy's own total (photons/cm^2 -> /mm^2)
    assert s.photons_per_mm2_per_mas.sum() == pytest.approx(ref.get_flu() / 100.0, rel=0.02)


def test_more_filtration_hardens_the_beam():
    assert tube_spectrum(tube(al=8.0)).effective_kev > tube_spectrum(tube(al=2.0)).effective_kev + 2


def test_water_mu():
    assert water_mu_per_mm(60.0) == pytest.approx(0.02059, rel=0.02)  # NIST: 0.2059 cm^2/g
