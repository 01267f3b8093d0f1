"""EM kernels (numba) over a fixed background density: the fused step, the loop to
convergence and the responsibilities of ``w_0 exp(log_bg[n]) + sum_k w_k N(x_n | mu_k,
Sigma_k)`` (the novelty fits over a station's reference, whose log-density ``log_bg`` (N,)
is computed once).

Counterparts of ``em_step`` and ``em_loop`` of :mod:`robot_change.mixture.em` (which
re-exports these; the docstrings below name its ``e_step``, ``em_step``, ``em_loop``), built on
:mod:`robot_change.mixture.em_core`.  Points (N, 3) in metres, float64 arrays,
``@njit(cache=True, nogil=True)``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from robot_change.mixture.em_core import (
    _EPS10,
    BLOCK,
    EMPTY_MASS,
    SKIP_LOG,
    STATUS_CONVERGED,
    STATUS_EMPTY,
    STATUS_MAX_ITER,
    _accumulate,
    _block_row,
    _block_workspace,
    _finish,
    _gauss_block,
    precision_cholesky,
)

__all__ = ["em_loop_background", "em_step_background", "responsibilities_background"]


@njit(cache=True, nogil=True)
def em_step_background(points, log_bg, weights, means, prec_chol, log_det, reg_covar):
    """:func:`em_step` for a mixture whose first term is a fixed background density.

    The mixture is ``w_0 exp(log_bg[n]) + sum_k w_k N(x_n | mu_k, Sigma_k)``: the background
    (e.g. the station's reference mixture, held fixed with its relative weights) enters only
    through its per-point log-density, so an iteration costs N x K_free, not N x (K_fixed +
    K_free).

    Parameters
    ----------
    points : array, shape (N, 3)
    log_bg : array, shape (N,)
        Log-density of each point under the background (its weights summing to 1).
    weights : array, shape (1 + K,)
        ``weights[0]``: the background's total weight; then the free components'.
    means, prec_chol, log_det : the K free components, as in :func:`e_step`
    reg_covar : float

    Returns
    -------
    mean_log_prob : float
    nk : array, shape (1 + K,)
        Responsibility mass (plus 10 eps), the background's first.
    new_means : array, shape (K, 3)
    new_covariances : array, shape (K, 3, 3)
    """
    n = points.shape[0]
    k_n = means.shape[0]
    log_w = np.log(weights[1:])
    log_w0 = math.log(weights[0]) if weights[0] > 0.0 else -np.inf
    row = np.empty(k_n)
    nk = np.zeros(k_n + 1)
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
            v0 = log_w0 + log_bg[i]
            if v0 > best:
                best = v0
            e0 = 0.0 if v0 - best < -SKIP_LOG else math.exp(v0 - best)
            s = e0
            for k in range(k_n):
                t = row[k] - best
                if t < -SKIP_LOG:
                    row[k] = 0.0
                else:
                    e = math.exp(t)
                    row[k] = e
                    s += e
            total += best + math.log(s)
            inv = 1.0 / s
            nk[0] += e0 * inv
            _accumulate(x0, x1, x2, row, inv, means, nk, 1, s1, s2)
    nk[0] += _EPS10
    new_means = _finish(means, nk, 1, s1, s2, reg_covar)
    return total / n, nk, new_means, s2


@njit(cache=True, nogil=True)
def em_loop_background(points, log_bg, weights, means, covariances, reg_covar, tol, max_iter,
                       fix_background=False):
    """:func:`em_loop` over a fixed background density (:func:`em_step_background`).

    The same iterations as :func:`em_loop` with the background's components fixed and
    ``fix_weights``: the background keeps its shape and only its total weight ``weights[0]``
    is re-estimated; the K free components are fitted.  Parameters and returns as
    :func:`em_loop`, with ``weights`` (1 + K,) (the background's first) and ``means``,
    ``covariances`` those of the free components; ``empty`` is the index of a free component
    among them (0-based, without the background).

    ``fix_background``: the background's total weight stays ``weights[0]`` too, and the free
    components share ``1 - weights[0]`` in proportion to their responsibility mass -- the
    partial EM of a split-and-merge move (Ueda et al.), which may then run on only the points
    the free components explain.
    """
    n = points.shape[0]
    k_n = means.shape[0]
    w = weights.copy()
    mu = means.copy()
    cov = covariances.copy()
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
        lp, nk, new_mu, new_cov = em_step_background(points, log_bg, w, mu, prec, log_det,
                                                     reg_covar)
        it += 1
        free_mass = 0.0
        for k in range(k_n):
            if nk[k + 1] < EMPTY_MASS:
                return w, mu, cov, lp, it, STATUS_EMPTY, k
            for a in range(3):  # element by element: an array-to-slice copy costs ~2 s of compile
                mu[k, a] = new_mu[k, a]
                for b in range(3):
                    cov[k, a, b] = new_cov[k, a, b]
            free_mass += nk[k + 1]
        if fix_background:
            for k in range(k_n):
                w[k + 1] = (1.0 - weights[0]) * nk[k + 1] / free_mass
        else:
            for k in range(k_n + 1):
                w[k] = nk[k] / n
            w /= w.sum()
        if abs(lp - prev) < tol:
            return w, mu, cov, lp, it, STATUS_CONVERGED, -1
        prev = lp
    return w, mu, cov, lp, it, STATUS_MAX_ITER, -1


@njit(cache=True, nogil=True)
def responsibilities_background(points, log_bg, weights, means, prec_chol, log_det):
    """Responsibilities (N, 1 + K) under ``w_0 exp(log_bg) + sum_k w_k N_k`` (column 0 the
    background's) and ``log p(x_n)`` (N,); arguments as :func:`em_step_background`."""
    n = points.shape[0]
    k_n = means.shape[0]
    log_w = np.log(weights[1:])
    log_w0 = math.log(weights[0]) if weights[0] > 0.0 else -np.inf
    row = np.empty(k_n)
    resp = np.zeros((n, k_n + 1))
    log_prob = np.empty(n)
    x0b, x1b, x2b, vb, _, const = _block_workspace(k_n, log_w, log_det)
    for b0 in range(0, n, BLOCK):
        nb = min(BLOCK, n - b0)
        _gauss_block(points, b0, nb, means, prec_chol, const, x0b, x1b, x2b, vb)
        for j in range(nb):
            i = b0 + j
            best = _block_row(vb, j, row)
            v0 = log_w0 + log_bg[i]
            if v0 > best:
                best = v0
            e0 = 0.0 if v0 - best < -SKIP_LOG else math.exp(v0 - best)
            s = e0
            for k in range(k_n):
                t = row[k] - best
                row[k] = 0.0 if t < -SKIP_LOG else math.exp(t)
                s += row[k]
            log_prob[i] = best + math.log(s)
            inv = 1.0 / s
            resp[i, 0] = e0 * inv
            for k in range(k_n):
                resp[i, k + 1] = row[k] * inv
    return resp, log_prob
