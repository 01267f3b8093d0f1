"""Gaussian mixtures of 3-D points: the immutable :class:`Mixture`, and split-EM fitting.

:func:`fit_mixture` follows ALGORITHM.md section 2: start from K = 1 (or from a given
mixture), run EM, split the component with the largest weighted Gaussianity deficiency
``w_k * J_k`` into two along its principal axis, run EM over all components, and keep the split
only if the model-selection criterion (MDL, BIC or AIC) drops; otherwise try the next
candidate; stop when none helps or K reaches ``max_components``.

Numeric module: arrays in, arrays out; the only I/O is :meth:`Mixture.save` /
:meth:`Mixture.load`.  The EM kernels are in :mod:`robot_change.mixture.em`.
"""

from __future__ import annotations

import hashlib
import math
import time
import warnings
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import digamma

from robot_change import npzfile, validate
from robot_change.errors import ConvergenceWarning, InputError, MixtureFileError
from robot_change.mixture import em

__all__ = [
    "CRITERIA",
    "FitRecord",
    "FitStep",
    "Mixture",
    "criterion_value",
    "fit_mixture",
    "fit_over_background",
    "gaussianity_deficiency",
    "knn_entropy",
    "reg_covar_for_leaf",
]

CRITERIA = ("mdl", "bic", "aic")
FILE_FORMAT = "robot_change.mixture"
FILE_VERSION = 2  # 2: the checksum of robot_change.npzfile (1: of the arrays alone)
#: Free parameters of one full-covariance 3-D Gaussian (3 for the mean, 6 for the covariance).
N_PARAMS_COMPONENT = 9
#: Default voxel leaf (m) the covariance floor is tied to when neither is given (the default
#: leaf of robot_change.cloud.chain.CloudParams).
DEFAULT_LEAF = 0.03
#: Above this many free components (the default K bound) the fit changes gear, so that its
#: work grows linearly with the bound, not quadratically: a round of the split search first
#: tries splitting the K_free // SPLIT_BATCH_SHARE best-ranked components at once, and the
#: final EM runs first on random subsets POLISH_GROWTH, POLISH_GROWTH**2, ... times the search
#: subsample's size (while at most half the cloud), then on all points.
LARGE_K = 16
SPLIT_BATCH_SHARE = 8
POLISH_GROWTH = 4


def reg_covar_for_leaf(leaf: float) -> float:
    """Covariance floor (m^2) for a cloud voxelised with ``leaf`` (m): ``leaf**2 / 12``.

    ``leaf**2 / 12`` is the variance of a uniform distribution over one voxel's width: the
    quantisation a voxel grid puts on every coordinate.  No structure finer than that is in
    the data, so no component needs to be thinner, and a plane (zero thickness in the ideal
    case) stays well-conditioned.
    """
    return validate.positive("reg_covar_for_leaf", "leaf", leaf, unit=" metres") ** 2 / 12.0


# --------------------------------------------------------------------------- the Mixture


def _check_points(points, name: str = "points") -> np.ndarray:
    """(N, 3) finite float64 copy-free view of ``points``; InputError otherwise."""
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric (N, 3) array: {exc}") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise InputError(f"{name} is empty: a mixture needs at least one point")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr).all(axis=1)).sum())
        raise InputError(f"{name} has {bad} rows with NaN or inf; drop them first "
                         f"(points[np.isfinite(points).all(axis=1)])")
    return np.ascontiguousarray(arr)


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64, order="C", copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Mixture:
    """A Gaussian mixture in 3-D: ``sum_k w_k N(x | mu_k, Sigma_k)``.

    Attributes
    ----------
    weights : array, shape (K,)
        Non-negative, summing to 1.
    means : array, shape (K, 3)
    covariances : array, shape (K, 3, 3)
        Symmetric positive definite.
    record : FitRecord or None
        How :func:`fit_mixture` made it (not saved to file, not part of equality).

    The arrays are float64 read-only copies.
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    record: FitRecord | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        w = _readonly(self.weights)
        mu = _readonly(self.means)
        cov = _readonly(self.covariances)
        if w.ndim != 1 or w.shape[0] < 1:
            raise InputError(f"weights must have shape (K,) with K >= 1, got {w.shape}")
        k = w.shape[0]
        if mu.shape != (k, 3):
            raise InputError(f"means must have shape ({k}, 3), got {mu.shape}")
        if cov.shape != (k, 3, 3):
            raise InputError(f"covariances must have shape ({k}, 3, 3), got {cov.shape}")
        for name, a in (("weights", w), ("means", mu), ("covariances", cov)):
            if not np.isfinite(a).all():
                raise InputError(f"{name} contain NaN or inf")
        if (w < 0).any() or abs(w.sum() - 1.0) > 1e-9:
            raise InputError(f"weights must be >= 0 and sum to 1, got sum {w.sum():.12g}, "
                             f"min {w.min():.3g}; normalise them (w / w.sum())")
        asym = np.abs(cov - cov.transpose(0, 2, 1)).max(axis=(1, 2))
        scale = np.abs(cov).max(axis=(1, 2))
        if (asym > 1e-12 * np.maximum(scale, 1e-300)).any():
            raise InputError("covariances must be symmetric; symmetrise them "
                             "(0.5 * (C + C.transpose(0, 2, 1)))")
        _, _, ok = em.precision_cholesky(np.array(cov))  # writable: one compiled type
        if not ok.all():
            bad = np.flatnonzero(~ok).tolist()
            raise InputError(f"covariances of components {bad} are not positive definite; "
                             "add a floor to their diagonal (reg_covar)")
        object.__setattr__(self, "weights", w)
        object.__setattr__(self, "means", mu)
        object.__setattr__(self, "covariances", cov)

    @property
    def n_components(self) -> int:
        """K, the number of components."""
        return int(self.weights.shape[0])

    @cached_property
    def _kernel_args(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(weights, means, precision Cholesky factors, their log-determinants): private
        writable copies, the array types the fit's own calls give the kernels (a read-only
        array would be another compile)."""
        prec, log_det, _ = em.precision_cholesky(np.array(self.covariances))
        return np.array(self.weights), np.array(self.means), prec, log_det

    def score_samples(self, points) -> np.ndarray:
        """Log density of each point under the mixture.

        Parameters
        ----------
        points : array, shape (N, 3)

        Returns
        -------
        log_prob : array, shape (N,)
        """
        return em.log_prob_samples(_check_points(points), *self._kernel_args)

    def score(self, points) -> float:
        """Mean log-likelihood per point (scikit-learn's ``GaussianMixture.score``)."""
        return float(self.score_samples(points).mean())

    def log_responsibilities(self, points) -> np.ndarray:
        """``log p(k | x_n)``, shape (N, K)."""
        log_resp, _ = em.e_step(_check_points(points), *self._kernel_args)
        return log_resp

    def responsibilities(self, points) -> np.ndarray:
        """Posterior probability of each component for each point, shape (N, K)."""
        return np.exp(self.log_responsibilities(points))

    def predict(self, points) -> np.ndarray:
        """Index of the most probable component for each point, shape (N,), int64 (the first
        on ties)."""
        return em.log_prob_labels(_check_points(points), *self._kernel_args)[1]

    def transformed(self, transform: np.ndarray) -> Mixture:
        """The mixture moved by the (4, 4) rigid ``transform``: means ``R mu + t``,
        covariances ``R Sigma R^T``, weights kept (the density of the moved points)."""
        T = np.asarray(transform, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError("transform must be a finite (4, 4) rigid transform")
        R, t = T[:3, :3], T[:3, 3]
        cov = np.einsum("ij,kjl,ml->kim", R, np.asarray(self.covariances), R)
        return Mixture(np.asarray(self.weights).copy(), np.asarray(self.means) @ R.T + t,
                       (cov + cov.transpose(0, 2, 1)) / 2.0)

    def log_likelihood(self, points) -> float:
        """Total log-likelihood ``sum_n log p(x_n)``."""
        return float(self.score_samples(points).sum())

    # ----------------------------------------------------------------------- files

    def save(self, path) -> None:
        """Write to ``path`` (a robot_change.npzfile: arrays ``weights``, ``means``,
        ``covariances``, a JSON header with K and the criterion the fit used, if known, and a
        SHA-256 over both), atomically."""
        npzfile.write(path, FILE_FORMAT, FILE_VERSION,
                      {"weights": self.weights, "means": self.means,
                       "covariances": self.covariances},
                      {"n_components": self.n_components,
                       "criterion": self.record.criterion if self.record is not None else None},
                      compress=False)

    @classmethod
    def load(cls, path) -> Mixture:
        """Read a mixture written by :meth:`save` (version 1 files too); verify format, version
        and checksum.

        Raises
        ------
        MixtureFileError
            Unreadable or truncated file, another format, a newer version, a checksum that
            does not match, or arrays that do not form a valid mixture.
        FileNotFoundError
            ``path`` does not exist.
        """
        path = Path(path)
        redo = "fit and save the mixture again"
        header, arrays = npzfile.read(path, FILE_FORMAT, FILE_VERSION,
                                      ("weights", "means", "covariances"), MixtureFileError,
                                      redo, verify=_verify)
        try:
            mixture = cls(arrays["weights"], arrays["means"], arrays["covariances"])
        except InputError as exc:
            raise MixtureFileError(f"{path}: the arrays do not form a valid mixture ({exc}); "
                                   f"{redo}") from exc
        if header.get("n_components") != mixture.n_components:
            raise MixtureFileError(f"{path}: header says K = {header.get('n_components')}, "
                                   f"arrays hold {mixture.n_components}; {redo}")
        return mixture


def _verify(header: dict, arrays: dict[str, np.ndarray]) -> bool:
    """The checksum of a mixture file: robot_change.npzfile's since version 2; version 1 hashed
    the three arrays alone (as float64, little-endian)."""
    if header.get("version") == 1:
        h = hashlib.sha256()
        for name in ("weights", "means", "covariances"):
            h.update(np.ascontiguousarray(arrays[name], dtype="<f8").tobytes())
        return header.get("sha256") == h.hexdigest()
    return header.get("sha256") == npzfile.checksum(header, arrays)


# --------------------------------------------------------------------------- fit record


@dataclass(frozen=True)
class FitStep:
    """One EM run inside :func:`fit_mixture`.

    ``action`` is ``"start"`` (the initial EM), ``"split k"`` (component k of the current
    mixture was split; ``"split i,j,..."`` when several were split in one round), ``"seed"``
    (a novelty component was added), ``"refine"`` (EM on the refinement subset before the
    split-and-merge moves) and ``"refine i+j/k"`` (components i and j merged and k split, at
    the same K), ``"polish m"`` (EM on a random subset of m points, coarse to fine, after the
    search), ``"polish"`` (the final EM on all points after a search on a subsample) or
    ``"prune"`` (free components left with fewer than ``min_points`` points of mass by the
    polish were dropped and EM run again); ``accepted`` says whether the result became the
    current mixture.
    """

    action: str
    n_components: int
    criterion: float
    log_likelihood: float
    n_iter: int
    converged: bool
    accepted: bool
    seconds: float


@dataclass(frozen=True)
class FitRecord:
    """How a mixture was fitted: settings, every EM run, and the totals.

    ``n_pruned``: free components dropped after the polish because they held fewer than
    ``min_points`` points of mass (0 when nothing was dropped, and in records written before
    the prune existed).
    """

    criterion: str
    n_points: int
    reg_covar: float
    max_components: int
    steps: tuple[FitStep, ...]
    n_iter: int
    seconds: float
    stop_reason: str
    n_pruned: int = 0

    @property
    def k_tried(self) -> tuple[int, ...]:
        """K of every EM run, in order."""
        return tuple(s.n_components for s in self.steps)


# --------------------------------------------------------------------------- criteria


def _n_free_weights(k: int, n_fixed: int, fix_weights: bool) -> int:
    if fix_weights and n_fixed > 0:
        return (k - n_fixed) + 1 - 1
    return k - 1


def criterion_value(name: str, log_likelihood: float, n_points: int, weights,
                    fixed=None, fix_weights: bool = False) -> float:
    """Model-selection criterion L_SC = -log L + P(K); smaller is better.

    Parameters
    ----------
    name : {"mdl", "bic", "aic"}
    log_likelihood : float
        Total log-likelihood ``sum_n log p(x_n)``.
    n_points : int
        N.
    weights : array, shape (K,)
    fixed : array of bool, shape (K,), optional
        Components given, not estimated: their 9 parameters are not counted (nor their
        weights when ``fix_weights``).

    Returns
    -------
    float
        AIC = -2 log L + 2p; BIC = -2 log L + p ln N; MDL (Figueiredo & Jain) = -log L +
        (Np/2) sum_k log(N w_k / 12) + (K/2) log(N/12) + K (Np + 1)/2, with p = 10K - 1 and
        Np = 9 when no component is fixed.
    """
    w = np.asarray(weights, dtype=np.float64)
    k = w.shape[0]
    fixed = np.zeros(k, dtype=bool) if fixed is None else np.asarray(fixed, dtype=bool)
    n_fixed = int(fixed.sum())
    k_free = k - n_fixed
    p = N_PARAMS_COMPONENT * k_free + _n_free_weights(k, n_fixed, fix_weights)
    n = float(n_points)
    if name == "aic":
        return -2.0 * log_likelihood + 2.0 * p
    if name == "bic":
        return -2.0 * log_likelihood + p * math.log(n)
    if name == "mdl":
        k_w = _n_free_weights(k, n_fixed, fix_weights) + 1
        nw = np.maximum(n * w[~fixed], 1e-300)
        return (-log_likelihood + 0.5 * N_PARAMS_COMPONENT * float(np.log(nw / 12.0).sum())
                + 0.5 * k_w * math.log(n / 12.0) + 0.5 * (N_PARAMS_COMPONENT * k_free + k_w))
    raise InputError(f"criterion must be one of {CRITERIA}, got {name!r}")


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


def fit_mixture(
    points,
    criterion: str = "mdl",
    init: Mixture | None = None,
    *,
    leaf: float = DEFAULT_LEAF,
    reg_covar: float | None = None,
    max_components: int = 16,
    tol: float = 1e-3,
    max_iter: int = 100,
    seed: int = 0,
    fixed=None,
    fix_weights: bool = False,
    novelty=None,
    split: bool = True,
    min_points: int = 10,
    max_tries: int = 3,
    entropy_k: int = 4,
    entropy_subsample: int = 2000,
    search_points: int | None = 2000,
    refine: int = 12,
    refine_points: int | None = 4000,
    refine_tol: float = 1e-4,
    refine_iter: int = 20,
) -> Mixture:
    """Fit a Gaussian mixture to 3-D points by split-EM, choosing K by a criterion.

    Parameters
    ----------
    points : array, shape (N, 3)
        Finite coordinates (m).
    criterion : {"mdl", "bic", "aic"}
    init : Mixture, optional
        Start EM from this mixture instead of K = 1 (e.g. the station's reference).
    leaf : float
        Voxel size of the cloud (m); sets ``reg_covar = leaf**2 / 12`` when that is None.
    reg_covar : float, optional
        Covariance floor (m^2) added to every covariance's diagonal in the M-step.  The blur
        of the Gaussianity deficiency is ``sqrt(12 reg_covar)`` (= leaf).
    max_components : int
        Bound on K: no split once K reaches it.
    tol : float
        EM stops when the mean log-likelihood per point changes by less than this.
    max_iter : int
        Bound on the iterations of each EM run; reaching it warns (ConvergenceWarning).
    seed : int
        Seed of the random subsets (entropy estimate, search subsample); same seed, same fit.
    fixed : "init", array of bool (K_init,) or of int indices, optional
        Components of ``init`` held fixed: their means and covariances never change, and
        they are never split (background for novelty components, ALGORITHM.md section 3).
    fix_weights : bool
        Fixed components also keep their relative weights (only their total is re-estimated).
    novelty : array of bool, shape (N,), optional
        Points the start explains poorly: one free component is seeded from their mean and
        covariance and kept if the criterion prefers it; splitting then refines it.
    split : bool
        If False, only run EM from the start (fixed K).
    min_points : int
        A component is a split candidate only with >= 2 * min_points hard-assigned points, and a
        split is rejected if any free component ends with fewer than ``min_points`` (N w_k).
        After the polish on all points (see ``search_points``) the same rule is enforced again:
        free components below it are dropped and EM is re-run (``"prune"`` steps; fixed
        components are never dropped).
    max_tries : int
        Single splits tried per round (in order of w_k J_k) before the search stops.  Above
        ``LARGE_K`` (16) free components, a round first splits the best-ranked
        K_free // ``SPLIT_BATCH_SHARE`` (8) components at once (``"split i,j,..."`` steps),
        so that the search's EM work grows linearly with ``max_components``, not
        quadratically; the single splits follow when that batch does not lower the criterion.
    entropy_k, entropy_subsample : int
        k of the k-NN entropy estimate, and the most query points per component.
    search_points : int, optional
        If set and N is larger, the split search runs on a fixed random subset of this many
        points (log L scaled to N in the criterion, the entropy blur scaled by
        sqrt(N / search_points)), and a final EM on all points polishes the chosen mixture.
        With more than ``LARGE_K`` free components it runs coarse to fine: first on random
        subsets ``POLISH_GROWTH`` (4) times larger than the search's, and so on while at most
        half the cloud (``"polish m"`` steps).
        None: the search uses every point (exact, about 5x slower on a room-sized cloud).
        Ignored when ``split`` is False.
    refine : int
        Budget of split-and-merge moves at the K the search chose (Ueda et al.'s SMEM; 0: none;
        bench/bench_mixture_quality.py measures what they gain).  A move merges two
        components i, j and splits a third, k, so K does not change.  Each round ranks the
        candidates by an estimated gain -- the log-likelihood a local EM of k's best split
        adds to k's points (two-means along k's largest axis or a cut across its smallest),
        minus what one Gaussian loses on the points of i and j, from hard assignments --
        over the ``REFINE_PAIRS`` most overlapping pairs and every k, and tries the best
        ``REFINE_TRIES`` in turn: a partial EM of the three new components with all others
        held fixed, on the points the replaced ones explain, then the criterion on the
        refinement subset.  The first that lowers it by more than ``refine_tol * N`` is kept
        and a new round starts; the moves stop when a round keeps none or ``refine`` were
        tried.  Skipped when starting from ``init`` or with ``split`` False.  ``"refine"``
        steps in the record.
    refine_points : int, optional
        The moves run on a fixed random subset of this many points (None or N smaller: all),
        after ``REFINE_START_ITER`` EM iterations there.
    refine_tol, refine_iter :
        EM tolerance and iteration bound of the local and partial EMs of the moves (a tighter
        tolerance than ``tol``: a move's gain shows only once EM has moved its components;
        hitting ``refine_iter`` does not warn).

    Returns
    -------
    Mixture
        With ``.record`` (a :class:`FitRecord`).
    """
    t_start = time.perf_counter()
    x = _check_points(points)
    n = x.shape[0]
    validate.choice("fit_mixture", "criterion", criterion, CRITERIA)
    if reg_covar is None:
        reg_covar = reg_covar_for_leaf(leaf)
    validate.positive("fit_mixture", "reg_covar", reg_covar,
                      unit=" m^2 (leaf**2/12 of the voxel size is the usual choice)")
    for name, v, lo in (("max_components", max_components, 1), ("max_iter", max_iter, 1),
                        ("min_points", min_points, 1), ("max_tries", max_tries, 1),
                        ("entropy_k", entropy_k, 1), ("entropy_subsample", entropy_subsample, 8),
                        ("search_points", 100 if search_points is None else search_points, 100),
                        ("refine", refine, 0), ("refine_iter", refine_iter, 1),
                        ("refine_points", 100 if refine_points is None else refine_points, 100)):
        validate.whole("fit_mixture", name, v, lo, 2**63 - 1)
    validate.number("fit_mixture", "tol", tol, 0.0, math.inf)
    validate.number("fit_mixture", "refine_tol", refine_tol, 0.0, math.inf)
    rng = np.random.default_rng(seed)
    opts = dict(fix_weights=bool(fix_weights), reg_covar=float(reg_covar), tol=float(tol),
                max_iter=int(max_iter))
    blur = math.sqrt(12.0 * reg_covar)
    steps: list[FitStep] = []

    if init is None:
        if fixed is not None:
            raise InputError("fixed needs init: there are no given components to hold fixed")
        cov = np.cov(x, rowvar=False, bias=True) if n > 1 else np.zeros((3, 3))
        cov = 0.5 * (cov + cov.T) + reg_covar * np.eye(3)
        st = _State(np.ones(1), x.mean(axis=0)[None, :], cov[None], np.zeros(1, dtype=bool),
                    np.full(1, np.nan))
    else:
        if not isinstance(init, Mixture):
            raise InputError(f"init must be a Mixture, got {type(init).__name__}")
        st = _State(np.array(init.weights), np.array(init.means), np.array(init.covariances),
                    _fixed_mask(fixed, init.n_components), np.full(init.n_components, np.nan))
    mask = None
    if novelty is not None:
        mask = np.asarray(novelty)
        if mask.dtype != bool or mask.shape != (n,):
            raise InputError(f"novelty must be a boolean mask of shape ({n},), "
                             f"got {mask.dtype} {mask.shape}")

    xs = x
    if split and search_points is not None and n > search_points:
        sub = np.sort(rng.choice(n, search_points, replace=False))
        xs = x[sub]
        mask = None if mask is None else mask[sub]
        blur *= math.sqrt(n / search_points)  # a surface subsample is a coarser voxel grid

    def run(state: _State, action: str, data=xs) -> tuple[_State, np.ndarray]:
        t0 = time.perf_counter()
        out = _run_em(data, state, **opts)
        labels = _evaluate(data, out, criterion, fix_weights, n)
        steps.append(FitStep(action, len(out.weights), out.crit, out.log_l, out.n_iter,
                             out.converged, False, time.perf_counter() - t0))
        return out, labels

    def accept():
        steps[-1] = _replace_accepted(steps[-1])

    cur, labels = run(st, "start")
    accept()
    if mask is not None and mask.sum() >= 2:
        seeded = _seed_component(cur, xs[mask], mask.mean(), reg_covar)
        cand, cand_labels = run(seeded, "seed")
        if cand.crit < cur.crit:
            accept()
            cur, labels = cand, cand_labels

    stop = "split disabled" if not split else "no split lowers the criterion"
    while split:
        if len(cur.weights) >= max_components:
            stop = f"K reached max_components = {max_components}"
            break
        order = _split_order(xs, labels, cur, min_points, entropy_k, entropy_subsample, blur, rng)
        if not order:
            stop = "no component has enough points to split"
            break
        # A large mixture splits several components per round (its EM work then grows
        # linearly with the bound, not quadratically); if the batch does not lower the
        # criterion, single splits are tried as for a small one.
        k_free = int((~cur.fixed).sum())
        n_batch = min(k_free // SPLIT_BATCH_SHARE if k_free > LARGE_K else 1,
                      max_components - len(cur.weights))
        tries = ([order[:n_batch]] if n_batch > 1 else []) + [[k] for k in order[:max_tries]]
        improved = False
        for ks in tries:
            start = _split_start(xs, labels, cur, ks, reg_covar, opts)
            if start is None:
                continue
            cand, cand_labels = run(start, "split " + ",".join(str(k) for k in ks))
            free_mass = n * cand.weights[~cand.fixed]
            if cand.crit < cur.crit and (free_mass >= min_points).all():
                accept()
                cur, labels = cand, cand_labels
                improved = True
                break
        if not improved:
            break

    refined = split and refine > 0 and init is None and len(cur.weights) >= 3
    if refined:
        xr = x
        if refine_points is not None and n > refine_points:
            xr = x[np.sort(rng.choice(n, refine_points, replace=False))]
        cur = _refine(xr, cur, n, criterion, refine, float(refine_tol), int(refine_iter),
                      reg_covar, opts, min_points, steps)

    n_pruned = 0
    if xs is not x or refined:
        # Coarse to fine for a large mixture: EM on nested random subsets growing by
        # POLISH_GROWTH before all points, so that most of the way from the search's fit
        # (long with many components on a small search subsample) is made where an
        # iteration is cheap.
        if (~cur.fixed).sum() > LARGE_K:
            perm = rng.permutation(n)
            size = len(xs) * POLISH_GROWTH
            while size <= n // 2:
                cur, _ = run(cur, f"polish {size}", x[np.sort(perm[:size])])
                accept()
                size *= POLISH_GROWTH
        cur, _ = run(cur, "polish", x)
        accept()
        # The search kept every free component at >= min_points of mass on a subsample, but
        # the polish on all points can leave some below it (high max_components, small
        # subsample).  Drop those, renormalise and re-run EM until none is left; each round
        # removes at least one component, so this ends.
        while True:
            keep = cur.fixed | (n * cur.weights >= min_points)
            if keep.all():
                break
            if not keep.any():  # never drop everything: keep the heaviest free component
                keep[int(np.argmax(cur.weights))] = True
                if keep.all():
                    break
            w = cur.weights[keep]
            start = _State(w / w.sum(), cur.means[keep], cur.covs[keep], cur.fixed[keep],
                           cur.j[keep])
            k_before = len(cur.weights)
            cur, _ = run(start, "prune", x)
            accept()
            n_pruned += k_before - len(cur.weights)  # incl. any the re-run EM emptied
    n_iter = sum(s.n_iter for s in steps)
    unconverged = sum(not s.converged for s in steps if not s.action.startswith("refine"))
    if unconverged:
        warnings.warn(f"EM reached max_iter = {max_iter} without converging to tol = {tol} in "
                      f"{unconverged} of {len(steps)} runs; "
                      f"the result is the last iterate. Raise max_iter or tol.",
                      ConvergenceWarning, stacklevel=2)
    record = FitRecord(criterion, n, float(reg_covar), int(max_components), tuple(steps), n_iter,
                       time.perf_counter() - t_start, stop, n_pruned)
    return Mixture(cur.weights / cur.weights.sum(), cur.means, _symmetric(cur.covs), record)


def fit_over_background(points, background: Mixture, log_background, weights, means,
                        covariances, *, leaf: float = DEFAULT_LEAF,
                        reg_covar: float | None = None, tol: float = 1e-3, max_iter: int = 100,
                        criterion: str = "mdl") -> Mixture:
    """EM of free components over a background mixture held fixed, weights and all.

    The same fit as ``fit_mixture(points, init=<background's components, then the free
    ones>, fixed=<the background's>, fix_weights=True, split=False)`` -- the background keeps
    its means, covariances and relative weights, only its total weight is re-estimated --
    but the background enters through its log-density at each point, computed once by the
    caller, so an EM iteration costs N x K_free instead of N x (K_background + K_free).
    Novelty components over a station's reference (robot_change.change.detect) are fitted
    this way.

    Parameters
    ----------
    points : array, shape (N, 3)
    background : Mixture
        The fixed components (its weights sum to 1).
    log_background : array, shape (N,)
        ``background.score_samples(points)``.
    weights : array, shape (1 + K,)
        Start: the background's total weight, then the free components' (summing to 1).
    means : array, shape (K, 3)
    covariances : array, shape (K, 3, 3)
        The free components' start (positive definite).
    leaf, reg_covar, tol, max_iter, criterion :
        As :func:`fit_mixture`.

    Returns
    -------
    Mixture
        The background's components first (weights scaled by its fitted total), then the
        free components that kept their points (a free component that loses them is removed
        and EM goes on, as :func:`fit_mixture` does); ``.record`` with one ``"start"`` step,
        whose log-likelihood is that of the last E-step (within ``tol`` x N of the returned
        parameters': no extra pass over the points).
    """
    t_start = time.perf_counter()
    x = _check_points(points)
    n = x.shape[0]
    if not isinstance(background, Mixture):
        raise InputError(f"background must be a Mixture, got {type(background).__name__}")
    log_bg = np.ascontiguousarray(log_background, dtype=np.float64)
    w = np.array(weights, dtype=np.float64)
    mu = np.array(means, dtype=np.float64).reshape(-1, 3)
    cov = np.array(covariances, dtype=np.float64).reshape(-1, 3, 3)
    if log_bg.shape != (n,) or w.shape != (1 + len(mu),) or len(cov) != len(mu):
        raise InputError(f"log_background ({n},), weights (1 + K,), means (K, 3) and "
                         f"covariances (K, 3, 3) must agree, got {log_bg.shape}, {w.shape}, "
                         f"{mu.shape} and {cov.shape}")
    validate.choice("fit_over_background", "criterion", criterion, CRITERIA)
    if reg_covar is None:
        reg_covar = reg_covar_for_leaf(leaf)
    total_iter = 0
    status = em.STATUS_CONVERGED
    log_l = float(log_bg.sum())  # with no free component left: the background alone
    while len(mu):
        w2, mu2, cov2, lp, n_it, status, empty = em.em_loop_background(
            x, log_bg, w, mu, cov, float(reg_covar), float(tol), max(max_iter - total_iter, 1),
            False)
        total_iter += n_it
        if status != em.STATUS_EMPTY:
            w, mu, cov, log_l = w2, mu2, cov2, float(lp) * n
            break
        keep = np.arange(len(mu)) != empty
        w = np.concatenate([w2[:1], w2[1:][keep]])
        w, mu, cov = w / w.sum(), mu2[keep], cov2[keep]
    if not len(mu):
        w = np.ones(1)
    k0 = background.n_components
    weights_all = np.concatenate([background.weights * w[0], w[1:]])
    fixed = np.arange(k0 + len(mu)) < k0
    seconds = time.perf_counter() - t_start
    step = FitStep("start", len(weights_all), criterion_value(criterion, log_l, n, weights_all,
                                                              fixed, True),
                   log_l, total_iter, status != em.STATUS_MAX_ITER, True, seconds)
    if status == em.STATUS_MAX_ITER:
        warnings.warn(f"EM reached max_iter = {max_iter} without converging to tol = {tol}; "
                      f"the result is the last iterate. Raise max_iter or tol.",
                      ConvergenceWarning, stacklevel=2)
    record = FitRecord(criterion, n, float(reg_covar), len(weights_all), (step,), total_iter,
                       seconds, "split disabled")
    return Mixture(weights_all / weights_all.sum(), np.vstack([background.means, mu]),
                   _symmetric(np.concatenate([background.covariances, cov])), record)


def _symmetric(c: np.ndarray) -> np.ndarray:
    return 0.5 * (c + c.transpose(0, 2, 1))


def _replace_accepted(step: FitStep) -> FitStep:
    d = dict(step.__dict__)
    d["accepted"] = True
    return FitStep(**d)


def _fixed_mask(fixed, k: int) -> np.ndarray:
    """Boolean (K,) mask from None, "init", a boolean mask or indices."""
    if fixed is None:
        return np.zeros(k, dtype=bool)
    if isinstance(fixed, str):
        if fixed != "init":
            raise InputError(f'fixed must be "init", a boolean mask or indices, got {fixed!r}')
        return np.ones(k, dtype=bool)
    arr = np.asarray(fixed)
    if arr.dtype == bool:
        if arr.shape != (k,):
            raise InputError(f"fixed mask must have shape ({k},), got {arr.shape}")
        return arr.copy()
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer) or (arr < 0).any() or \
            (arr >= k).any():
        raise InputError(f"fixed indices must be integers in [0, {k}), got {fixed!r}")
    mask = np.zeros(k, dtype=bool)
    mask[arr] = True
    return mask


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


def _merged(cur: _State, i: int, j: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Moment-matched merge of components i and j: (weight, mean, covariance)."""
    wi, wj = cur.weights[i], cur.weights[j]
    w = wi + wj
    mu = (wi * cur.means[i] + wj * cur.means[j]) / w
    di, dj = cur.means[i] - mu, cur.means[j] - mu
    cov = (wi * (cur.covs[i] + np.outer(di, di)) + wj * (cur.covs[j] + np.outer(dj, dj))) / w
    return w, mu, _symmetric(cov[None])[0]


#: Split-and-merge moves (``refine`` of :func:`fit_mixture`): the most overlapping pairs
#: considered for a merge in a round, the moves tried per round (largest estimated gain
#: first), the EM iterations on the refinement subset before the moves, and the
#: responsibility mass above which a point takes part in a move's partial EM.
REFINE_PAIRS = 8
REFINE_TRIES = 4
REFINE_START_ITER = 5
PARTIAL_MASS = 1e-3


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
        for (i, j), loss in zip(pairs.tolist(), losses):
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
