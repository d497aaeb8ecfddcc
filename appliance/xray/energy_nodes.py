"""A few energies for the polychromatic detector signal instead of every bin of the spectrum.

The energy-integrating detector's signal relative to the open beam is
    T(L) = sum_e w_e exp(-0.1 mu_e . L)
over the spectrum's bins e (`casting.DetectorTables`), with L a ray's four material integrals
(g/cm^3 * mm). Per pixel that is one exp per bin, the larger part of a frame's cost when the
line integrals are cached. The same function is well approximated by a handful of terms
    T(L) ~ sum_k v_k exp(-0.1 mu_(e_k) . L)
at a subset of the bins with weights v_k >= 0 fitted to it: a quadrature fitted to this
spectrum and these materials over the integrals a patient presents (the profile's
`energy_nodes` ranges), the way a correlated-k method replaces a line-by-line sum.

Nodes are bins of the spectrum itself, so a node's attenuation is the table's own row at any
iodine concentration (the contrast column is linear in it), and the fit holds while the
contrast fills and washes out. The fit is greedy: each step adds the bin that most lowers the
root-mean-square relative error (weights by non-negative least squares), then the weights are
moved toward the minimax fit (Lawson), until the largest relative error over the fitting rays
and over a second, independent set of rays is within the profile's bound. If `max_nodes`
cannot reach it, there is no quadrature and the frame sums every bin.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..config.energy_nodes import EnergyNodes

#: Random rays (sets of material integrals) per contrast concentration of the fit, and of its
#: independent check: enough that the largest error among them stands for the range's.
FIT_RAYS = 1500
#: Concentrations of the case's iodine the fit covers, as fractions of the case's: filling and
#: washing out pass through all of them (the contrast column is linear in between).
FIT_FACTORS = (0.0, 0.5, 1.0)


@dataclass(frozen=True)
class NodeQuadrature:
    """The bins (indices into the spectrum's energies) the sum is evaluated at, their weights,
    and the largest relative error in I/I0 the fit found over its rays and its check's."""

    bins: np.ndarray        # (k,) int
    weights: np.ndarray     # (k,) float32, >= 0
    max_error: float        # fraction of the whole spectrum's transmission


def fitting_rays(limits: EnergyNodes, n: int, seed: int) -> np.ndarray:
    """(m, 4) material integrals (g/cm^3 * mm): `n` uniform in the box of the profile's ranges,
    and each material alone along its whole range (the edges of the box, where a uniform draw
    rarely falls)."""
    top = 10.0 * np.array([limits.air_max_g_per_cm2, limits.soft_tissue_max_g_per_cm2, limits.bone_max_g_per_cm2,
                           limits.contrast_max_g_per_cm2])       # g/cm^2 -> g/cm^3 * mm
    rng = np.random.default_rng(seed)
    axes = np.zeros((4 * 33, 4))
    for m in range(4):
        axes[33 * m:33 * (m + 1), m] = np.linspace(0.0, top[m], 33)
    return np.vstack([rng.uniform(0.0, 1.0, (n, 4)) * top, axes])


def relative_terms(weights: np.ndarray, mu_by_factor: list[np.ndarray], rays: np.ndarray,
                   min_transmission: float) -> np.ndarray:
    """(rows, bins): each bin's term exp(-0.1 mu_e . L) over the whole sum T(L), for every ray
    and concentration whose T(L) is at least `min_transmission`. A quadrature's relative error
    on a row is then (row @ v) - 1."""
    blocks = []
    for mu in mu_by_factor:
        terms = np.exp(-0.1 * rays @ np.asarray(mu, float).T)
        total = terms @ np.asarray(weights, float)
        keep = total >= min_transmission
        blocks.append(terms[keep] / total[keep, None])
    return np.vstack(blocks)


def _minimax(terms: np.ndarray, rounds: int) -> tuple[float, np.ndarray]:
    """(largest relative error, weights) of the bins whose `terms` are given, by Lawson's
    iteration: non-negative least squares reweighted toward the rows with the largest error,
    which drives the fit from the least-squares toward the minimax one."""
    from scipy.optimize import nnls

    u = np.full(len(terms), 1.0 / len(terms))
    best: tuple[float, np.ndarray] | None = None
    # The open beam's row (every term 1) weighted far above the rest: sum v = 1 all but exactly.
    open_beam = np.full((1, terms.shape[1]), OPEN_BEAM_WEIGHT)
    for _ in range(rounds):
        s = np.sqrt(u)
        v, _ = nnls(np.vstack([terms * s[:, None], open_beam]), np.append(s, OPEN_BEAM_WEIGHT))
        v = v / v.sum()         # the open beam reads exactly 1, as with every bin
        err = np.abs(terms @ v - 1.0)
        if best is None or err.max() < best[0]:
            best = (float(err.max()), v)
        u = u * err
        total = u.sum()
        if total <= 0:
            break
        u /= total
    assert best is not None
    return best


#: Lawson rounds per candidate set, started only once the least-squares fit is within this
#: many times the bound (earlier sets cannot reach it; they cost the fit's time for nothing).
MINIMAX_ROUNDS = 20
MINIMAX_FROM = 10.0
#: Weight of the open beam's row in the fit, against rows of weight at most 1.
OPEN_BEAM_WEIGHT = 100.0


#: Fits made in this process, by what they were fitted to: every renderer of one fluoroscope
#: (the moving matrices' included) shares them, so a kV's fit (a tenth of a second or more on
#: two cores) is paid once per process.
_FITS: dict[tuple, NodeQuadrature | None] = {}


def fit_nodes(weights: np.ndarray, mu_by_factor: list[np.ndarray], limits: EnergyNodes) -> NodeQuadrature | None:
    """The quadrature of the spectrum `weights` (n_e,) and mass attenuation tables
    `mu_by_factor` ((n_e, 4) each, cm^2/g; one per iodine concentration to cover) within
    `limits`; None where max_nodes bins cannot reach max_relative_error. Kept for the process."""
    key = (np.asarray(weights, np.float64).tobytes(), tuple(np.asarray(m, np.float64).tobytes() for m in mu_by_factor),
           limits)
    if key not in _FITS:
        if len(_FITS) > 256:
            _FITS.clear()
        _FITS[key] = _fit(weights, mu_by_factor, limits)
    return _FITS[key]


#: One side thread fits the kVs a live renderer meets for the first time (fit_soon).
_SIDE: ThreadPoolExecutor | None = None
_SIDE_LOCK = threading.Lock()


def fit_soon(weights: np.ndarray, mu_by_factor: list[np.ndarray], limits: EnergyNodes) -> Future:
    """`fit_nodes` on a side thread: a live frame at a kV not fitted yet sums every bin (exact,
    a few ms dearer) instead of stalling the picture for the fit (a tenth of a second or more on
    two cores); the frames after it at that kV use the nodes. The result is fit_nodes's."""
    global _SIDE
    with _SIDE_LOCK:
        if _SIDE is None:
            _SIDE = ThreadPoolExecutor(max_workers=1, thread_name_prefix="energy-nodes")
        return _SIDE.submit(fit_nodes, weights, mu_by_factor, limits)


def _fit(weights: np.ndarray, mu_by_factor: list[np.ndarray], limits: EnergyNodes) -> NodeQuadrature | None:
    from scipy.optimize import nnls

    fit = relative_terms(weights, mu_by_factor, fitting_rays(limits, FIT_RAYS, 1), limits.min_transmission)
    check = relative_terms(weights, mu_by_factor, fitting_rays(limits, FIT_RAYS, 2), limits.min_transmission)
    ones = np.ones(len(fit))
    bound = limits.max_relative_error
    chosen: list[int] = []
    for _ in range(min(limits.max_nodes, len(weights))):
        best: tuple[float, int, np.ndarray] | None = None
        for e in range(len(weights)):
            if e in chosen:
                continue
            v, _ = nnls(fit[:, chosen + [e]], ones)
            rms = float(np.sqrt(np.mean((fit[:, chosen + [e]] @ v - 1.0) ** 2)))
            if best is None or rms < best[0]:
                best = (rms, e, v)
        assert best is not None
        chosen.append(best[1])
        v = best[2]
        if float(np.abs(fit[:, chosen] @ v - 1.0).max()) > MINIMAX_FROM * bound:
            continue
        _, v = _minimax(fit[:, chosen], MINIMAX_ROUNDS)
        worst = max(float(np.abs(fit[:, chosen] @ v - 1.0).max()), float(np.abs(check[:, chosen] @ v - 1.0).max()))
        if worst <= bound:
            order = np.argsort(chosen)
            return NodeQuadrature(np.asarray(chosen)[order], v[order].astype(np.float32), worst)
    return None
