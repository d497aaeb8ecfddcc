"""The spectrum sum at a few fitted energies (appliance/xray/energy_nodes.py), checked against
the sum over every bin at rays the fit never saw, against the closed-form transmission of a
tissue slab through spekpy's fine spectrum, and in the renderer's own kernel."""

from pathlib import Path

import numpy as np
import pytest
import spekpy
import xraylib

from appliance.config.case import Contrast, Materials
from appliance.config.energy_nodes import EnergyNodes
from appliance.config.fluoroscope import FluoroscopeProfile
from appliance.config.loading import load_profile
from appliance.config.yamlfile import ProfileProblems
from appliance.geometry import make_transform
from appliance.patient.materials import mass_attenuation, spectrum_at
from appliance.xray.energy_nodes import fit_nodes
from appliance.xray.renderer import Renderer, View, at_resolution
from appliance.xray.truth.analytic import box_volume

CONFIGS = Path(__file__).resolve().parents[1] / "configs" / "fluoroscopes"
IODINE = Contrast(concentration_mg_per_ml=150)
LIMITS = EnergyNodes()


def tables(kvp, factor=1.0):
    """The binned spectrum's weights and the materials' mass attenuation at `factor` of the case's iodine."""
    sp = spectrum_at(kvp, 3.0, 24)
    contrast = None if factor == 0 else Contrast(concentration_mg_per_ml=IODINE.concentration_mg_per_ml * factor)
    return sp, sp.energy_weights(), mass_attenuation(sp.energies_kev, contrast)


def quadrature(kvp):
    sp, w, _ = tables(kvp)
    return fit_nodes(w, [tables(kvp, f)[2] for f in (0.0, 0.5, 1.0)], LIMITS)


def whole_and_nodes(kvp, factor, rays):
    """I/I0 of `rays` (n, 4; g/cm^3 * mm) summed over every bin, and over the fitted nodes."""
    _, w, mu = tables(kvp, factor)
    q = quadrature(kvp)
    whole = np.exp(-0.1 * rays @ mu.T) @ w
    nodes = np.exp(-0.1 * rays @ mu[q.bins].T) @ q.weights.astype(float)
    return whole, nodes


@pytest.mark.parametrize("kvp", [60.0, 85.0, 110.0])
def test_nodes_keep_every_ray_within_the_bound_at_concentrations_the_fit_never_saw(kvp):
    q = quadrature(kvp)
    assert q is not None and len(q.bins) <= 10       # the cut is real: under half the 24 bins
    top = 10.0 * np.array([LIMITS.air_max_g_per_cm2, LIMITS.soft_tissue_max_g_per_cm2, LIMITS.bone_max_g_per_cm2,
                           LIMITS.contrast_max_g_per_cm2])
    rays = np.random.default_rng(1234).uniform(0.0, 1.0, (4000, 4)) * top
    for factor in (0.3, 0.8, 1.0):
        whole, nodes = whole_and_nodes(kvp, factor, rays)
        seen = whole >= LIMITS.min_transmission
        assert seen.sum() > 1000
        assert np.abs(nodes[seen] / whole[seen] - 1.0).max() <= LIMITS.max_relative_error
    whole, nodes = whole_and_nodes(kvp, 1.0, np.zeros((1, 4)))
    assert nodes[0] == pytest.approx(1.0, abs=1e-6)        # the open beam reads 1


def test_nodes_follow_the_closed_form_transmission_of_a_tissue_slab():
    """T(t) = sum phi(E) E exp(-mu(E) t) / sum phi(E) E over spekpy's 0.5 keV spectrum (70 kV, 6 mm
    Al, as generic-flat-detector), for soft tissue 0-40 cm: the nodes add at most their bound to
    what the 24 bins make of it."""
    ref = spekpy.Spek(kvp=70, th=12)
    ref.filter("Al", 6.0)
    k, phi = ref.get_spectrum()
    mu_fine = np.array([xraylib.CS_Total_CP("Tissue, Soft (ICRP)", float(e)) for e in k]) / 10.0   # 1/mm at 1 g/cm^3
    sp = spectrum_at(70.0, 6.0, 24)
    w = sp.energy_weights()
    mus = [mass_attenuation(sp.energies_kev, None if f == 0 else Contrast(concentration_mg_per_ml=150 * f))
           for f in (0.0, 0.5, 1.0)]
    q = fit_nodes(w, mus, LIMITS)
    assert q is not None
    for t in (10.0, 50.0, 100.0, 200.0, 300.0, 400.0):
        closed = float(np.sum(phi * k * np.exp(-mu_fine * t)) / np.sum(phi * k))
        binned = float(w @ np.exp(-0.1 * t * mus[2][:, 1]))
        nodes = float(q.weights.astype(float) @ np.exp(-0.1 * t * mus[2][q.bins, 1]))
        assert abs(nodes / binned - 1.0) <= LIMITS.max_relative_error
        assert abs(nodes / closed - 1.0) <= abs(binned / closed - 1.0) + LIMITS.max_relative_error
        assert abs(binned / closed - 1.0) < 0.02, t


def test_the_kernel_sums_the_nodes_and_matches_every_bin():
    """A 40 mm bone-and-tissue slab through the renderer: nodes on and off agree within the bound,
    and the device sums under half the bins."""
    base = at_resolution(load_profile(CONFIGS / "generic-flat-detector.yaml", FluoroscopeProfile), 64, 64)
    off = base.model_copy(update={"energy_nodes": EnergyNodes(enabled=False)})
    vol, _, _ = box_volume((16, 32, 32), (6.0, 6.0, 2.5), (0, 0, 0), (31, 31, 15), hu=700)
    pose = make_transform(np.eye(3), [0.0, 0.0, 750.0])
    view = View(quantity="intensity", noise=False)
    images = []
    for fl in (base, off):
        r = Renderer(fl, Materials(), device="cpu")
        images.append(r.render(r.prepare(vol), pose, view).image)
        images.append(r.caster.tables().device_bins)
        # Another matrix of the same fluoroscope fits nothing again: the process keeps the fit.
        assert r.at_matrix(32, 32).caster.tables().quadrature is r.caster.tables().quadrature
    on_img, on_bins, off_img, off_bins = images
    assert off_bins == 24 and on_bins <= 10
    inside = off_img > 0
    assert inside.sum() > 1000 and 0.01 < float(np.median(off_img[inside])) < 0.9
    assert np.abs(on_img[inside] / off_img[inside] - 1.0).max() <= LIMITS.max_relative_error


def test_a_node_count_out_of_range_is_refused_with_its_line(tmp_path):
    good = (CONFIGS / "generic-flat-detector.yaml").read_text()
    assert "  max_nodes: 12 " in good
    text = good.replace("  max_nodes: 12 ", "  max_nodes: 30 ", 1)
    line = text[:text.index("  max_nodes: 30")].count("\n") + 1
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ProfileProblems) as err:
        load_profile(bad, FluoroscopeProfile)
    message = str(err.value)
    assert "energy_nodes.max_nodes" in message and f"bad.yaml:{line}" in message


def test_a_display_frame_fits_nodes_only_at_the_kv_its_exposure_control_chose(monkeypatch):
    """The control's kV search reads many kV values on the host; only the image's kV is fitted."""
    import appliance.xray.energy_nodes as energy_nodes

    monkeypatch.setattr(energy_nodes, "_FITS", {})
    fl = at_resolution(load_profile(CONFIGS / "generic-flat-detector.yaml", FluoroscopeProfile), 48, 48)
    assert fl.abc.enabled and len(fl.abc.curve) > 1
    r = Renderer(fl, Materials(), device="cpu")
    vol, _, _ = box_volume((16, 32, 32), (6.0, 6.0, 2.5), (0, 0, 0), (31, 31, 15), hu=700)
    frame = r.render(r.prepare(vol), make_transform(np.eye(3), [0.0, 0.0, 750.0]), View(noise=False))
    assert frame.kvp is not None and frame.kvp != fl.tube.kvp       # the search left the reference kV
    assert len(energy_nodes._FITS) == 1
    assert r.caster.tables(frame.kvp, None, True).quadrature is not None


def test_a_live_renderer_sums_every_bin_until_its_side_thread_has_fitted_the_kv(monkeypatch):
    """A live frame at a kV met for the first time does not wait for the fit: it is the exact sum
    over all 24 bins; once the side thread's fit has come, the same kV is summed at the nodes,
    within the fit's bound of the exact image."""
    import appliance.xray.energy_nodes as energy_nodes

    monkeypatch.setattr(energy_nodes, "_FITS", {})
    base = at_resolution(load_profile(CONFIGS / "generic-flat-detector.yaml", FluoroscopeProfile), 48, 48)
    exact = Renderer(base.model_copy(update={"energy_nodes": EnergyNodes(enabled=False)}), Materials(), device="cpu")
    live = Renderer(base, Materials(), device="cpu")
    live.caster.fit_in_background = True
    assert live.at_matrix(32, 32).caster.fit_in_background      # the moving matrices are live too
    vol, _, _ = box_volume((16, 32, 32), (6.0, 6.0, 2.5), (0, 0, 0), (31, 31, 15), hu=700)
    pose = make_transform(np.eye(3), [0.0, 0.0, 750.0])
    view = View(quantity="intensity", noise=False)
    truth = exact.render(exact.prepare(vol), pose, view).image
    prepared = live.prepare(vol)
    first = live.render(prepared, pose, view).image
    kv = float(base.tube.kvp)
    assert live.caster.tables().device_bins == 24 and live.caster.tables().quadrature is None
    np.testing.assert_allclose(first, truth, rtol=1e-5, atol=1e-7)
    live.caster._fitting[kv].result(timeout=60)                  # the side thread's fit, done
    later = live.render(prepared, pose, view).image
    tables = live.caster.tables()
    assert tables.quadrature is not None and tables.device_bins <= 10 and not tables.awaiting_nodes
    inside = truth > 0
    assert inside.sum() > 500
    assert np.abs(later[inside] / truth[inside] - 1.0).max() <= LIMITS.max_relative_error
    assert np.abs(later[inside] / truth[inside] - 1.0).max() > 0.0     # the nodes, not the bins


def test_lawsons_rounds_reach_the_minimax_weights_of_two_bins():
    """Two bins, the open beam holding v1 + v2 = 1, so each row's error is linear in t = v1:
    e0 = 1.3 t + 0.9 (1 - t) - 1 = 0.4 t - 0.1 rises and e1 = 0.8 t + 1.02 (1 - t) - 1 =
    0.02 - 0.22 t falls; the others stay smaller in between. The largest error is least where
    e0 = e1: t = 0.12 / 0.62 = 6/31, |e| = 0.7/31 = 0.02258 (the least-squares weights give
    0.0253)."""
    from appliance.xray.energy_nodes import MINIMAX_ROUNDS, _minimax

    terms = np.array([[1.3, 0.9], [0.8, 1.02], [1.0, 1.0], [1.05, 0.99], [0.9, 1.01]])
    err, v = _minimax(terms, MINIMAX_ROUNDS)
    assert err == pytest.approx(0.7 / 31, abs=1e-5)
    np.testing.assert_allclose(v, [6 / 31, 25 / 31], atol=1e-4)
    assert err == pytest.approx(float(np.abs(terms @ v - 1.0).max()), abs=1e-12)


def test_a_bound_no_quadrature_of_max_nodes_reaches_sums_every_bin():
    """One node cannot follow the beam's hardening: for every bin e alone (weight 1, the open
    beam exact) the ratio exp(-0.1 mu_e . L) / T(L) over the profile's soft-tissue range, worked
    here ray by ray, strays far beyond the 0.2 % bound. So at max_nodes 1 there is no fit (even
    after the default limits' fit of the same spectrum), and the renderer sums all 24 bins:
    its image is the exact one."""
    sp, w, mu = tables(70.0)
    mus = [tables(70.0, f)[2] for f in (0.0, 0.5, 1.0)]
    one = EnergyNodes(max_nodes=1)
    soft = np.zeros((50, 4))
    soft[:, 1] = np.linspace(0.0, 10.0 * one.soft_tissue_max_g_per_cm2, 50)
    whole = np.exp(-0.1 * soft @ mu.T) @ w
    seen = whole >= one.min_transmission
    for e in range(len(w)):
        assert np.abs(np.exp(-0.1 * soft[seen] @ mu[e]) / whole[seen] - 1.0).max() > 10 * one.max_relative_error
    q = fit_nodes(w, mus, LIMITS)
    assert q is not None and (q.weights >= 0).all() and len(q.bins) <= LIMITS.max_nodes
    assert fit_nodes(w, mus, one) is None
    base = at_resolution(load_profile(CONFIGS / "generic-flat-detector.yaml", FluoroscopeProfile), 32, 32)
    base = base.model_copy(update={"abc": base.abc.model_copy(update={"enabled": False})})
    vol, _, _ = box_volume((16, 32, 32), (6.0, 6.0, 2.5), (0, 0, 0), (31, 31, 15), hu=700)
    pose = make_transform(np.eye(3), [0.0, 0.0, 750.0])
    view = View(quantity="intensity", noise=False)
    images = []
    for limits in (one, EnergyNodes(enabled=False)):
        r = Renderer(base.model_copy(update={"energy_nodes": limits}), Materials(), device="cpu")
        images.append(r.render(r.prepare(vol), pose, view).image)
        assert r.caster.tables().device_bins == 24 and r.caster.tables().quadrature is None
    assert images[0].max() > 0.01
    np.testing.assert_array_equal(images[0], images[1])


def test_a_side_threads_fit_is_kept_for_the_process(monkeypatch):
    """fit_soon's result is fit_nodes's own: once it has come, the same spectrum and tables are
    not fitted again (another matrix's renderer takes the same object)."""
    import appliance.xray.energy_nodes as energy_nodes

    monkeypatch.setattr(energy_nodes, "_FITS", {})
    _, w, _ = tables(85.0)
    mus = [tables(85.0, f)[2] for f in (0.0, 0.5, 1.0)]
    q = energy_nodes.fit_soon(w, mus, LIMITS).result(timeout=60)
    assert q is not None and len(energy_nodes._FITS) == 1
    assert energy_nodes.fit_nodes(w, mus, LIMITS) is q
    # Another kV's fit beside it does not push it out (the process keeps up to 256).
    _, w60, _ = tables(60.0)
    assert energy_nodes.fit_nodes(w60, [tables(60.0, f)[2] for f in (0.0, 0.5, 1.0)], LIMITS) is not None
    assert len(energy_nodes._FITS) == 2 and energy_nodes.fit_nodes(w, mus, LIMITS) is q


def test_a_renderer_with_contrast_fits_its_nodes_to_the_iodine_too():
    """A renderer of a case with 150 mg/ml iodine: its nodes keep rays of iodinated contrast (up
    to the profile's 4 g/cm^2, in 10 cm of soft tissue) within the bound of the every-bin sum
    worked here from the mass attenuation tables, at the case's concentration and half of it."""
    fl = at_resolution(load_profile(CONFIGS / "generic-flat-detector.yaml", FluoroscopeProfile), 32, 32)
    r = Renderer(fl, Materials(), contrast=IODINE, device="cpu")
    q = r.caster.tables().quadrature
    assert q is not None
    rays = np.zeros((200, 4))
    rays[:, 1] = 100.0                                            # 10 cm of soft tissue
    rays[:, 3] = np.linspace(0.0, 10.0 * LIMITS.contrast_max_g_per_cm2, 200)
    sp = r.caster.tables().spectrum
    w = sp.energy_weights()
    for factor in (0.5, 1.0):
        mu = mass_attenuation(sp.energies_kev, Contrast(concentration_mg_per_ml=IODINE.concentration_mg_per_ml * factor))
        whole = np.exp(-0.1 * rays @ mu.T) @ w
        nodes = np.exp(-0.1 * rays @ mu[q.bins].T) @ q.weights.astype(float)
        assert whole.min() >= LIMITS.min_transmission
        assert np.abs(nodes / whole - 1.0).max() <= LIMITS.max_relative_error
