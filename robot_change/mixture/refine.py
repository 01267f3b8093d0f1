"""Split-and-merge moves at fixed K (Ueda et al.'s SMEM; ``refine`` of
:func:`robot_change.mixture.model.fit_mixture`): after the split search, merge two overlapping
components and split a third, ranked by an estimated log-likelihood gain (nats) from hard
assignments, each tried by a partial EM over the other components held fixed and kept only if
the criterion drops.  Works on the search's :class:`~robot_change.mixture.search._State`;
points (N, 3) in metres.
"""

from __future__ import annotations

import math
import time

import numpy as np

from robot_change.mixture import em
from robot_change.mixture.fit_record import FitStep, _replace_accepted
from robot_change.mixture.search import (
    _evaluate,
    _run_em,
    _split_component,
    _State,
    _symmetric,
    component_of,
)

__all__ = ["PARTIAL_MASS", "REFINE_PAIRS", "REFINE_START_ITER", "REFINE_TRIES"]


#: Split-and-merge moves (``refine`` of :func:`fit_mixture`): the most overlapping pairs
#: considered for a merge in a round, the moves tried per round (largest estimated gain
#: first), the EM iterations on the refinement subset before the moves, and the
#: responsibility mass above which a point takes part in a move's partial EM.
REFINE_PAIRS = 8
REFINE_TRIES = 4
REFINE_START_ITER = 5
PARTIAL_MASS = 1e-3


def _merged(cur: _State, i: int, j: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Moment-matched merge of components i and j: (weight, mean, covariance)."""
    wi, wj = cur.weights[i], cur.weights[j]
    w = wi + wj
    mu = (wi * cur.means[i] + wj * cur.means[j]) / w
    di, dj = cur.means[i] - mu, cur.means[j] - mu
    cov = (wi * (cur.covs[i] + np.outer(di, di)) + wj * (cur.covs[j] + np.outer(dj, dj))) / w
    return w, mu, _symmetric(cov[None])[0]


def _fitted_log_l_per_point(covs, reg_covar) -> np.ndarray:
    """Mean log-likelihood per point of a group of points under its own Gaussian (ML mean, ML
    covariance plus the floor: ``covs`` (..., 3, 3)): ``-0.5 (3 log 2 pi + log det C + 3 -
    reg tr C^-1)``, shape (...)."""
    _, logdet = np.linalg.slogdet(covs)
    tr = np.trace(np.linalg.inv(covs), axis1=-2, axis2=-1)
    return -0.5 * (3.0 * math.log(2.0 * math.pi) + logdet + 3.0 - reg_covar * tr)


def _hard_log_l(counts, covs, reg_covar) -> float:
    """Log-likelihood of points hard-partitioned into groups, each under its own Gaussian
    (``covs`` (G, 3, 3), :func:`_fitted_log_l_per_point`) with the groups' shares as weights."""
    counts = np.asarray(counts, dtype=np.float64)
    per = _fitted_log_l_per_point(covs, reg_covar)
    return float((counts * (np.log(counts / counts.sum()) + per)).sum())


def _split_gain(xk, mean, cov, reg_covar, tol, max_iter):
    """How much splitting a component raises the log-likelihood of its points ``xk``.

    Two splits: the two-means seeded along the largest axis of ``cov`` (as the greedy
    search's), and the plain cut through the mean across the smallest axis (no Lloyd steps:
    on two parallel sheets of a wall's extent they would turn the cut back across the sheets,
    as Euclidean two-means prefers); the better by hard log-likelihood is refined by a local EM
    of the two halves on ``xk`` (which also finds a thin sheet inside a thicker spread, where
    no cut separates the two).  Returns ``(gain, weights (2,) summing to 1,
    means (2, 3), covariances (2, 3, 3))`` -- the gain against the points' own single
    Gaussian, nats -- or None.
    """
    best = None
    for axis, n_lloyd in ((-1, 5), (0, 0)):
        parts = _split_component(xk, mean, cov, 1.0, reg_covar, n_lloyd, axis)
        if parts is None:
            continue
        log_l = _hard_log_l(parts[0] * len(xk), parts[2], reg_covar)
        if best is None or log_l > best[0]:
            best = (log_l, *parts)
    if best is None:
        return None
    w2, mu2, cov2, lp, _, status, _ = em.em_loop(
        xk, best[1], best[2], best[3], np.zeros(2, dtype=bool), False, reg_covar, tol, max_iter)
    if status != em.STATUS_EMPTY:
        best = (float(lp) * len(xk), w2, mu2, cov2)
    _, single = component_of(xk, reg_covar)
    return (best[0] - _hard_log_l([len(xk)], single[None], reg_covar), *best[1:])


def _merge_losses(x, labels, k_n, pairs, reg_covar) -> np.ndarray:
    """For each pair (i, j) of ``pairs`` (P, 2): the log-likelihood lost when the points
    hard-assigned to i and j are described by one Gaussian instead of two (:func:`_hard_log_l`
    from each group's count, mean and scatter; nats, <= 0 up to the floor; -inf when either
    has fewer than 2 points)."""
    counts = np.bincount(labels, minlength=k_n).astype(np.float64)
    sums = np.stack([np.bincount(labels, x[:, a], k_n) for a in range(3)], axis=1)
    outer = np.stack([np.bincount(labels, x[:, a] * x[:, b], k_n)
                      for a in range(3) for b in range(3)], axis=1).reshape(k_n, 3, 3)
    i, j = pairs[:, 0], pairs[:, 1]
    n = np.stack([counts[i], counts[j], counts[i] + counts[j]], axis=1)  # (P, 3)
    ok = n[:, :2].min(axis=1) >= 2
    n = np.maximum(n, 1.0)
    s1 = np.stack([sums[i], sums[j], sums[i] + sums[j]], axis=1)  # (P, 3, 3)
    s2 = np.stack([outer[i], outer[j], outer[i] + outer[j]], axis=1)  # (P, 3, 3, 3)
    m = s1 / n[..., None]
    covs = s2 / n[..., None, None] - m[..., :, None] * m[..., None, :] + reg_covar * np.eye(3)
    covs = 0.5 * (covs + np.swapaxes(covs, -1, -2))
    per = _fitted_log_l_per_point(covs, reg_covar)  # (P, 3)
    share = np.log(n[:, :2] / n[:, 2:])
    loss = n[:, 2] * per[:, 2] - (n[:, :2] * (share + per[:, :2])).sum(axis=1)
    return np.where(ok, loss, -np.inf)


def _partial_em(x, log_resp, cur: _State, gone, new_w, new_mu, new_cov, reg_covar, tol,
                max_iter, mass=PARTIAL_MASS):
    """EM of new free components replacing the components ``gone`` of ``cur`` (no fixed
    ones), with every other component held fixed, weights and all, on the points the replaced
    ones explain (responsibility mass > ``mass``, from ``log_resp`` (N, K)): the partial EM
    of SMEM; the new components share the replaced ones' total weight.  Returns the new
    _State (the kept components first, then the new ones; weights summing to 1) or None when
    a new component loses its points."""
    keep = np.ones(len(cur.weights), dtype=bool)
    keep[list(gone)] = False
    w_gone = float(cur.weights[~keep].sum())
    sel = np.exp(log_resp[:, ~keep]).sum(axis=1) > mass
    xp = x[sel]
    if len(xp) < 2 * len(new_w):
        return None
    wk = cur.weights[keep]
    prec, log_det, _ = em.precision_cholesky(cur.covs[keep])
    log_bg = em.log_prob_samples(xp, wk / wk.sum(), cur.means[keep], prec, log_det)
    w0 = np.concatenate([[1.0 - w_gone], new_w / new_w.sum() * w_gone])
    w2, mu2, cov2, _, n_it, status, _ = em.em_loop_background(
        xp, log_bg, w0, new_mu, new_cov, reg_covar, tol, max_iter, True)
    if status == em.STATUS_EMPTY:
        return None
    w = np.concatenate([wk, w2[1:]])
    return _State(w / w.sum(), np.vstack([cur.means[keep], mu2]),
                  np.concatenate([cur.covs[keep], cov2]),
                  np.zeros(len(w), dtype=bool), np.full(len(w), np.nan), n_iter=int(n_it),
                  converged=status == em.STATUS_CONVERGED)


def _refine(x, cur: _State, n_total, criterion, budget, tol, max_iter, reg_covar, opts,
            min_points, steps) -> _State:
    """Split-and-merge moves at fixed K on ``x`` (see ``refine`` of :func:`fit_mixture`)."""
    t0 = time.perf_counter()
    cur = _run_em(x, _State(cur.weights, cur.means, cur.covs, cur.fixed,
                            np.full(len(cur.weights), np.nan)),
                  **dict(opts, tol=tol, max_iter=min(max_iter, REFINE_START_ITER)))
    _evaluate(x, cur, criterion, opts["fix_weights"], n_total)
    steps.append(_replace_accepted(FitStep("refine", len(cur.weights), cur.crit, cur.log_l,
                                           cur.n_iter, cur.converged, True,
                                           time.perf_counter() - t0)))
    k_n = len(cur.weights)
    min_drop = tol * n_total  # a move must lower the criterion by more than EM's own noise
    ids = list(range(k_n))  # each component's identity, kept across moves (the cache's keys)
    next_id = k_n
    gains: dict = {}  # id -> _split_gain of that component (computed once)
    rejected: set = set()  # moves (as ids) tried and rejected
    while budget > 0:
        prec, log_det, _ = em.precision_cholesky(cur.covs)
        log_resp, _ = em.e_step(x, cur.weights, cur.means, prec, log_det)
        labels = log_resp.argmax(axis=1)
        for k in range(k_n):
            if ids[k] not in gains:
                xk = x[labels == k]
                gains[ids[k]] = None if len(xk) < 2 * min_points else _split_gain(
                    xk, cur.means[k], cur.covs[k], reg_covar, tol, max_iter)
        resp = np.exp(log_resp)
        gram = resp.T @ resp
        norm = np.sqrt(np.maximum(np.diag(gram), 1e-300))
        iu, ju = np.triu_indices(k_n, 1)
        top = np.argsort(-(gram / np.outer(norm, norm))[iu, ju], kind="stable")[:REFINE_PAIRS]
        pairs = np.stack([iu[top], ju[top]], axis=1)
        losses = _merge_losses(x, labels, k_n, pairs, reg_covar)
        cands = []
        for (i, j), loss in zip(pairs.tolist(), losses, strict=False):
            for k in range(k_n):
                g = gains[ids[k]]
                if g is None or k in (i, j) or (ids[i], ids[j], ids[k]) in rejected:
                    continue
                cands.append((g[0] + loss, i, j, k))
        cands.sort(key=lambda c: -c[0])
        improved = False
        for _, i, j, k in cands[:REFINE_TRIES]:
            if budget <= 0:
                break
            budget -= 1
            t0 = time.perf_counter()
            g = gains[ids[k]]
            wm, mm, cm = _merged(cur, i, j)
            cand = _partial_em(x, log_resp, cur, (i, j, k),
                               np.concatenate([[wm], g[1] * cur.weights[k]]),
                               np.vstack([mm[None], g[2]]), np.concatenate([cm[None], g[3]]),
                               reg_covar, tol, max_iter)
            ok = False
            if cand is not None:
                _evaluate(x, cand, criterion, opts["fix_weights"], n_total)
                ok = bool(len(cand.weights) == k_n and cand.crit < cur.crit - min_drop
                          and (n_total * cand.weights >= min_points).all())
                steps.append(FitStep(f"refine {i}+{j}/{k}", len(cand.weights), cand.crit,
                                     cand.log_l, cand.n_iter, cand.converged, ok,
                                     time.perf_counter() - t0))
            if not ok:
                rejected.add((ids[i], ids[j], ids[k]))
                continue
            ids = [ids[q] for q in range(k_n) if q not in (i, j, k)] + [next_id, next_id + 1,
                                                                         next_id + 2]
            next_id += 3
            cur, improved = cand, True
            break
        if not improved:
            return cur
    return cur
