"""The tube's beam as spekpy models it, kept on disk between processes.

Importing spekpy and modelling one beam costs about 2.5 s of CPU, and every process that
renders (the daemon at boot, each `fluorosim render`, `calibrate`, `demo`) asks for the same
few beams. What spekpy returns for a beam depends only on its settings and spekpy's version,
so the raw figures (fine spectrum, effective and mean energy, fluence and air kerma) are
stored once per settings in the cache directory and read back bit for bit; everything
derived from them (the renderer's energy bins, photons per air kerma) is still computed by
the caller each time, so a change there never meets a stale file.

The cache directory: `$FLUOROSIM_CACHE_DIR`, else systemd's `$CACHE_DIRECTORY` (the unit's
CacheDirectory=), else `$XDG_CACHE_HOME/fluorosim`, else `~/.cache/fluorosim`. A missing,
unreadable or unwritable cache only costs the time: the beam is modelled afresh.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FluorosimError


@dataclass(frozen=True)
class Beam:
    """spekpy's figures of one beam. `energies_kev` are the fine bins' centres and
    `photons_per_cm2_per_mas_per_kev` their fluence at 1 m; `fluence_per_cm2_per_mas` and
    `air_kerma_ugy_per_mas` the totals at 1 m; energies in keV."""

    energies_kev: np.ndarray
    photons_per_cm2_per_mas_per_kev: np.ndarray
    effective_kev: float
    mean_kev: float
    fluence_per_cm2_per_mas: float
    air_kerma_ugy_per_mas: float


def cache_dir() -> Path:
    """Where modelled beams are kept (see the module's docstring)."""
    for var in ("FLUOROSIM_CACHE_DIR", "CACHE_DIRECTORY"):
        if os.environ.get(var):
            return Path(os.environ[var].split(":")[0])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "fluorosim"


def _spekpy_version() -> str:
    try:
        return importlib.metadata.version("spekpy")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _path(settings: dict) -> Path:
    key = json.dumps({**settings, "spekpy": _spekpy_version()}, sort_keys=True)
    return cache_dir() / "spekpy" / f"beam-{hashlib.sha256(key.encode()).hexdigest()[:24]}.npz"


def _model(kvp: float, anode_angle_deg: float, dk_kev: float, filters: tuple[tuple[str, float], ...]) -> Beam:
    import spekpy

    try:
        s = spekpy.Spek(kvp=kvp, th=anode_angle_deg, dk=dk_kev)
        for material, mm in filters:
            if mm > 0:
                s.filter(material, mm)
        k, phi = s.get_spectrum()   # keV, photons / cm^2 / mAs / keV at 1 m
        return Beam(np.asarray(k, np.float64), np.asarray(phi, np.float64), float(s.get_eeff()),
                    float(s.get_emean()), float(s.get_flu()), float(s.get_kerma()))
    except Exception as e:  # spekpy raises plain Exceptions for out-of-range settings
        al = sum(mm for material, mm in filters if material == "Al")
        raise FluorosimError(f"spekpy cannot model a {kvp} kVp tube with {al} mm Al: {e}; check "
                             "tube.kvp and tube.filtration_mm_al") from None


def _read(path: Path) -> Beam | None:
    try:
        with np.load(path) as f:
            scalars = f["scalars"]
            return Beam(f["energies_kev"], f["phi"], *(float(x) for x in scalars))
    except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile):
        return None     # absent, truncated or from something else: model it again


def _write(path: Path, beam: Beam) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".beam-", suffix=".npz")
        with os.fdopen(fd, "wb") as f:
            np.savez(f, energies_kev=beam.energies_kev, phi=beam.photons_per_cm2_per_mas_per_kev,
                     scalars=np.array([beam.effective_kev, beam.mean_kev, beam.fluence_per_cm2_per_mas,
                                       beam.air_kerma_ugy_per_mas], np.float64))
        os.replace(tmp, path)     # a reader sees the whole file or none
    except OSError:
        pass                      # a read-only or full cache only costs the next process the time


@functools.lru_cache(maxsize=64)
def beam(kvp: float, anode_angle_deg: float, dk_kev: float, filters: tuple[tuple[str, float], ...] = ()) -> Beam:
    """spekpy's beam of a `kvp` tube with anode angle `anode_angle_deg` (degrees), fine bins
    `dk_kev` wide, behind `filters` ((spekpy material name, thickness mm), in order)."""
    settings = {"kvp": float(kvp), "th": float(anode_angle_deg), "dk": float(dk_kev),
                "filters": [[m, float(mm)] for m, mm in filters if mm > 0]}
    path = _path(settings)
    cached = _read(path)
    if cached is not None:
        return cached
    fresh = _model(float(kvp), float(anode_angle_deg), float(dk_kev), tuple(filters))
    _write(path, fresh)
    return fresh
