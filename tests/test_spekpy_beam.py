"""spekpy's beams kept on disk: the figures read back are spekpy's own, bit for bit, and a
process with a warm cache never imports spekpy."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from appliance.errors import FluorosimError
from appliance.patient import spekpy_beam
from appliance.patient.spekpy_beam import beam

REPO = Path(__file__).resolve().parents[1]
SETTINGS = (70.0, 12.0, 0.5, (("Al", 3.0),))


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FLUOROSIM_CACHE_DIR", str(tmp_path / "cache"))
    beam.cache_clear()
    yield tmp_path / "cache"
    beam.cache_clear()


def test_the_cached_beam_is_spekpys_own_and_is_read_back_without_modelling(cache, monkeypatch):
    import spekpy

    fresh = beam(*SETTINGS)
    (stored,) = (cache / "spekpy").glob("beam-*.npz")
    s = spekpy.Spek(kvp=70.0, th=12.0, dk=0.5)
    s.filter("Al", 3.0)
    k, phi = s.get_spectrum()
    np.testing.assert_array_equal(fresh.energies_kev, k)
    np.testing.assert_array_equal(fresh.photons_per_cm2_per_mas_per_kev, phi)
    assert (fresh.effective_kev, fresh.mean_kev) == (s.get_eeff(), s.get_emean())
    assert (fresh.fluence_per_cm2_per_mas, fresh.air_kerma_ugy_per_mas) == (s.get_flu(), s.get_kerma())

    def no_modelling(*args):
        raise AssertionError("modelled again although the cache holds the beam")

    monkeypatch.setattr(spekpy_beam, "_model", no_modelling)
    beam.cache_clear()
    again = beam(*SETTINGS)
    np.testing.assert_array_equal(again.photons_per_cm2_per_mas_per_kev, phi)
    assert again.effective_kev == fresh.effective_kev and again.air_kerma_ugy_per_mas == fresh.air_kerma_ugy_per_mas
    # Other settings are another beam, never the stored one.
    with pytest.raises(AssertionError, match="modelled again"):
        beam(70.0, 12.0, 0.5, (("Al", 3.5),))
    assert stored.is_file()


def test_a_damaged_or_unwritable_cache_only_costs_the_time(cache, tmp_path, monkeypatch):
    fresh = beam(*SETTINGS)
    (stored,) = (cache / "spekpy").glob("beam-*.npz")
    stored.write_bytes(stored.read_bytes()[:100])           # cut short, as by a power loss
    beam.cache_clear()
    again = beam(*SETTINGS)
    np.testing.assert_array_equal(again.photons_per_cm2_per_mas_per_kev, fresh.photons_per_cm2_per_mas_per_kev)
    with np.load(stored) as f:                                # written again, whole
        np.testing.assert_array_equal(f["phi"], fresh.photons_per_cm2_per_mas_per_kev)
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    monkeypatch.setenv("FLUOROSIM_CACHE_DIR", str(blocked))
    beam.cache_clear()
    assert beam(*SETTINGS).effective_kev == fresh.effective_kev
    assert blocked.read_text() == "not a folder"


def test_out_of_range_settings_are_one_clear_error(cache):
    with pytest.raises(FluorosimError, match="1000.0 kVp tube.*check tube.kvp"):
        beam(1000.0, 12.0, 0.5, ())
    assert not list(cache.glob("**/*.npz"))


def test_cache_folder_follows_systemd_then_xdg(monkeypatch, tmp_path):
    for var in ("FLUOROSIM_CACHE_DIR", "CACHE_DIRECTORY", "XDG_CACHE_HOME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert spekpy_beam.cache_dir() == tmp_path / ".cache" / "fluorosim"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert spekpy_beam.cache_dir() == tmp_path / "xdg" / "fluorosim"
    monkeypatch.setenv("CACHE_DIRECTORY", "/var/cache/fluorosim")
    assert spekpy_beam.cache_dir() == Path("/var/cache/fluorosim")
    monkeypatch.setenv("FLUOROSIM_CACHE_DIR", str(tmp_path / "mine"))
    assert spekpy_beam.cache_dir() == tmp_path / "mine"


def test_a_process_with_a_warm_cache_never_imports_spekpy(cache):
    code = ("import sys, types; from appliance.patient.materials import tube_spectrum; "
            "s = tube_spectrum(types.SimpleNamespace(kvp=70.0, filtration_mm_al=3.0)); "
            "print('spekpy' in sys.modules, repr(s.effective_kev))")
    env = {**os.environ, "FLUOROSIM_CACHE_DIR": str(cache)}
    runs = [subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
            for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), [r.stderr[-500:] for r in runs]
    (cold, cold_eff), (warm, warm_eff) = (r.stdout.split() for r in runs)
    assert (cold, warm) == ("True", "False") and cold_eff == warm_eff
