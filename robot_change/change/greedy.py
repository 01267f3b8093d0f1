"""The EMD part of a check: the ground cost between two mixtures, the greedy EMD trajectory
over the candidate components and the explicit acceptance rule on it, and the posteriors of
the components a direction found changed.
"""

from __future__ import annotations

import numpy as np

from robot_change.change import transport as emd_mod
from robot_change.change.params import ChangeParams
from robot_change.change.results import GreedyTrace
from robot_change.mixture import em
from robot_change.mixture.model import Mixture

__all__ = [
    "accept_trajectory",
    "greedy_trace",
    "ground_cost",
    "posteriors",
]


def ground_cost(ma: Mixture, mb: Mixture, kind: str) -> np.ndarray:
    if kind == "euclidean":
        return emd_mod.ground_distance(ma.means, mb.means, kind="euclidean")
    return emd_mod.ground_distance(ma.means, mb.means, ma.covariances, mb.covariances,
                                   kind="wasserstein2")


def accept_trajectory(order: np.ndarray, emd_after: np.ndarray, weights: np.ndarray,
                      n_points: int, params: ChangeParams) -> int:
    """How many leading removals of a greedy EMD trajectory the acceptance rule keeps.

    Step i (removing ``order[i]``) is accepted while ``emd_after[i] - emd_after[i + 1]`` is at
    least ``accept_min_drop_m`` and at least ``accept_min_drop_rel * emd_after[0]``, and the
    removed component holds at least ``min_region_points`` points (``n_points * w``); the
    first step that fails stops it.
    """
    d0 = float(emd_after[0]) if len(emd_after) else 0.0
    need = max(params.accept_min_drop_m, params.accept_min_drop_rel * d0)
    n_ok = 0
    for i, k in enumerate(order):
        drop = float(emd_after[i] - emd_after[i + 1])
        if drop < need or n_points * float(weights[k]) < params.min_region_points:
            break
        n_ok += 1
    return n_ok


def greedy_trace(fixed_mix: Mixture, var_mix: Mixture, candidates: np.ndarray, n_points: int,
            params: ChangeParams) -> GreedyTrace:
    cand_idx = np.flatnonzero(candidates)
    if cand_idx.size == 0:
        return GreedyTrace(cand_idx, np.zeros(0, np.int64),
                           np.array([np.nan]), 0, np.zeros(0, np.int64))
    cost = ground_cost(fixed_mix, var_mix, params.ground_distance)
    res = emd_mod.greedy_emd(fixed_mix.weights, var_mix.weights, cost, candidates,
                             int(cand_idx.size))
    order = np.asarray(res.order, dtype=np.int64)
    emd_after = np.asarray(res.emd_after, dtype=np.float64)
    if params.greedy:
        n_ok = accept_trajectory(order, emd_after, var_mix.weights, n_points, params)
        change = order[:n_ok]
    else:
        n_ok = int(order.size)
        change = cand_idx
    return GreedyTrace(cand_idx, order, emd_after, n_ok, np.sort(change))


def posteriors(mix: Mixture, points: np.ndarray, rows: np.ndarray | None,
               background: tuple[int, np.ndarray] | None = None) -> np.ndarray:
    """(M, K) posteriors of ``mix``'s components at ``points`` (M, 3); only ``rows`` filled
    when given (zeros elsewhere).

    ``background``: (k0, log_bg) when the first k0 components are a fixed background whose
    log-density at each point (M,) is at hand (their weights summing to 1; a novelty fit,
    :func:`robot_change.mixture.model.fit_over_background`): then only the other components'
    columns are computed, at N x (K - k0) cost, and the background's are left 0.
    """
    k_n = mix.n_components
    sel = np.arange(points.shape[0]) if rows is None else rows
    post = np.zeros((points.shape[0], k_n))
    if sel.size == 0:
        return post
    if background is None:
        post[sel] = mix.responsibilities(points[sel])
        return post
    k0, log_bg = background
    weights = np.concatenate([[mix.weights[:k0].sum()], mix.weights[k0:]])
    # writable copies: the array types the fit gives these kernels (one compile)
    prec, log_det, _ = em.precision_cholesky(np.array(mix.covariances[k0:]))
    resp, _ = em.responsibilities_background(
        np.ascontiguousarray(points[sel], dtype=np.float64), np.ascontiguousarray(log_bg[sel]),
        weights, np.array(mix.means[k0:]), prec, log_det)
    post[sel, k0:] = resp[:, 1:]
    return post
