"""Greedy EMD: the whole loop that removes, one by one, the components of the variable side
whose removal lowers the EMD most (one numba call, warm-started dual simplex of
:mod:`robot_change.change.transport_simplex`), and its trajectory :class:`GreedyResult`.

Masses ``weights_fixed`` (Ka,) and ``weights_var`` (Kb,), ground distance ``cost`` (Ka, Kb)
(rows the fixed side; the EMD values are in its unit).  The kernel is
``@njit(cache=True, nogil=True)`` with a plain NumPy/SciPy twin in ``tests/test_emd.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from robot_change import validate
from robot_change.change.transport_simplex import (
    _CUT_OFF,
    _DANTZIG_PIVOTS_PER_NODE,
    _OK,
    _REL_TOL_COST,
    _check_cost,
    _check_weights,
    _cold_solve,
    _objective,
    _raise_solver_failure,
    _tolerance,
    _warm_solve,
    _workspace,
)
from robot_change.change.transport_tree import _build_tree
from robot_change.errors import InputError

__all__ = [
    "STOP_REASONS",
    "GreedyResult",
    "greedy_emd",
]

#: Why :func:`greedy_emd` stopped (:attr:`GreedyResult.stop_reason`).
STOP_REASONS = ("no removal lowers the EMD", "no candidate left",
                "every removal would leave no mass", "max_removals reached")
_STOP_NO_IMPROVEMENT, _STOP_NO_CANDIDATE, _STOP_ZERO_MASS, _STOP_MAX_REMOVALS = 0, 1, 2, 3


@njit(cache=True, nogil=True)
def _greedy_kernel(a, b, cost, candidates, max_removals, compute_single, rel_tol, bland_after):
    """The greedy removal loop of :func:`greedy_emd`.

    Each round solves the candidates warm from the current optimal basis, in increasing order
    of the lower bound that basis's potentials give (the dual objective with the new column
    masses); a candidate is dropped as soon as its bound exceeds the best value found so far
    (or ``emd - tol_drop``), so only the promising ones are solved to the end.

    Parameters
    ----------
    a : array, shape (m,)
        Masses of the fixed side (rows), summing to 1.
    b : array, shape (n,)
        Masses of the side components are removed from (columns), summing to 1.
    cost : array, shape (m, n)
    candidates : array of bool, shape (n,)
    max_removals : int
    compute_single : bool
        Solve every candidate of the first round to the end (for ``emd_single``).
    rel_tol, bland_after
        As :func:`_emd_kernel`; a removal must also lower the EMD by more than
        ``rel_tol * max|cost|``.

    Returns
    -------
    order : array of int64, shape (k,)
    emd_after : array, shape (k + 1,)
    emd_single : array, shape (n,)
        EMD after removing only component j (first round), NaN if not solved to the end.
    n_solves : int
        Solves started (1 cold, then warm ones, cut-off ones included).
    n_pivots : int
    stop_code : int
    status : int
        0, or the status of a solve that failed (a bug).
    """
    m, n = cost.shape
    ne = m + n - 1
    tol_c = _tolerance(cost, rel_tol)
    tol_drop = tol_c
    if bland_after < 0:
        bland_after = _DANTZIG_PIVOTS_PER_NODE * (m + n)
    ws = _workspace(m, n)
    link, net, pot, x, tree = ws[1], ws[2], ws[3], ws[4], ws[9]
    cur_bi = np.zeros(ne, dtype=np.int64)
    cur_bj = np.zeros(ne, dtype=np.int64)
    try_bi = np.zeros(ne, dtype=np.int64)
    try_bj = np.zeros(ne, dtype=np.int64)
    best_bi = np.zeros(ne, dtype=np.int64)
    best_bj = np.zeros(ne, dtype=np.int64)
    bb = np.zeros(n)
    removed = np.zeros(n, dtype=np.bool_)
    k_list = np.zeros(n, dtype=np.int64)
    bounds = np.zeros(n)
    masses = np.zeros(n)
    n_max = min(max_removals, n)
    order = np.zeros(n_max, dtype=np.int64)
    emd_after = np.zeros(n_max + 1)
    emd_single = np.full(n, np.nan)

    status, n_pivots = _cold_solve(a, b, cost, tol_c, bland_after, cur_bi, cur_bj, ws)
    if status != _OK:
        return order[:0], emd_after[:1], emd_single, 1, n_pivots, _STOP_NO_IMPROVEMENT, status
    current = _objective(m, n, cur_bi, cur_bj, cost, x)
    emd_after[0] = current
    n_solves = 1
    steps = 0
    stop = _STOP_MAX_REMOVALS
    while steps < n_max:
        # potentials of the current optimum: dual feasible for every candidate
        _build_tree(m, n, cur_bi, cur_bj, a, b, cost, tree, link, net, pot, x)
        ua = 0.0
        for i in range(m):
            ua += a[i] * pot[i]
        any_candidate = False
        n_cand = 0
        for k in range(n):
            if removed[k] or not candidates[k]:
                continue
            any_candidate = True
            mass = 0.0
            bv = 0.0
            for j in range(n):
                if j != k and not removed[j]:
                    mass += b[j]
                    bv += b[j] * pot[m + j]
            if not mass > 0.0:
                continue
            k_list[n_cand] = k
            masses[n_cand] = mass
            bounds[n_cand] = ua + bv / mass
            n_cand += 1
        if not any_candidate:
            stop = _STOP_NO_CANDIDATE
            break
        if n_cand == 0:
            stop = _STOP_ZERO_MASS
            break
        threshold = current - tol_drop
        single = compute_single and steps == 0
        best = np.inf
        best_k = -1
        for idx in np.argsort(bounds[:n_cand], kind="mergesort"):
            k = k_list[idx]
            cutoff = np.inf if single else min(best, threshold)
            if bounds[idx] > cutoff:
                break  # the bounds ascend: no later candidate can do better
            mass = masses[idx]
            for j in range(n):
                bb[j] = 0.0 if (j == k or removed[j]) else b[j] / mass
            for e in range(try_bi.shape[0]):
                try_bi[e] = cur_bi[e]
                try_bj[e] = cur_bj[e]
            status, piv = _warm_solve(a, bb, cost, tol_c, cutoff, bland_after, try_bi, try_bj,
                                      ws)
            n_solves += 1
            n_pivots += piv
            if status == _CUT_OFF:
                continue
            if status != _OK:
                return (order[:steps].copy(), emd_after[:steps + 1].copy(), emd_single,
                        n_solves, n_pivots, stop, status)
            value = _objective(m, n, try_bi, try_bj, cost, x)
            if single:
                emd_single[k] = value
            if value < best or (value == best and k < best_k):
                best = value
                best_k = k
                for e in range(best_bi.shape[0]):
                    best_bi[e] = try_bi[e]
                    best_bj[e] = try_bj[e]
        if not (best_k >= 0 and best < threshold):
            stop = _STOP_NO_IMPROVEMENT
            break
        removed[best_k] = True
        order[steps] = best_k
        steps += 1
        emd_after[steps] = best
        current = best
        for e in range(cur_bi.shape[0]):
            cur_bi[e] = best_bi[e]
            cur_bj[e] = best_bj[e]
    return (order[:steps].copy(), emd_after[:steps + 1].copy(), emd_single, n_solves, n_pivots,
            stop, _OK)


@dataclass(frozen=True)
class GreedyResult:
    """Trajectory of :func:`greedy_emd`.

    Attributes
    ----------
    order : array of int64, shape (k,)
        Indices of the removed components of the variable side, in the order removed.
    emd_after : array, shape (k + 1,)
        ``emd_after[0]`` the EMD before any removal; ``emd_after[i]`` after removing
        ``order[:i]`` (remaining weights renormalised).  Strictly decreasing.
    emd_single : array, shape (Kb,)
        With ``compute_single``: EMD after removing component j alone (the first round's
        values); NaN for components that are not candidates, whose removal would leave no
        mass, when ``max_removals == 0``, and everywhere without ``compute_single``.
    stop_reason : str
        One of :data:`STOP_REASONS`.
    n_solves : int
        Transportation problems started (1 cold, the rest warm-started; those cut off early
        by their lower bound included).
    n_pivots : int
        Simplex pivots over all solves.
    """

    order: np.ndarray
    emd_after: np.ndarray
    emd_single: np.ndarray
    stop_reason: str
    n_solves: int
    n_pivots: int

    @property
    def drops(self) -> np.ndarray:
        """EMD lowered by each removal, shape (k,): ``-diff(emd_after)``, all > 0."""
        return -np.diff(self.emd_after)


def greedy_emd(weights_fixed, weights_var, cost, candidates=None,
               max_removals: int | None = None, compute_single: bool = False) -> GreedyResult:
    """Greedy EMD: remove the components of the variable side that lower the EMD most.

    One round: for each remaining candidate j, remove it, renormalise the remaining variable
    weights, solve the EMD; the removal with the lowest EMD is recorded (ties to the smallest
    index).  Rounds repeat until no removal lowers the EMD by more than
    ``1e-12 * max|cost|``, no candidate remains, every removal would leave no mass, or
    ``max_removals`` removals were made.

    Parameters
    ----------
    weights_fixed : array, shape (Ka,)
        Masses of the side kept whole (e.g. the reference to find what appeared in the current).
    weights_var : array, shape (Kb,)
        Masses of the side components are removed from.
    cost : array, shape (Ka, Kb)
        Ground distance, rows the fixed side.
    candidates : array of bool, shape (Kb,), optional
        Components that may be removed; default all.
    max_removals : int, optional
        At most this many removals (>= 0); default Kb.
    compute_single : bool
        Also solve every candidate of the first round exactly, for
        :attr:`GreedyResult.emd_single` (slower: no candidate is cut off in that round).

    Returns
    -------
    GreedyResult
        The whole trajectory; which prefix of ``order`` is a real change is the caller's call.

    Raises
    ------
    InputError
        As :func:`emd`, and a ``candidates`` that is not a (Kb,) boolean mask or a
        ``max_removals`` that is not an integer >= 0.
    """
    a = _check_weights(weights_fixed, "weights_fixed")
    b = _check_weights(weights_var, "weights_var")
    kb = b.shape[0]
    c = _check_cost(cost, a.shape[0], kb)
    if candidates is None:
        cand = np.ones(kb, dtype=np.bool_)
    else:
        cand = np.asarray(candidates)
        if cand.dtype != np.bool_ or cand.shape != (kb,):
            raise InputError(f"candidates must be a boolean mask of shape ({kb},), "
                             f"got {cand.dtype} {cand.shape}")
        cand = np.ascontiguousarray(cand)
    if max_removals is None:
        max_removals = kb
    validate.whole("greedy_emd", "max_removals", max_removals, 0, 2**31 - 1)
    order, emd_after, single, n_solves, n_pivots, stop, status = _greedy_kernel(
        a, b, c, cand, int(max_removals), bool(compute_single), _REL_TOL_COST, -1)
    if status != _OK:
        _raise_solver_failure(status, c.shape)
    return GreedyResult(order, emd_after, single, STOP_REASONS[stop], int(n_solves),
                        int(n_pivots))
