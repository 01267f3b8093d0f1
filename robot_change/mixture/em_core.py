"""The pieces every EM kernel shares (numba): constants and status codes, the precision
Cholesky factors of the components, the Gaussian log-densities of a block of points, and the
sums of the fused M-step.

The kernels themselves are in :mod:`robot_change.mixture.em` (plain mixtures) and
:mod:`robot_change.mixture.em_background` (over a fixed background density); both build on these.
Every function here is ``@njit(cache=True, nogil=True)`` (the M-step sums also
``inline="always"``), single-threaded, without fastmath, on float64 arrays; ``prec_chol`` and
``log_det`` as in :mod:`robot_change.mixture.em`'s conventions, points (N, 3) in metres.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = [
    "BLOCK",
    "EMPTY_MASS",
    "LOG_2PI",
    "SKIP_LOG",
    "STATUS_CONVERGED",
    "STATUS_EMPTY",
    "STATUS_MAX_ITER",
    "precision_cholesky",
]

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
