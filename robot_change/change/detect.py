"""Change detection: what appeared and what disappeared between a reference scene and now.

ALGORITHM.md section 3, as we built and measured it (docs/algorithm.md, "Change detection";
numbers in docs/evaluation.md).  For what appeared (current points):

1. **Free-space check** against the reference depth image: a current point is a candidate only
   if the reference saw *through* it at the majority of its pixels -- its nearest reading
   within a few pixels (pose tolerance) is farther by a depth-dependent margin; where it has no
   reading, the farthest reading around a shadow or dropout stands in; with none at all,
   "no reading" counts as seen through.
2. **Novelty components.**  The reference mixture is held fixed (means, covariances and
   relative weights) as the background model of the current cloud; current points it explains
   poorly (log-density below a low quantile of the reference's own points) or that the
   reference saw through seed new free components, one per connected group on the voxel grid,
   and EM fits them (:func:`robot_change.mixture.model.fit_mixture` with ``fixed=`` and
   ``fix_weights=True``).
3. **Greedy EMD** (reference -> current) over the novelty components, with an explicit
   acceptance rule on its trajectory.  Computed and reported always; it decides only with
   ``greedy=True`` (off by default: measured to lose real changes, docs/evaluation.md).
4. **Segmentation**: a point is changed when the posterior mass of the change components at it
   exceeds ``posterior_threshold`` (0.5) and it passed the free-space check.
5. **Objects completed** (:func:`robot_change.change.objects.complete_objects`): a surface
   segment of the depth image that the changed points make up ``object_min_share`` of is
   claimed whole (a moved object stands partly where it stood); then, with both directions
   done, a segment that stands where a changed surface of the other epoch stood
   (:func:`robot_change.change.objects.claim_counterparts`).
6. **Regions**: connected components on the voxel grid (26-neighbourhood of voxel keys), kept
   only where they hold enough core evidence; regions below ``min_region_points`` points or
   ``min_region_extent_m`` long dropped.

The mirror (disappeared: reference points) runs the same steps with the roles swapped: the
reference cloud against the current's mixture held fixed, the free-space check against the
current depth image.

Each ingredient can be switched off (:class:`ChangeParams`) so it can be measured.  The
baselines (the plain method, the nearest-neighbour threshold, the geometric check) are
:func:`detect_plain`, :func:`detect_nn_threshold` and :func:`detect_geometric`.

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.  Kernels are
``@njit(cache=True, nogil=True)`` with NumPy twins in ``tests/test_change.py``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from hw.depth import Intrinsics
from robot_change.change.baselines import detect_plain
from robot_change.change.compare import (
    Aligned,
    Current,
    Direction,
    Reference,
    align,
    direction_free,
    direction_regions,
    finish,
    fit_own,
    geometric_filters,
    not_at_station_result,
)
from robot_change.change.epoch import Epoch, kept
from robot_change.change.greedy import greedy_trace, posteriors
from robot_change.change.objects import claim_counterparts, complete_objects
from robot_change.change.parallel import both
from robot_change.change.params import ChangeParams
from robot_change.change.regions import in_groups_of, label_voxel_components
from robot_change.change.results import ChangeSet
from robot_change.errors import InputError
from robot_change.mixture.model import (
    Mixture,
    component_of,
    fit_mixture,
    fit_over_background,
)

__all__ = [
    "detect_changes",
]


def _current_mixture(cur: Epoch, ref: Epoch, ref_mix: Mixture, params: ChangeParams,
                     seen_through: np.ndarray) -> Mixture:
    """The current's mixture for the mirror when the current came without one.

    ``seen_through`` (M,) bool: the reference's points the current camera sees through (the
    disappeared direction's free-space check)."""
    if params.current_mixture == "fit":
        return fit_own(cur, params)
    # EM from the reference mixture, every component free, no splits: the reference's
    # components follow the current cloud
    step = 1
    if params.current_fit_points and cur.n_points > params.current_fit_points:
        step = -(-cur.n_points // params.current_fit_points)
    mix = fit_mixture(cur.points[::step], init=ref_mix, leaf=cur.leaf_m, seed=params.seed,
                      split=False, tol=params.novelty_tol)
    # a removed object's component need not die: EM may pull it onto what the object hid,
    # where it still explains the object's rear points.  A component of the current whose
    # reference points (each to its most probable component) the current camera mostly sees
    # through is no surface of the current: it goes
    gone = _components_seen_through(ref, mix, seen_through, params.gone_component_share)
    if gone.any() and not gone.all():
        keep = ~gone
        mix = Mixture(mix.weights[keep] / mix.weights[keep].sum(), mix.means[keep],
                      mix.covariances[keep])
    return mix


def _components_seen_through(ref: Epoch, mix: Mixture, seen_through: np.ndarray,
                             share: float, max_points: int = 4000) -> np.ndarray:
    """(K,) bool: components of ``mix`` more than ``share`` of whose reference points are
    ``seen_through`` (M,) bool; each point goes to its most probable component, on a fixed
    stride subsample of at most ``max_points`` of the reference's points."""
    step = max(1, -(-ref.n_points // max_points))
    labels = mix.predict(ref.points[::step])
    k = mix.n_components
    total = np.bincount(labels, minlength=k)
    through = np.bincount(labels[seen_through[::step]], minlength=k)
    return through > share * np.maximum(total, 1)


def _novelty_seeds(other: Epoch, novel: np.ndarray, params: ChangeParams
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One new component per connected group (on the voxel grid) of novel points of
    ``other`` with at least ``min_region_points`` points, largest first, at most
    ``max_novelty_components``: their weights (G,) (share of ``other``'s points), means
    (G, 3) and covariances (G, 3, 3) (:func:`robot_change.mixture.model.component_of`)."""
    idx = np.flatnonzero(novel)
    groups = []
    if idx.size:
        labels = label_voxel_components(other.keys[idx], params.region_connectivity)
        sizes = np.bincount(labels)
        for lab in np.argsort(-sizes, kind="stable")[:params.max_novelty_components]:
            if sizes[lab] < max(params.min_region_points, 4):
                break
            groups.append(idx[labels == lab])
    if not groups:
        return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3))
    reg = other.leaf_m ** 2 / 12.0
    means, covs = zip(*(component_of(other.points[g], reg) for g in groups), strict=True)
    return np.array([len(g) / other.n_points for g in groups]), np.array(means), np.array(covs)


def _novelty_fit(base_mix: Mixture, other: Epoch, log_dens: np.ndarray, novel: np.ndarray,
                 params: ChangeParams) -> tuple[Mixture, bool]:
    """The searched mixture: ``base_mix`` held fixed as the background of ``other``'s cloud,
    plus novelty components seeded from the novel points (:func:`_novelty_seeds`) and fitted
    by EM.  Returns (mixture, whether its first K_base components are the background held
    with its weights, so that ``log_dens`` is their log-density)."""
    k0 = base_mix.n_components
    w_new, means, covs = _novelty_seeds(other, novel, params)
    if not len(w_new) and params.novelty_fix_weights:
        # no group of novel points to seed: with the fixed components' weights held, EM has
        # nothing to estimate, so the searched mixture is the base mixture itself
        return base_mix, True
    if params.novelty_fix_weights and not params.novelty_split:
        return fit_over_background(other.points, base_mix, log_dens,
                                   np.concatenate([[1.0 - w_new.sum()], w_new]), means, covs,
                                   leaf=other.leaf_m, tol=params.novelty_tol), True
    weights = np.concatenate([base_mix.weights * (1.0 - w_new.sum()), w_new])
    init = Mixture(weights / weights.sum(), np.vstack([base_mix.means, means]),
                   np.concatenate([base_mix.covariances, covs]))
    fixed = np.arange(init.n_components) < k0
    return fit_mixture(other.points, init=init, fixed=fixed,
                       fix_weights=params.novelty_fix_weights, leaf=other.leaf_m,
                       seed=params.seed, split=params.novelty_split, tol=params.novelty_tol,
                       max_components=k0 + params.max_novelty_components), \
        params.novelty_fix_weights


def _self_threshold(base: Epoch, base_mix: Mixture, quantile: float) -> float:
    """The ``quantile`` of ``base_mix``'s log-density on ``base``'s own points (a fixed
    stride subsample of <= 4000); kept in ``base.derived`` when ``base_mix`` is the epoch's
    own mixture (a rigid move changes neither)."""
    step = max(1, base.n_points // 4000)

    def make() -> float:
        return float(np.quantile(base_mix.score_samples(base.points[::step]), quantile))

    if base_mix is not base.mixture:
        return make()
    return kept(base.derived, ("self_log_density_quantile", quantile), make)


def _novelty_direction(kind, base: Epoch, other: Epoch, base_mix: Mixture, params: ChangeParams,
                       timings: dict, prefix: str, free: np.ndarray, observed: np.ndarray):
    """Changed points of ``other`` relative to ``base``: the mixture part.

    ``base_mix`` (fitted on ``base``) is held fixed as the background of ``other``'s cloud;
    novelty components for poorly explained points; greedy EMD base -> other over them.  A
    point is a candidate when the accepted components hold most of its posterior, or, where
    the base explains it less than its own points (log-density below the self threshold),
    most of the novelty components' share.
    Returns (candidate mask (M,), searched mixture, posterior (M, K) of its novelty
    components (the fixed ones' columns may be 0) or None when no component is a change,
    trace).
    """
    t0 = time.perf_counter()
    thr = _self_threshold(base, base_mix, params.novelty_quantile)
    log_dens = base_mix.score_samples(other.points)
    novel = log_dens < thr
    if params.novelty_seed == "density+free_space":
        novel |= free
    novel &= observed  # what the base's camera could not see is no evidence of novelty
    t1 = time.perf_counter()
    k0 = base_mix.n_components
    fitted, background = _novelty_fit(base_mix, other, log_dens, novel, params)
    t2 = time.perf_counter()
    candidates = np.zeros(fitted.n_components, dtype=bool)
    candidates[k0:] = True
    trace = greedy_trace(base_mix, fitted, candidates, other.n_points, params)
    t3 = time.perf_counter()
    post = None
    cand = np.zeros(other.n_points, dtype=bool)
    if trace.change.size:
        # posteriors only where they can matter: with the free-space check on, a point it
        # rejects is never changed, so its posterior is not computed (left 0)
        rows = np.flatnonzero(free) if params.free_space else None
        post = posteriors(fitted, other.points, rows, (k0, log_dens) if background else None)
        cand = post[:, trace.change].sum(axis=1) > params.posterior_threshold
        # where the fixed components explain a point less than they explain their own points
        # (log-density below the self threshold), they do not compete for it: a narrow fixed
        # component 15 cm away would win the posterior from a wide novelty one by default
        lost = np.flatnonzero(novel & (log_dens < thr) & (free if params.free_space else True))
        if lost.size and fitted.weights[k0:].sum() > 0:
            part = Mixture(fitted.weights[k0:] / fitted.weights[k0:].sum(), fitted.means[k0:],
                           fitted.covariances[k0:])
            share = part.responsibilities(other.points[lost])[:, trace.change - k0].sum(axis=1)
            cand[lost[share > params.posterior_threshold]] = True
    t4 = time.perf_counter()
    timings[f"{prefix}novelty_mask_ms"] = (t1 - t0) * 1e3
    timings[f"{prefix}novelty_fit_ms"] = (t2 - t1) * 1e3
    timings[f"{prefix}greedy_ms"] = (t3 - t2) * 1e3
    timings[f"{prefix}segment_ms"] = (t4 - t3) * 1e3
    return cand, fitted, post, trace


def _counterparts(aligned: Aligned, app: Direction, dis: Direction, params: ChangeParams,
                  timings: dict) -> tuple[Direction, Direction]:
    """Both directions with the surfaces that stand where the other epoch's changed surfaces
    stood (:func:`robot_change.change.objects.claim_counterparts`), each judged against the
    other's changed points as completed, timed as ``counterparts_ms``."""
    t0 = time.perf_counter()
    reg = aligned.registration
    ref_from_cur = None if reg.is_identity else reg.T_ref_from_cur
    cur_from_ref = None if reg.is_identity else reg.inverse()
    app_changed = claim_counterparts(aligned.cur, app.changed, app.observed, aligned.ref,
                                     dis.changed, ref_from_cur, params)
    dis_changed = claim_counterparts(aligned.ref, dis.changed, dis.observed, aligned.cur,
                                     app.changed, cur_from_ref, params)
    timings["counterparts_ms"] = (time.perf_counter() - t0) * 1e3
    return (dataclasses.replace(app, changed=app_changed),
            dataclasses.replace(dis, changed=dis_changed))


#: the default parameters (frozen, built once)
_DEFAULT_PARAMS = ChangeParams()


def detect_changes(reference: Reference, current: Current,
                   params: ChangeParams = _DEFAULT_PARAMS, *,
                   intrinsics: Intrinsics | None = None,
                   initial_pose: np.ndarray | None = None) -> ChangeSet:
    """What appeared and what disappeared between the station's reference and now.

    The current view is first registered to the reference
    (:func:`robot_change.change.registration.register_depth`, ``params.registration``); when the
    registration fails or the offset is beyond the station tolerance, the outcome is
    ``"not_at_station"`` and nothing is compared.  Otherwise both directions are compared in
    the current camera frame.

    Parameters
    ----------
    reference : SceneModel or Epoch
        The station's reference (fused depth, intrinsics, clean cloud, mixture).
    current : SceneModel, Epoch, or (H, W) uint16 depth array
        A depth array is cleaned with the reference's CloudParams (``intrinsics``: the
        reference's when not given; they must match).
    params : ChangeParams
        ``novelty=False`` runs the plain method (:func:`detect_plain`).
    initial_pose : (4, 4), optional
        Where registration starts (``T_ref_from_cur``; the identity by default: the robot
        believes it is at its station).  WATCH passes the last check's estimate.

    Returns
    -------
    ChangeSet

    Raises
    ------
    SceneMismatchError (robot_change.change.scene)
        Other image size, intrinsics or cloud parameters than the reference.
    EmptySceneError (robot_change.errors)
        Either clean cloud has fewer than ``params.min_cloud_points`` points: the camera sees
        nothing to compare.  Deliberately an error, not a "no change" result: with no
        readings we cannot tell an unchanged room from something right in front of the lens
        (nearer than the sensor's minimum range), a covered lens or a dead camera.  The
        caller decides (watch mode: a fault, pause the base).
    """
    if not isinstance(params, ChangeParams):
        raise InputError(f"params must be a ChangeParams, got {type(params).__name__}")
    if not params.novelty:
        return detect_plain(reference, current, params, intrinsics=intrinsics)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    aligned = align(reference, current, params, intrinsics, timings, initial_pose,
                    free_space=False)
    if not aligned.at_station:
        return not_at_station_result("novelty", params, aligned, timings, t_start)
    ref, cur = aligned.ref, aligned.cur
    ref_mix = ref.mixture
    if ref_mix is None:
        t0 = time.perf_counter()
        ref_mix = fit_own(ref, params)
        timings["reference_fit_ms"] = (time.perf_counter() - t0) * 1e3

    def appeared() -> Direction:
        free, observed, core = direction_free(aligned, "appeared", params, timings)
        cand, mix, post, trace = _novelty_direction("appeared", ref, cur, ref_mix, params,
                                                    timings, "appeared_", free, observed)
        cand = geometric_filters(cur, ref, cand, params, timings, "appeared_", free, observed)
        t0 = time.perf_counter()
        cand = in_groups_of(cur, cand, core if params.free_space else cand,
                            params.evidence_min_points, params.region_connectivity)
        cand = complete_objects(cur, cand, observed, params)
        timings["appeared_objects_ms"] = (time.perf_counter() - t0) * 1e3
        return Direction(cand, post, mix, trace, observed)

    def disappeared() -> tuple[Direction | None, int]:
        if not params.disappeared:
            return None, 0
        free, observed, core = direction_free(aligned, "disappeared", params, timings)
        cur_mix = cur.mixture
        if cur_mix is None:
            t0 = time.perf_counter()
            cur_mix = _current_mixture(cur, ref, ref_mix, params, free)
            timings["current_fit_ms"] = (time.perf_counter() - t0) * 1e3
        cand, mix, post, trace = _novelty_direction("disappeared", cur, ref, cur_mix, params,
                                                    timings, "disappeared_", free, observed)
        cand = geometric_filters(ref, cur, cand, params, timings, "disappeared_", free,
                                 observed)
        t0 = time.perf_counter()
        cand = in_groups_of(ref, cand, core if params.free_space else cand,
                            params.evidence_min_points, params.region_connectivity)
        cand = complete_objects(ref, cand, observed, params)
        timings["disappeared_objects_ms"] = (time.perf_counter() - t0) * 1e3
        return Direction(cand, post, mix, trace, observed), cur_mix.n_components

    threads = params.threads if params.disappeared else 1
    app, (dis, k_cur) = both(appeared, disappeared, threads)
    if dis is not None:
        app, dis = _counterparts(aligned, app, dis, params, timings)

    def grouped(kind: str, epoch: Epoch, direction: Direction) -> Callable[[], Direction]:
        def run() -> Direction:
            t0 = time.perf_counter()
            out = dataclasses.replace(
                direction, regions=direction_regions(kind, epoch, direction, params))
            timings[f"{kind}_regions_ms"] = (time.perf_counter() - t0) * 1e3
            return out
        return run

    app, dis = both(grouped("appeared", cur, app),
                    (lambda: None) if dis is None else grouped("disappeared", ref, dis),
                    threads)
    return finish("novelty", params, aligned, app, dis, ref_mix.n_components, k_cur, timings,
                   t_start)
