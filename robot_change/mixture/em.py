"""Numba kernels of EM for 3-D Gaussian mixtures with full covariances: the E-step and the
log-densities, the M-step, the fused EM step and its loop to convergence, and the two-means
split of one component's points.

Every kernel is ``@njit(cache=True, nogil=True)``, single-threaded, without fastmath, and takes
and returns float64 arrays.  Each has a plain NumPy twin in ``tests/test_mixture.py``.  The
pieces they share (constants, :func:`precision_cholesky`, the blocked Gaussian log-density, the
M-step sums) are in :mod:`robot_change.mixture.em_core`, the kernels over a fixed background
density (:func:`em_step_background`, :func:`em_loop_background`,
:func:`responsibilities_background`) in :mod:`robot_change.mixture.em_background`; both are
re-exported here, the one place the rest of the project imports EM from.

Conventions (as in scikit-learn's ``sklearn/mixture``):

- ``prec_chol[k]`` is the upper-triangular Cholesky factor of the precision of component k,
  ``inv(L_k).T`` with ``covariances[k] = L_k @ L_k.T``; then the Mahalanobis term is
  ``|(x - mu_k) @ prec_chol[k]|^2``.
- ``log_det[k] = sum(log(diag(prec_chol[k]))) = -0.5 * log(det(covariances[k]))``.

Status codes returned by :func:`em_loop`: ``0`` converged, ``1`` hit ``max_iter``,
``2`` a free component lost its points (its index is returned; the caller removes it and
calls again).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from robot_change.mixture.em_background import (
    em_loop_background,
    em_step_background,
    responsibilities_background,
)
from robot_change.mixture.em_core import (
    _EPS10,
    BLOCK,
    EMPTY_MASS,
    LOG_2PI,
    SKIP_LOG,
    STATUS_CONVERGED,
    STATUS_EMPTY,
    STATUS_MAX_ITER,
    _accumulate,
    _block_row,
    _block_workspace,
    _finish,
    _finish_cov,
    _gauss_block,
    precision_cholesky,
)

__all__ = [
    "BLOCK",
    "EMPTY_MASS",
    "LOG_2PI",
    "SKIP_LOG",
    "STATUS_CONVERGED",
    "STATUS_EMPTY",
    "STATUS_MAX_ITER",
    "e_step",
    "em_loop",
    "em_loop_background",
    "em_step",
    "em_step_background",
    "log_prob_labels",
    "log_prob_samples",
    "m_step",
    "precision_cholesky",
    "responsibilities_background",
    "two_means",
]


@njit(cache=True, nogil=True)
def e_step(points, weights, means, prec_chol, log_det):
    """E-step in the log domain.

    Parameters
    ----------
    points : array, shape (N, 3)
    weights : array, shape (K,)
    means : array, shape (K, 3)
    prec_chol : array, shape (K, 3, 3)
    log_det : array, shape (K,)

    Returns
    -------
    log_resp : array, shape (N, K)
        Log responsibilities, ``log p(k | x_n)``.
    log_prob : array, shape (N,)
        ``log p(x_n)`` under the mixture (log-sum-exp over components).
    """
    n = points.shape[0]
    k_n = means.shape[0]
    log_w = np.log(weights)
    log_resp = np.empty((n, k_n))
    log_prob = np.empty(n)
    x0b, x1b, x2b, vb, _, const = _block_workspace(k_n, log_w, log_det)
    for b0 in range(0, n, BLOCK):
        nb = min(BLOCK, n - b0)
        _gauss_block(points, b0, nb, means, prec_chol, const, x0b, x1b, x2b, vb)
        for j in range(nb):
            i = b0 + j
            row = log_resp[i]
            best = _block_row(vb, j, row)
            s = 0.0
            for k in range(k_n):
                s += math.exp(row[k] - best)
            lp = best + math.log(s)
            log_prob[i] = lp
            for k in range(k_n):
                row[k] -= lp
    return log_resp, log_prob


@njit(cache=True, nogil=True)
def log_prob_samples(points, weights, means, prec_chol, log_det):
    """``log p(x_n)`` under the mixture, without storing responsibilities.

    Parameters
    ----------
    points : array, shape (N, 3)
    weights, means, prec_chol, log_det : as in :func:`e_step`

    Returns
    -------
    log_prob : array, shape (N,)
    """
    n = points.shape[0]
    k_n = means.shape[0]
    log_w = np.log(weights)
    row = np.empty(k_n)
    log_prob = np.empty(n)
    x0b, x1b, x2b, vb, _, const = _block_workspace(k_n, log_w, log_det)
    for b0 in range(0, n, BLOCK):
        nb = min(BLOCK, n - b0)
        _gauss_block(points, b0, nb, means, prec_chol, const, x0b, x1b, x2b, vb)
        for j in range(nb):
            i = b0 + j
            best = _block_row(vb, j, row)
            s = 0.0
            for k in range(k_n):
                t = row[k] - best
                if t >= -SKIP_LOG:
                    s += math.exp(t)
            log_prob[i] = best + math.log(s)
    return log_prob


@njit(cache=True, nogil=True)
def log_prob_labels(points, weights, means, prec_chol, log_det):
    """``log p(x_n)`` and the most probable component of each point, in one pass.

    Parameters
    ----------
    points : array, shape (N, 3)
    weights, means, prec_chol, log_det : as in :func:`e_step`

    Returns
    -------
    log_prob : array, shape (N,)
    labels : array of int64, shape (N,)
        ``argmax_k log p(k | x_n)`` (the first on ties, as ``numpy.argmax``).
    """
    n = points.shape[0]
    k_n = means.shape[0]
    log_w = np.log(weights)
    row = np.empty(k_n)
    log_prob = np.empty(n)
    labels = np.empty(n, dtype=np.int64)
    x0b, x1b, x2b, vb, _, const = _block_workspace(k_n, log_w, log_det)
    for b0 in range(0, n, BLOCK):
        nb = min(BLOCK, n - b0)
        _gauss_block(points, b0, nb, means, prec_chol, const, x0b, x1b, x2b, vb)
        for j in range(nb):
            i = b0 + j
            best = _block_row(vb, j, row)
            s = 0.0
            arg = -1
            for k in range(k_n):
                t = row[k] - best
                if arg < 0 and row[k] == best:
                    arg = k
                if t >= -SKIP_LOG:
                    s += math.exp(t)
            labels[i] = arg
            log_prob[i] = best + math.log(s)
    return log_prob, labels


@njit(cache=True, nogil=True)
def m_step(points, resp, reg_covar):
    """M-step from responsibilities (two passes per component, as scikit-learn).

    Parameters
    ----------
    points : array, shape (N, 3)
    resp : array, shape (N, K)
        Responsibilities (not logs).
    reg_covar : float
        Added to the diagonal of every covariance.

    Returns
    -------
    nk : array, shape (K,)
        Responsibility mass per component (plus 10 eps).
    means : array, shape (K, 3)
    covariances : array, shape (K, 3, 3)
    """
    n = points.shape[0]
    k_n = resp.shape[1]
    nk = np.zeros(k_n)
    means = np.zeros((k_n, 3))
    covs = np.zeros((k_n, 3, 3))
    for i in range(n):
        for k in range(k_n):
            r = resp[i, k]
            nk[k] += r
            means[k, 0] += r * points[i, 0]
            means[k, 1] += r * points[i, 1]
            means[k, 2] += r * points[i, 2]
    for k in range(k_n):
        nk[k] += _EPS10
        for a in range(3):
            means[k, a] /= nk[k]
    for i in range(n):
        for k in range(k_n):
            r = resp[i, k]
            d0 = points[i, 0] - means[k, 0]
            d1 = points[i, 1] - means[k, 1]
            d2 = points[i, 2] - means[k, 2]
            covs[k, 0, 0] += r * d0 * d0
            covs[k, 0, 1] += r * d0 * d1
            covs[k, 0, 2] += r * d0 * d2
            covs[k, 1, 1] += r * d1 * d1
            covs[k, 1, 2] += r * d1 * d2
            covs[k, 2, 2] += r * d2 * d2
    for k in range(k_n):
        _finish_cov(covs[k], nk[k], reg_covar)
    return nk, means, covs


@njit(cache=True, nogil=True)
def em_step(points, weights, means, prec_chol, log_det, reg_covar):
    """One fused EM iteration: E-step on the given parameters and the M-step statistics.

    The scatter is accumulated about the *old* means in one pass and corrected to the new
    means afterwards (``S = sum r d d^T / nk - e e^T`` with ``e`` the mean shift); the old mean
    is close to the new one, so there is no cancellation of large coordinates.

    Parameters
    ----------
    points : array, shape (N, 3)
    weights, means, prec_chol, log_det : the current parameters, as in :func:`e_step`
    reg_covar : float

    Returns
    -------
    mean_log_prob : float
        Mean log-likelihood per point of the *given* parameters.
    nk : array, shape (K,)
    new_means : array, shape (K, 3)
    new_covariances : array, shape (K, 3, 3)
    """
    n = points.shape[0]
    k_n = means.shape[0]
    log_w = np.log(weights)
    row = np.empty(k_n)
    nk = np.zeros(k_n)
    s1 = np.zeros((k_n, 3))
    s2 = np.zeros((k_n, 3, 3))
    total = 0.0
    x0b, x1b, x2b, vb, _, const = _block_workspace(k_n, log_w, log_det)
    for b0 in range(0, n, BLOCK):
        nb = min(BLOCK, n - b0)
        _gauss_block(points, b0, nb, means, prec_chol, const, x0b, x1b, x2b, vb)
        for j in range(nb):
            i = b0 + j
            x0 = points[i, 0]
            x1 = points[i, 1]
            x2 = points[i, 2]
            best = _block_row(vb, j, row)
            s = 0.0
            for k in range(k_n):
                t = row[k] - best
                if t < -SKIP_LOG:
                    row[k] = 0.0
                else:
                    e = math.exp(t)
                    row[k] = e
                    s += e
            total += best + math.log(s)
            _accumulate(x0, x1, x2, row, 1.0 / s, means, nk, 0, s1, s2)
    new_means = _finish(means, nk, 0, s1, s2, reg_covar)
    return total / n, nk, new_means, s2


@njit(cache=True, nogil=True)
def em_loop(points, weights, means, covariances, fixed, fix_weights, reg_covar, tol, max_iter):
    """EM to convergence of the mean log-likelihood per point.

    Each iteration evaluates the current parameters (E-step), updates them (M-step), and stops
    when the mean log-likelihood changed by less than ``tol`` -- the same order as
    scikit-learn's ``GaussianMixture.fit``, so the same start gives the same parameters.

    Parameters
    ----------
    points : array, shape (N, 3)
    weights : array, shape (K,)
    means : array, shape (K, 3)
    covariances : array, shape (K, 3, 3)
        Must be positive definite.
    fixed : array of bool, shape (K,)
        Components whose means and covariances are never changed.
    fix_weights : bool
        If True the fixed components keep their relative weights; only their total mass is
        re-estimated (the exact M-step for that constraint).
    reg_covar : float
        Covariance floor added to the diagonal in the M-step.
    tol : float
    max_iter : int

    Returns
    -------
    weights, means, covariances : the updated parameters (new arrays)
    mean_log_prob : float
        Mean log-likelihood per point of the parameters before the last M-step (-inf if
        no iteration ran).
    n_iter : int
    status : int
        ``STATUS_CONVERGED``, ``STATUS_MAX_ITER`` or ``STATUS_EMPTY``.
    empty : int
        Index of the free component that lost its points when ``status == STATUS_EMPTY``.
    """
    n = points.shape[0]
    k_n = weights.shape[0]
    w = weights.copy()
    mu = means.copy()
    cov = covariances.copy()
    fixed_w_total = 0.0
    for k in range(k_n):
        if fixed[k]:
            fixed_w_total += weights[k]
    prev = -np.inf
    lp = -np.inf
    it = 0
    while it < max_iter:
        prec, log_det, ok = precision_cholesky(cov)
        for k in range(k_n):
            if not ok[k]:  # rounding on a degenerate cloud: fall back to the diagonal
                for a in range(3):
                    for b in range(3):
                        if a != b:
                            cov[k, a, b] = 0.0
                    cov[k, a, a] = max(cov[k, a, a], reg_covar)
        if not ok.all():
            prec, log_det, ok = precision_cholesky(cov)
        lp, nk, new_mu, new_cov = em_step(points, w, mu, prec, log_det, reg_covar)
        it += 1
        fixed_mass = 0.0
        for k in range(k_n):
            if fixed[k]:
                fixed_mass += nk[k]
                continue
            if nk[k] < EMPTY_MASS:
                return w, mu, cov, lp, it, STATUS_EMPTY, k
            for a in range(3):  # element by element: an array-to-slice copy costs ~2 s of compile
                mu[k, a] = new_mu[k, a]
                for b in range(3):
                    cov[k, a, b] = new_cov[k, a, b]
        for k in range(k_n):
            if fixed[k] and fix_weights and fixed_w_total > 0.0:
                w[k] = weights[k] / fixed_w_total * fixed_mass / n
            else:
                w[k] = nk[k] / n
        w /= w.sum()
        if abs(lp - prev) < tol:
            return w, mu, cov, lp, it, STATUS_CONVERGED, -1
        prev = lp
    return w, mu, cov, lp, it, STATUS_MAX_ITER, -1


@njit(cache=True, nogil=True)
def two_means(points, c0, c1, n_lloyd, reg_covar):
    """Lloyd's two-means from the centres ``c0``, ``c1``, and the Gaussian of each half.

    At most ``n_lloyd`` updates of the centres (fewer when they stop moving); a point goes to
    the nearer centre (``x . (c1 - c0) > (|c1|^2 - |c0|^2) / 2``: the second).

    Parameters
    ----------
    points : array, shape (N, 3)
    c0, c1 : array, shape (3,)
    n_lloyd : int
    reg_covar : float
        Added to the diagonal of both covariances.

    Returns
    -------
    ok : bool
        False when a half is empty or has fewer than 2 points (the rest is then undefined).
    counts : array, shape (2,)
        Points per half (float).
    means : array, shape (2, 3)
    covariances : array, shape (2, 3, 3)
        Maximum-likelihood covariance of each half plus ``reg_covar`` on the diagonal.
    """
    n = points.shape[0]
    side = np.zeros(n, dtype=np.bool_)
    cen = np.empty((2, 3))
    for a in range(3):  # element by element: an array-to-slice copy costs ~2 s of compile
        cen[0, a] = c0[a]
        cen[1, a] = c1[a]
    counts = np.zeros(2)
    means = np.zeros((2, 3))
    covs = np.zeros((2, 3, 3))
    for it in range(n_lloyd + 1):
        d0 = cen[1, 0] - cen[0, 0]
        d1 = cen[1, 1] - cen[0, 1]
        d2 = cen[1, 2] - cen[0, 2]
        thr = 0.5 * (cen[1, 0] * cen[1, 0] + cen[1, 1] * cen[1, 1] + cen[1, 2] * cen[1, 2]
                     - cen[0, 0] * cen[0, 0] - cen[0, 1] * cen[0, 1] - cen[0, 2] * cen[0, 2])
        counts[:] = 0.0
        means[:, :] = 0.0
        for i in range(n):
            s = 1 if points[i, 0] * d0 + points[i, 1] * d1 + points[i, 2] * d2 > thr else 0
            side[i] = s == 1
            counts[s] += 1.0
            for a in range(3):
                means[s, a] += points[i, a]
        if counts[0] < 2.0 or counts[1] < 2.0:
            return False, counts, means, covs
        for h in range(2):
            for a in range(3):
                means[h, a] /= counts[h]
        if it == n_lloyd:
            break
        same = True
        for h in range(2):
            for a in range(3):
                if means[h, a] != cen[h, a]:
                    same = False
                cen[h, a] = means[h, a]
        if same:
            break
    for i in range(n):
        h = 1 if side[i] else 0
        e0 = points[i, 0] - means[h, 0]
        e1 = points[i, 1] - means[h, 1]
        e2 = points[i, 2] - means[h, 2]
        covs[h, 0, 0] += e0 * e0
        covs[h, 0, 1] += e0 * e1
        covs[h, 0, 2] += e0 * e2
        covs[h, 1, 1] += e1 * e1
        covs[h, 1, 2] += e1 * e2
        covs[h, 2, 2] += e2 * e2
    for h in range(2):
        _finish_cov(covs[h], counts[h], reg_covar)
    return True, counts, means, covs
