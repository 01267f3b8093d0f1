"""Numba kernels of EM for 3-D Gaussian mixtures with full covariances.

Every kernel is ``@njit(cache=True, nogil=True)``, single-threaded, without fastmath, and takes
and returns float64 arrays.  Each has a plain NumPy twin in ``tests/test_mixture.py``.

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

LOG_2PI = math.log(2.0 * math.pi)
#: A free component whose responsibility mass falls below this many points is removed.
EMPTY_MASS = 1e-3
#: In the fused EM step, terms below exp(-SKIP_LOG) of the largest are dropped: they are below
#: half an ulp of the normaliser (exp(-40) = 4e-18), so the log-likelihood does not change and
#: the responsibilities change by less than 1e-17 absolute.
SKIP_LOG = 40.0
_EPS10 = 10.0 * np.finfo(np.float64).eps  # as sklearn: keeps nk > 0 in the M-step

STATUS_CONVERGED = 0
STATUS_MAX_ITER = 1
STATUS_EMPTY = 2


@njit(cache=True, nogil=True)
def _chol3(c, out):
    """Lower Cholesky factor of one symmetric 3x3 matrix.

    Parameters
    ----------
    c : array, shape (3, 3)
    out : array, shape (3, 3), written with L (lower triangular, zeros above).

    Returns
    -------
    ok : bool
        False when ``c`` is not positive definite (``out`` is then undefined).
    """
    a00 = c[0, 0]
    if not a00 > 0.0:
        return False
    l00 = math.sqrt(a00)
    l10 = c[1, 0] / l00
    l20 = c[2, 0] / l00
    a11 = c[1, 1] - l10 * l10
    if not a11 > 0.0:
        return False
    l11 = math.sqrt(a11)
    l21 = (c[2, 1] - l20 * l10) / l11
    a22 = c[2, 2] - l20 * l20 - l21 * l21
    if not a22 > 0.0:
        return False
    l22 = math.sqrt(a22)
    out[0, 0] = l00
    out[0, 1] = 0.0
    out[0, 2] = 0.0
    out[1, 0] = l10
    out[1, 1] = l11
    out[1, 2] = 0.0
    out[2, 0] = l20
    out[2, 1] = l21
    out[2, 2] = l22
    return True


@njit(cache=True, nogil=True)
def precision_cholesky(covariances):
    """Precision Cholesky factors and their log-determinants.

    Parameters
    ----------
    covariances : array, shape (K, 3, 3)

    Returns
    -------
    prec_chol : array, shape (K, 3, 3)
        Upper triangular, ``inv(cholesky(cov)).T``.
    log_det : array, shape (K,)
        ``sum(log(diag(prec_chol)))`` = ``-0.5 * log det(cov)``.
    ok : array of bool, shape (K,)
        False where a covariance is not positive definite (its rows are then zero).
    """
    k_n = covariances.shape[0]
    prec = np.zeros((k_n, 3, 3))
    log_det = np.zeros(k_n)
    ok = np.ones(k_n, dtype=np.bool_)
    low = np.empty((3, 3))
    for k in range(k_n):
        if not _chol3(covariances[k], low):
            ok[k] = False
            continue
        # inverse of the lower factor, written transposed (upper)
        i00 = 1.0 / low[0, 0]
        i11 = 1.0 / low[1, 1]
        i22 = 1.0 / low[2, 2]
        i10 = -low[1, 0] * i00 * i11
        i21 = -low[2, 1] * i11 * i22
        i20 = -(low[2, 0] * i00 + low[2, 1] * i10) * i22
        prec[k, 0, 0] = i00
        prec[k, 1, 1] = i11
        prec[k, 2, 2] = i22
        prec[k, 0, 1] = i10
        prec[k, 1, 2] = i21
        prec[k, 0, 2] = i20
        log_det[k] = math.log(i00) + math.log(i11) + math.log(i22)
    return prec, log_det, ok


#: Points per block of :func:`_gauss_block`.
BLOCK = 128


@njit(cache=True, nogil=True)
def _block_workspace(k_n, log_w, log_det):
    """Buffers of :func:`_gauss_block` for K components: (x0, x1, x2) (BLOCK,) each, values
    (K, BLOCK), a row (K,), and ``log w_k + log_det_k`` (K,)."""
    const = np.empty(k_n)
    for k in range(k_n):
        const[k] = log_w[k] + log_det[k]
    return (np.empty(BLOCK), np.empty(BLOCK), np.empty(BLOCK), np.empty((k_n, BLOCK)),
            np.empty(k_n), const)


@njit(cache=True, nogil=True)
def _gauss_block(points, b0, m, means, prec, const, x0, x1, x2, v):
    """``v[k, j] = log w_k + log N(x_{b0+j} | mu_k, Sigma_k)`` for the ``m`` points from ``b0``
    and every k, component by component over a block of points held coordinate by coordinate
    (so the inner loop vectorises)."""
    for j in range(m):
        x0[j] = points[b0 + j, 0]
        x1[j] = points[b0 + j, 1]
        x2[j] = points[b0 + j, 2]
    for k in range(means.shape[0]):
        m0 = means[k, 0]
        m1 = means[k, 1]
        m2 = means[k, 2]
        p00 = prec[k, 0, 0]
        p01 = prec[k, 0, 1]
        p11 = prec[k, 1, 1]
        p02 = prec[k, 0, 2]
        p12 = prec[k, 1, 2]
        p22 = prec[k, 2, 2]
        c = const[k]
        vk = v[k]
        for j in range(m):
            d0 = x0[j] - m0
            d1 = x1[j] - m1
            d2 = x2[j] - m2
            y0 = d0 * p00
            y1 = d0 * p01 + d1 * p11
            y2 = d0 * p02 + d1 * p12 + d2 * p22
            vk[j] = c - 0.5 * (3.0 * LOG_2PI + y0 * y0 + y1 * y1 + y2 * y2)


@njit(cache=True, nogil=True)
def _block_row(v, j, row):
    """Copy column ``j`` of a block's values into ``row`` (K,); returns its max."""
    best = -np.inf
    for k in range(row.shape[0]):
        t = v[k, j]
        row[k] = t
        if t > best:
            best = t
    return best


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
def _finish_cov(c, nk, reg_covar):
    """Scale the upper triangle of accumulated scatter by 1/nk, mirror it, add the floor."""
    for a in range(3):
        for b in range(a, 3):
            c[a, b] /= nk
            c[b, a] = c[a, b]
        c[a, a] += reg_covar


@njit(cache=True, nogil=True, inline="always")
def _accumulate(x0, x1, x2, row, inv, means, nk, off, s1, s2):
    """Add one point's M-step sums: responsibility ``r = row[k] * inv`` of every component k
    (skipped when 0) into ``nk[off + k]``, and ``r d``, ``r d d^T`` (upper triangle), with
    ``d = x - means[k]`` the offset from the *old* mean, into ``s1[k]`` (K, 3), ``s2[k]``
    (K, 3, 3)."""
    for k in range(means.shape[0]):
        r = row[k] * inv
        if r == 0.0:
            continue
        d0 = x0 - means[k, 0]
        d1 = x1 - means[k, 1]
        d2 = x2 - means[k, 2]
        nk[off + k] += r
        s1[k, 0] += r * d0
        s1[k, 1] += r * d1
        s1[k, 2] += r * d2
        rd0 = r * d0
        rd1 = r * d1
        s2[k, 0, 0] += rd0 * d0
        s2[k, 0, 1] += rd0 * d1
        s2[k, 0, 2] += rd0 * d2
        s2[k, 1, 1] += rd1 * d1
        s2[k, 1, 2] += rd1 * d2
        s2[k, 2, 2] += r * d2 * d2


@njit(cache=True, nogil=True, inline="always")
def _finish(means, nk, off, s1, s2, reg_covar):
    """M-step from the sums of :func:`_accumulate`: adds 10 eps to ``nk[off + k]``, returns the
    new means (K, 3) and turns ``s2`` in place into the new covariances (scatter about the old
    mean corrected by the mean shift ``e``: ``S / nk - e e^T``, plus the floor)."""
    k_n = means.shape[0]
    new_means = np.empty((k_n, 3))
    for k in range(k_n):
        m = nk[off + k] + _EPS10
        nk[off + k] = m
        e0 = s1[k, 0] / m
        e1 = s1[k, 1] / m
        e2 = s1[k, 2] / m
        new_means[k, 0] = means[k, 0] + e0
        new_means[k, 1] = means[k, 1] + e1
        new_means[k, 2] = means[k, 2] + e2
        c = s2[k]
        _finish_cov(c, m, 0.0)
        c[0, 0] -= e0 * e0
        c[0, 1] -= e0 * e1
        c[0, 2] -= e0 * e2
        c[1, 1] -= e1 * e1
        c[1, 2] -= e1 * e2
        c[2, 2] -= e2 * e2
        c[1, 0] = c[0, 1]
        c[2, 0] = c[0, 2]
        c[2, 1] = c[1, 2]
        for a in range(3):
            c[a, a] += reg_covar
    return new_means


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
