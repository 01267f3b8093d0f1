"""The split search of :func:`robot_change.mixture.model.fit_mixture`: its working state
(:class:`_State`: weights (K,), means (K, 3) m, covariances (K, 3, 3) m^2, the fixed mask, the
cached deficiencies), its EM runs and their scoring by the criterion, and its moves: rank the
components by weighted Gaussianity deficiency ``w_k J_k`` (k-NN entropy), split a component
along an axis by two-means, seed a novelty component.  The gear constants of a large K are
here too; the public names are re-exported by :mod:`robot_change.mixture.model`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import digamma

from robot_change.errors import InputError
from robot_change.mixture import em
from robot_change.mixture.criteria import criterion_value

__all__ = [
    "LARGE_K",
    "POLISH_GROWTH",
    "SPLIT_BATCH_SHARE",
    "component_of",
    "gaussianity_deficiency",
    "knn_entropy",
]

#: Above this many free components (the default K bound) the fit changes gear, so that its
#: work grows linearly with the bound, not quadratically: a round of the split search first
#: tries splitting the K_free // SPLIT_BATCH_SHARE best-ranked components at once, and the
#: final EM runs first on random subsets POLISH_GROWTH, POLISH_GROWTH**2, ... times the search
#: subsample's size (while at most half the cloud), then on all points.
LARGE_K = 16
SPLIT_BATCH_SHARE = 8
POLISH_GROWTH = 4


# --------------------------------------------------------------------------- split choice


def knn_entropy(points: np.ndarray, k: int = 4, floor: float = 1e-9, queries=None) -> float:
    """Kozachenko–Leonenko k-nearest-neighbour estimate of differential entropy (nats).

    ``H = psi(n) - psi(k) + log(V_3) + (3/m) sum_i log(max(eps_i, floor))`` with ``eps_i`` the
    distance from query point i to its k-th neighbour among the n points and
    ``V_3 = 4 pi / 3``.

    Parameters
    ----------
    points : array, shape (n, 3), n > k
    k : int
    floor : float
        Smallest distance used (m): duplicate points would otherwise give log(0).
    queries : array of int, shape (m,), optional
        Indices of the points whose distances are averaged (default: all).  A random subset
        gives an unbiased estimate of the same average at the full density.
    """
    n = points.shape[0]
    if n <= k:
        raise InputError(f"k-NN entropy needs more than k = {k} points, got {n}")
    q = points if queries is None else points[queries]
    dist, _ = cKDTree(points).query(q, k=k + 1)
    eps = np.maximum(dist[:, k], floor)
    return float(digamma(n) - digamma(k) + math.log(4.0 * math.pi / 3.0)
                 + 3.0 * np.log(eps).mean())


def gaussianity_deficiency(points: np.ndarray, blur: float, k: int = 4, n_queries: int = 2000,
                           rng=None) -> float:
    """J = H_gauss - H_est of points blurred at scale ``blur``: how far they are from Gaussian.

    The points are blurred by isotropic Gaussian noise of standard deviation ``blur`` (m, the
    voxel size) first, then ``H_est`` is the k-NN entropy of the blurred points and
    ``H_gauss = 0.5 log((2 pi e)^3 det S)`` with S their sample covariance, the largest entropy
    any density with that covariance can have.  So J >= 0 up to estimation noise, J ~ 0 for
    Gaussian points, and J does not depend on the unit of length (unlike the paper's ratio of
    entropies).  Without the blur, a voxelised surface is 2-D at the scale of its k-th
    neighbour and the 3-D estimator overstates its entropy, making J of planes negative.

    Parameters
    ----------
    points : array, shape (n, 3), n > k
    blur : float
        Standard deviation of the blur (m), >= 0.
    n_queries : int
        At most this many points are queried (all points stay in the k-NN tree).
    rng : numpy Generator, optional
    """
    rng = np.random.default_rng(0) if rng is None else rng
    xb = points + rng.normal(0.0, blur, points.shape) if blur > 0 else points
    n = xb.shape[0]
    queries = None if n <= n_queries else rng.choice(n, n_queries, replace=False)
    cov = np.cov(xb, rowvar=False, bias=True)
    det = max(float(np.linalg.det(cov)), 1e-300)
    h_gauss = 0.5 * (3.0 * math.log(2.0 * math.pi * math.e) + math.log(det))
    return h_gauss - knn_entropy(xb, k, 1e-9 + 1e-3 * blur, queries)


def _split_component(x: np.ndarray, mean, cov, weight: float, reg_covar: float,
                     n_lloyd: int = 5, axis: int = -1):
    """Two-means split of one component's points along one of its axes.

    Parameters
    ----------
    x : array, shape (n, 3)
        Points hard-assigned to the component.
    mean : array, shape (3,)
    cov : array, shape (3, 3)
    weight : float
    axis : int
        Which eigenvector of ``cov`` the two seeds ``mean +- sqrt(lambda) v`` lie on, in
        ``numpy.linalg.eigh``'s increasing order: -1 the principal axis, 0 the thinnest (it
        separates two parallel sheets).

    Returns
    -------
    (weights (2,), means (2, 3), covariances (2, 3, 3)) or None when a half gets < 2 points.
    """
    lam, vec = np.linalg.eigh(cov)
    step = math.sqrt(max(lam[axis], 0.0)) * vec[:, axis]
    mean = np.asarray(mean, dtype=np.float64)
    ok, counts, mus, covs = em.two_means(x, mean - step, mean + step, n_lloyd, reg_covar)
    if not ok:
        return None
    return counts / len(x) * weight, mus, covs


# --------------------------------------------------------------------------- EM driver


@dataclass
class _State:
    """Mutable working copy of a mixture inside :func:`fit_mixture`.

    ``j`` caches each component's Gaussianity deficiency (NaN: not computed yet).
    """

    weights: np.ndarray
    means: np.ndarray
    covs: np.ndarray
    fixed: np.ndarray
    j: np.ndarray
    log_l: float = -np.inf
    crit: float = np.inf
    n_iter: int = 0
    converged: bool = True


def _run_em(x, st: _State, *, fix_weights, reg_covar, tol, max_iter) -> _State:
    """EM from ``st`` to convergence, removing free components that lose their points."""
    w, mu, cov, fixed, j = st.weights, st.means, st.covs, st.fixed, st.j
    total_iter = 0
    while True:
        w2, mu2, cov2, _, n_it, status, empty = em.em_loop(
            x, w, mu, cov, fixed, fix_weights, reg_covar, tol, max(max_iter - total_iter, 1))
        total_iter += n_it
        if status != em.STATUS_EMPTY:
            break
        keep = np.arange(len(w)) != empty
        w, mu, cov, fixed, j = w2[keep], mu2[keep], cov2[keep], fixed[keep], j[keep]
        w = w / w.sum()
    return _State(w2, mu2, cov2, fixed, j, n_iter=total_iter,
                  converged=status == em.STATUS_CONVERGED)


def _evaluate(x, st: _State, criterion, fix_weights, n_total):
    """Final E-step: fills ``st.log_l`` and ``st.crit``; returns hard labels (N,).

    With ``x`` a subsample of ``n_total`` points, log L is scaled to the whole cloud.
    """
    prec, log_det, _ = em.precision_cholesky(st.covs)
    log_prob, labels = em.log_prob_labels(x, st.weights, st.means, prec, log_det)
    st.log_l = float(log_prob.sum()) * (n_total / x.shape[0])
    st.crit = criterion_value(criterion, st.log_l, n_total, st.weights, st.fixed, fix_weights)
    return labels


# --------------------------------------------------------------------------- moves


def component_of(points: np.ndarray, reg_covar: float) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian of a group of points (M, 3), float64: (mean (3,), covariance (3, 3), the
    maximum-likelihood one plus ``reg_covar`` on the diagonal): how a new component is seeded,
    here and in robot_change.change.detect (novelty seeds)."""
    xs = np.asarray(points, dtype=np.float64)
    return xs.mean(axis=0), np.cov(xs, rowvar=False, bias=True) + reg_covar * np.eye(3)


def _seed_component(cur: _State, xs: np.ndarray, frac: float, reg_covar: float) -> _State:
    """``cur`` plus one free component on the points ``xs`` (weight ``frac``)."""
    mean, cov = component_of(xs, reg_covar)
    w = np.concatenate([cur.weights * (1.0 - frac), [frac]])
    return _State(w / w.sum(), np.vstack([cur.means, mean]),
                  np.concatenate([cur.covs, cov[None]]), np.append(cur.fixed, False),
                  np.append(cur.j, np.nan))


def _split_start(xs: np.ndarray, labels: np.ndarray, cur: _State, ks, reg_covar: float,
                 opts) -> _State | None:
    """Start of the EM after splitting each component of ``ks`` (sequence of indices), or None
    when none of them can be split.

    Each is split by two-means along its principal axis, then a local EM of the two halves on
    its hard-assigned points alone (cheap: n_k points, two components), so that the EM over
    all components starts close to its optimum and needs few iterations.  The split
    components' halves go last, in the order of ``ks``.
    """
    split = np.zeros(len(cur.weights), dtype=bool)
    ws, mus, covs = [], [], []
    for k in ks:
        xk = xs[labels == k]
        parts = _split_component(xk, cur.means[k], cur.covs[k], cur.weights[k], reg_covar)
        if parts is None:
            continue
        w2, mu2, cov2 = parts
        lw, lmu, lcov, _, _, status, _ = em.em_loop(
            xk, w2 / w2.sum(), mu2, cov2, np.zeros(2, dtype=bool), False, opts["reg_covar"],
            opts["tol"], opts["max_iter"])
        if status != em.STATUS_EMPTY:
            w2, mu2, cov2 = lw * cur.weights[k], lmu, lcov
        split[k] = True
        ws.append(w2)
        mus.append(mu2)
        covs.append(cov2)
    if not split.any():
        return None
    keep = ~split
    n_new = 2 * len(ws)
    return _State(np.concatenate([cur.weights[keep], *ws]), np.vstack([cur.means[keep], *mus]),
                  np.concatenate([cur.covs[keep], *covs]),
                  np.concatenate([cur.fixed[keep], np.zeros(n_new, dtype=bool)]),
                  np.concatenate([cur.j[keep], np.full(n_new, np.nan)]))


def _split_order(x, labels, cur: _State, min_points, entropy_k, subsample, blur, rng):
    """Free components with >= 2 * min_points points, by decreasing w_k * J_k.

    J_k is computed once per component, when it is first ranked, and cached in ``cur.j``:
    EM moves the other components only a little after a split.
    """
    counts = np.bincount(labels, minlength=len(cur.weights))
    scored = []
    for k in np.flatnonzero((counts >= 2 * min_points) & ~cur.fixed):
        if np.isnan(cur.j[k]):
            cur.j[k] = gaussianity_deficiency(x[labels == k], blur, entropy_k, subsample, rng)
        scored.append((-cur.weights[k] * cur.j[k], int(k)))
    scored.sort()
    return [k for _, k in scored]


def _symmetric(c: np.ndarray) -> np.ndarray:
    return 0.5 * (c + c.transpose(0, 2, 1))
