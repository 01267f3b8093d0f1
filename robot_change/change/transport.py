"""Earth Mover's Distance between small discrete distributions, and greedy EMD for change.

ALGORITHM.md section 3: the EMD between two Gaussian mixtures takes the component weights as
masses (each side normalised to 1) and a ground distance between components; it is solved
exactly, and the greedy loop removes the components of one mixture that lower the EMD most.

- :func:`emd` solves the transportation problem exactly (K up to a few dozen per side).
- :func:`ground_distance` gives the (Ka, Kb) ground distance: Euclidean between the means
  (default) or the closed-form 2-Wasserstein distance between the Gaussians.
- :func:`greedy_emd` runs the whole greedy removal loop in one numba call and returns its
  trajectory; which prefix of it is a real change is the caller's decision
  (:mod:`robot_change.change.detect`).
- :func:`mixture_emd` is EMD between two :class:`~robot_change.mixture.model.Mixture`.

The solver (all in numba) is the network simplex on the bipartite graph rows x columns (the
transportation simplex).  A basis is ``Ka + Kb - 1`` cells forming a spanning tree; it always
holds exactly that many cells, zero flows included, so degenerate problems (ties, zero weights,
Ka or Kb = 1) need no special case.

- Cold start (:func:`emd`, the greedy loop's first solve): the least-cost rule, crossing out
  exactly one row or column per cell, so the start is a feasible spanning tree.  Then primal
  pivots on a rooted tree (root row 0) kept as parent / edge-to-parent / thread (the cyclic
  preorder) / reverse thread / subtree size / last node of the subtree arrays:

  * pricing by block search: blocks of ``sqrt(Ka Kb)`` cells (at least 10) scanned cyclically
    from where the last one ended; the most negative reduced cost of the first block that has
    one enters;
  * the cycle closes at the deepest common ancestor (climb from the smaller subtree); the
    leaving cell is the smallest flow the cycle takes from, ties to the last one met going round
    the cycle from that ancestor (the strongly feasible rule);
  * the subtree cut off by the leaving cell is re-hung from the entering cell: its potentials
    shift by the entering reduced cost, its preorder is rebuilt in O(subtree) (the parts hanging
    off the reversed path, each in its old order), and only the path's and the cycle's
    ancestors' sizes change.  Flows change on the cycle only;
  * optimality is declared only after a full scan with the potentials recomputed from scratch,
    and the final flows are recomputed from scratch from the tree, so the rounding of the
    updates never reaches the result;
  * after ``_DANTZIG_PIVOTS_PER_NODE * (Ka + Kb)`` pivots the rule switches to Bland's (first
    improving cell in row-major order, smallest-index leaving cell), which cannot cycle.

  :func:`emd` checks and normalises the inputs inside the same kernel call (the Python checks
  only run to word the error), so a 10 x 10 call costs a few microseconds.
- Warm start (greedy): removing a component only changes the column masses, so the previous
  optimal tree stays dual feasible (the costs are the same); dual simplex pivots (the most
  negative flow leaves, the crossing cell of least reduced cost enters, which keeps every
  reduced cost >= 0; Bland's rule after the same bound) restore primal feasibility, hence
  optimality.  The tree is updated as in the primal; the pivots are few per solve (K ~ 30), so
  flows and potentials are then recomputed from the tree (one preorder pass).  The dual objective
  is a lower bound that only rises, so a candidate removal is abandoned as soon as its bound
  exceeds the best removal found so far in the round; the candidates are tried in increasing
  order of their starting bound.  A failed warm solve (pivot bound, rounding) falls back to a
  cold solve.

Tolerances: a reduced cost counts as negative below ``-1e-12 * max|cost|``; a flow counts as
negative below ``-1e-13`` (the masses sum to 1) and flows up to ``1e-13`` count as 0 in the
primal ratio test; flows in ``(-1e-13, 0)`` are reported as 0.

Numeric module: arrays in, arrays out.  Every kernel is ``@njit(cache=True, nogil=True)`` with
a plain NumPy/SciPy twin in ``tests/test_emd.py``.  The kernels live in
:mod:`robot_change.change.transport_tree` (the spanning-tree basis: start, tree arrays, flows,
potentials, pivot), :mod:`robot_change.change.transport_simplex` (primal and dual simplex, the
exact EMD kernels, the input checks) and :mod:`robot_change.change.transport_greedy` (the greedy
loop, :func:`greedy_emd`); this module is their public face and keeps the ground distances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robot_change.change.transport_greedy import STOP_REASONS, GreedyResult, greedy_emd
from robot_change.change.transport_simplex import (
    _BAD_INPUT,
    _OK,
    _REL_TOL_COST,
    _check_cost,
    _check_weights,
    _checked_emd_kernel,
    _raise_solver_failure,
)
from robot_change.change.transport_simplex import _emd_kernel as _emd_kernel  # bench/ uses it
from robot_change.errors import InputError, SolverError
from robot_change.mixture.model import Mixture

__all__ = [
    "GROUND_DISTANCES",
    "STOP_REASONS",
    "EmdResult",
    "GreedyResult",
    "emd",
    "greedy_emd",
    "ground_distance",
    "mixture_emd",
]

GROUND_DISTANCES = ("euclidean", "wasserstein2")


# --------------------------------------------------------------------------- public API


@dataclass(frozen=True)
class EmdResult:
    """Result of :func:`emd`.

    Attributes
    ----------
    distance : float
        ``sum(cost * flow)``: the EMD between the two normalised mass vectors.
    flow : array, shape (Ka, Kb)
        An optimal transport plan: ``flow >= 0``, row sums the normalised ``weights_a``,
        column sums the normalised ``weights_b`` (to rounding).
    """

    distance: float
    flow: np.ndarray


def emd(weights_a, weights_b, cost) -> EmdResult:
    """Exact Earth Mover's Distance between two discrete distributions.

    Parameters
    ----------
    weights_a : array, shape (Ka,)
        Masses of the first distribution, >= 0, not all zero; normalised to sum 1 here.
    weights_b : array, shape (Kb,)
        Masses of the second distribution, likewise.
    cost : array, shape (Ka, Kb)
        Finite ground distance (e.g. :func:`ground_distance`).

    Returns
    -------
    EmdResult
        ``distance`` = min over transport plans of ``sum(cost * flow)``, and one optimal
        ``flow``.

    Raises
    ------
    InputError
        Wrong shapes, empty, NaN / inf, negative or all-zero weights.
    """
    # fast path: conversions and shapes here, the value checks inside the kernel; the Python
    # checks below only run to name what is wrong
    try:
        a = np.asarray(weights_a, dtype=np.float64)
        b = np.asarray(weights_b, dtype=np.float64)
        c = np.ascontiguousarray(cost, dtype=np.float64)
    except (TypeError, ValueError):
        a = b = c = None
    if (a is None or a.ndim != 1 or b.ndim != 1 or c.shape != (a.shape[0], b.shape[0])
            or a.shape[0] == 0 or b.shape[0] == 0):
        _raise_emd_input_error(weights_a, weights_b, cost)
    if not a.flags.c_contiguous:
        a = a.copy()
    if not b.flags.c_contiguous:
        b = b.copy()
    distance, flow, status, _ = _checked_emd_kernel(a, b, c, _REL_TOL_COST)
    if status == _BAD_INPUT:
        _raise_emd_input_error(weights_a, weights_b, cost)
    if status != _OK:
        _raise_solver_failure(status, c.shape)
    return EmdResult(float(distance), flow)


def _raise_emd_input_error(weights_a, weights_b, cost) -> None:
    """The InputError :func:`emd`'s checks give for these inputs."""
    a = _check_weights(weights_a, "weights_a")
    b = _check_weights(weights_b, "weights_b")
    _check_cost(cost, a.shape[0], b.shape[0])
    raise SolverError("emd: the input checks of the kernel and of Python disagree; this is a bug "
                      "in robot_change.change.transport")


# --------------------------------------------------------------------------- ground distance


def _check_means(means, name: str) -> np.ndarray:
    try:
        mu = np.asarray(means, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric (K, 3) array: {exc}") from None
    if mu.ndim != 2 or mu.shape[0] == 0 or mu.shape[1] == 0:
        raise InputError(f"{name} must have shape (K, D) with K, D >= 1, got {mu.shape}")
    if not np.isfinite(mu).all():
        raise InputError(f"{name} contain NaN or inf")
    return mu


def _check_covariances(cov, name: str, k: int, d: int) -> np.ndarray:
    if cov is None:
        raise InputError(f'kind="wasserstein2" needs {name} of shape ({k}, {d}, {d})')
    try:
        s = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric (K, D, D) array: {exc}") from None
    if s.shape != (k, d, d):
        raise InputError(f"{name} must have shape ({k}, {d}, {d}), got {s.shape}")
    if not np.isfinite(s).all():
        raise InputError(f"{name} contain NaN or inf")
    asym = np.abs(s - s.transpose(0, 2, 1)).max(axis=(1, 2)) if k else np.zeros(0)
    scale = np.abs(s).max(axis=(1, 2))
    if (asym > 1e-9 * np.maximum(scale, 1e-300)).any():
        raise InputError(f"{name} must be symmetric; symmetrise them "
                         "(0.5 * (C + C.transpose(0, 2, 1)))")
    s = 0.5 * (s + s.transpose(0, 2, 1))
    evals = np.linalg.eigvalsh(s)
    if (evals[:, 0] < -1e-9 * np.maximum(evals[:, -1], 1e-300)).any():
        bad = np.flatnonzero(evals[:, 0] < -1e-9 * np.maximum(evals[:, -1], 1e-300)).tolist()
        raise InputError(f"{name} of components {bad} are not positive semi-definite")
    return s


def _sqrtm_psd(s: np.ndarray) -> np.ndarray:
    """Symmetric square roots of PSD matrices, shape (K, D, D), eigenvalues clipped at 0."""
    evals, evecs = np.linalg.eigh(s)
    root = np.sqrt(np.clip(evals, 0.0, None))
    return (evecs * root[:, None, :]) @ evecs.transpose(0, 2, 1)


def _bures_squared(cov_a: np.ndarray, cov_b: np.ndarray) -> np.ndarray:
    """``tr(Sa + Sb - 2 (Sa^1/2 Sb Sa^1/2)^1/2)`` for every pair, shape (Ka, Kb), >= 0.

    Exactly 0 where ``Sa == Sb`` element for element (the rounding of the formula would leave
    ~1e-16 tr S, i.e. a distance of ~1e-8 sqrt(tr S)).
    """
    root_a = _sqrtm_psd(cov_a)                                   # (Ka, D, D)
    mid = root_a[:, None] @ cov_b[None] @ root_a[:, None]        # (Ka, Kb, D, D)
    mid = 0.5 * (mid + np.swapaxes(mid, -1, -2))
    cross = np.sqrt(np.clip(np.linalg.eigvalsh(mid), 0.0, None)).sum(axis=-1)
    tr_a = np.trace(cov_a, axis1=1, axis2=2)
    tr_b = np.trace(cov_b, axis1=1, axis2=2)
    bures = np.clip(tr_a[:, None] + tr_b[None, :] - 2.0 * cross, 0.0, None)
    same = (cov_a[:, None] == cov_b[None]).all(axis=(2, 3))
    bures[same] = 0.0
    return bures


def ground_distance(means_a, means_b, covariances_a=None, covariances_b=None,
                    kind: str = "euclidean") -> np.ndarray:
    """Ground distance between the components of two mixtures.

    Parameters
    ----------
    means_a : array, shape (Ka, D)
    means_b : array, shape (Kb, D)
    covariances_a : array, shape (Ka, D, D), optional
        Symmetric positive semi-definite; needed for ``kind="wasserstein2"``.
    covariances_b : array, shape (Kb, D, D), optional
    kind : {"euclidean", "wasserstein2"}
        ``"euclidean"``: ``|mu_a - mu_b|``.  ``"wasserstein2"``: the 2-Wasserstein distance
        between the Gaussians, ``sqrt(|mu_a - mu_b|^2 + tr(Sa + Sb - 2 (Sa^1/2 Sb Sa^1/2)^1/2))``
        (symmetric square roots by eigendecomposition, tiny negative eigenvalues clipped).

    Returns
    -------
    distance : array, shape (Ka, Kb)
        Non-negative, in the unit of the means.

    Raises
    ------
    InputError
        Unknown kind, wrong shapes, NaN / inf, missing, asymmetric or indefinite covariances.
    """
    if kind not in GROUND_DISTANCES:
        raise InputError(f"kind must be one of {GROUND_DISTANCES}, got {kind!r}")
    mu_a = _check_means(means_a, "means_a")
    mu_b = _check_means(means_b, "means_b")
    if mu_a.shape[1] != mu_b.shape[1]:
        raise InputError(f"means_a and means_b must have the same dimension, got "
                         f"{mu_a.shape[1]} and {mu_b.shape[1]}")
    sq = ((mu_a[:, None, :] - mu_b[None, :, :]) ** 2).sum(axis=-1)
    if kind == "wasserstein2":
        d = mu_a.shape[1]
        cov_a = _check_covariances(covariances_a, "covariances_a", mu_a.shape[0], d)
        cov_b = _check_covariances(covariances_b, "covariances_b", mu_b.shape[0], d)
        sq = sq + _bures_squared(cov_a, cov_b)
    return np.sqrt(sq)


def mixture_emd(a, b, kind: str = "euclidean") -> float:
    """EMD between two :class:`~robot_change.mixture.model.Mixture` (weights as masses).

    Parameters
    ----------
    a, b : Mixture
    kind : {"euclidean", "wasserstein2"}
        Ground distance, see :func:`ground_distance`.

    Returns
    -------
    float
    """
    for name, mix in (("a", a), ("b", b)):
        if not isinstance(mix, Mixture):
            raise InputError(f"{name} must be a Mixture, got {type(mix).__name__}")
    cost = ground_distance(a.means, b.means, a.covariances, b.covariances, kind=kind)
    return emd(a.weights, b.weights, cost).distance
