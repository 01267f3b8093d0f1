"""Fitting Gaussian mixtures to 3-D points: :func:`fit_mixture` (split-EM stopped by a
criterion) and :func:`fit_over_background` (EM of free components over a fixed mixture), and the
covariance floor they share.

:func:`fit_mixture` follows ALGORITHM.md section 2: start from K = 1 (or from a given
mixture), run EM, split the component with the largest weighted Gaussianity deficiency
``w_k * J_k`` into two along its principal axis, run EM over all components, and keep the split
only if the model-selection criterion (MDL, BIC or AIC) drops; otherwise try the next
candidate; stop when none helps or K reaches ``max_components``.

This module is also the face of the mixtures: the immutable :class:`Mixture` and its file
(:mod:`robot_change.mixture.gmm`) and the public names of the fit's parts --
:mod:`~robot_change.mixture.search` (the split search's state, EM runs and moves),
:mod:`~robot_change.mixture.refine` (split-and-merge moves at fixed K),
:mod:`~robot_change.mixture.criteria` (MDL / BIC / AIC), :mod:`~robot_change.mixture.fit_record`
(:class:`FitStep`, :class:`FitRecord`) -- are re-exported here: import them from this module.
Numeric: arrays in, arrays out (the only I/O is :meth:`Mixture.save` / :meth:`Mixture.load`).
The EM kernels are in :mod:`robot_change.mixture.em`.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np

from robot_change import validate
from robot_change.errors import ConvergenceWarning, InputError
from robot_change.mixture import em
from robot_change.mixture.criteria import CRITERIA, N_PARAMS_COMPONENT, criterion_value
from robot_change.mixture.fit_record import FitRecord, FitStep, _replace_accepted
from robot_change.mixture.gmm import FILE_FORMAT, FILE_VERSION, Mixture, _check_points
from robot_change.mixture.refine import (
    PARTIAL_MASS,
    REFINE_PAIRS,
    REFINE_START_ITER,
    REFINE_TRIES,
    _refine,
)
from robot_change.mixture.search import (
    LARGE_K,
    POLISH_GROWTH,
    SPLIT_BATCH_SHARE,
    _evaluate,
    _run_em,
    _seed_component,
    _split_order,
    _split_start,
    _State,
    _symmetric,
    component_of,
    gaussianity_deficiency,
    knn_entropy,
)

__all__ = [
    "CRITERIA",
    "FILE_FORMAT",
    "FILE_VERSION",
    "LARGE_K",
    "N_PARAMS_COMPONENT",
    "PARTIAL_MASS",
    "POLISH_GROWTH",
    "REFINE_PAIRS",
    "REFINE_START_ITER",
    "REFINE_TRIES",
    "SPLIT_BATCH_SHARE",
    "FitRecord",
    "FitStep",
    "Mixture",
    "component_of",
    "criterion_value",
    "fit_mixture",
    "fit_over_background",
    "gaussianity_deficiency",
    "knn_entropy",
    "reg_covar_for_leaf",
]

#: Default voxel leaf (m) the covariance floor is tied to when neither is given (the default
#: leaf of robot_change.cloud.chain.CloudParams).
DEFAULT_LEAF = 0.03


def reg_covar_for_leaf(leaf: float) -> float:
    """Covariance floor (m^2) for a cloud voxelised with ``leaf`` (m): ``leaf**2 / 12``.

    ``leaf**2 / 12`` is the variance of a uniform distribution over one voxel's width: the
    quantisation a voxel grid puts on every coordinate.  No structure finer than that is in
    the data, so no component needs to be thinner, and a plane (zero thickness in the ideal
    case) stays well-conditioned.
    """
    return validate.positive("reg_covar_for_leaf", "leaf", leaf, unit=" metres") ** 2 / 12.0


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
