"""What every method shares: the two epochs of a check aligned in the current camera frame
(registration, the station test, the reference moved, the free-space checks both ways), the
observed / free-space / nearest-neighbour filters of a direction's candidates, and the
ChangeSet made from the two directions (regions, masks, the unobserved share).
"""

from __future__ import annotations

import dataclasses
import time
from typing import TypeAlias

import numpy as np
from scipy.spatial import cKDTree

from hw.depth import Intrinsics
from robot_change.change.blind import unread_share
from robot_change.change.epoch import (
    Epoch,
    as_epoch,
    check_current_depth,
    check_pair,
    check_scene_models,
    clean_current,
    current_epoch,
    kept,
)
from robot_change.change.free_space import (
    FreeSpace,
    free_and_observed,
    free_space_views,
)
from robot_change.change.limits import DetectionLimit, detection_limit
from robot_change.change.parallel import both
from robot_change.change.params import ChangeParams
from robot_change.change.regions import group_regions, pixel_mask
from robot_change.change.registration import (
    Registration,
    register_depth,
    transform_points,
)
from robot_change.change.results import ChangeSet, GreedyTrace
from robot_change.change.scene import SceneModel
from robot_change.errors import EmptySceneError
from robot_change.mixture.model import Mixture, fit_mixture

__all__ = [
    "Aligned",
    "Current",
    "Direction",
    "Reference",
    "align",
    "direction_free",
    "direction_regions",
    "finish",
    "fit_own",
    "geometric_filters",
    "nn_far",
    "not_at_station_result",
    "reference_limit",
    "timed_free",
]


#: What a comparison takes as the reference, and as now (a depth array: (H, W) uint16 mm).
Reference: TypeAlias = "SceneModel | Epoch"
Current: TypeAlias = "SceneModel | Epoch | np.ndarray"


@dataclasses.dataclass(frozen=True, eq=False)
class Direction:
    """One direction's result: candidate mask (M,) bool, posteriors (M, K) of the searched
    mixture (or None), that mixture, its greedy trace, the observed mask, and its regions
    when the direction grouped them itself (None: :func:`finish` groups them)."""

    changed: np.ndarray
    posterior: np.ndarray | None
    mixture: Mixture | None
    trace: GreedyTrace | None
    observed: np.ndarray
    regions: tuple | None = None


def direction_regions(kind: str, epoch: Epoch, direction: Direction, params: ChangeParams
                      ) -> tuple:
    """The direction's changed points of ``epoch`` grouped into regions
    (:func:`robot_change.change.regions.group_regions`)."""
    return group_regions(kind, epoch, direction.changed, params, direction.posterior,
                         direction.trace.change if direction.trace is not None else None)


@dataclasses.dataclass(frozen=True, eq=False)
class Aligned:
    """The two epochs of a check in the current camera frame: ``ref`` with its points (and
    mixture) mapped through the registration, ``cur`` as it is; ``registration``; ``reason``
    why this is not the station ("" when it is); the free-space results (free, observed) of
    the current's points and, when the disappeared direction runs, of the reference's."""

    ref: Epoch
    cur: Epoch
    registration: Registration
    reason: str = ""
    free_cur: np.ndarray | None = None
    observed_cur: np.ndarray | None = None
    free_ref: np.ndarray | None = None
    observed_ref: np.ndarray | None = None

    @property
    def at_station(self) -> bool:
        return not self.reason


def fit_own(ep: Epoch, params: ChangeParams) -> Mixture:
    return fit_mixture(ep.points, leaf=ep.leaf_m, seed=params.seed)


def align(reference: Reference, current: Current, params: ChangeParams,
           intrinsics: Intrinsics | None, timings: dict, initial_pose: np.ndarray | None = None,
           free_space: bool = True) -> Aligned:
    """Checks, the current's clean cloud, registration and whether this is the station at all,
    the reference moved into the current camera frame, and (``free_space``) the free-space
    checks both ways (:func:`direction_free`; a caller that runs the two directions on two
    threads leaves them to each direction).  With ``params.threads`` > 1 the current's
    cleaning (and the free-space views of its image) runs beside the registration."""
    check_scene_models(reference, current)
    ref = as_epoch(reference, "reference")
    model = reference if isinstance(reference, SceneModel) else None
    if isinstance(current, np.ndarray):
        intrinsics = check_current_depth(ref, current, intrinsics, model)
        current_depth = current

        def prepare() -> Epoch:
            cur = clean_current(ref, current, intrinsics, timings)
            if params.threads > 1 and params.disappeared and params.free_space:
                free_space_views(cur, params)  # the disappeared direction's, made here
            return cur
    else:
        cur = current_epoch(ref, current, intrinsics, timings)
        current_depth = cur.depth

        def prepare() -> Epoch:
            return cur

    cur_levels: dict = {}  # the current's pyramid, for its epoch once there is one
    registration = ref.registration_params(params.registration)  # the reference's camera

    def register() -> Registration | Exception:
        try:
            return register_depth(ref.depth, current_depth, ref.intrinsics, registration,
                                  initial=initial_pose, keep=ref.derived,
                                  keep_current=cur_levels)
        except Exception as exc:  # raised after the pair's own checks, which come first
            return exc

    reg, cur = both(register, prepare, params.threads)
    cur.derived.update(cur_levels)
    check_pair(ref, cur, params)
    if isinstance(reg, Exception):
        raise reg
    timings["registration_ms"] = reg.ms
    unread = unread_share(ref.depth, current_depth, ref.intrinsics, reg.T_ref_from_cur,
                          registration, ref.derived, cur.derived)
    if unread > params.max_unread_share:
        raise EmptySceneError(
            f"the current view reads nothing where the reference read {unread:.0%} of what it "
            f"sees from here (> max_unread_share = {params.max_unread_share:.0%}): the lens "
            f"covered, or something nearer than the camera's minimum range; treat it as a "
            f"fault")
    reason = reg.not_at_station(registration)
    if reason:
        return Aligned(ref, cur, reg, reason)
    if not reg.is_identity:
        T = reg.inverse()
        ref = dataclasses.replace(
            ref, points=transform_points(T, ref.points),
            mixture=ref.mixture.transformed(T) if ref.mixture is not None else None)
    aligned = Aligned(ref, cur, reg, reason)
    if not free_space:
        return aligned
    free_cur, obs_cur, _ = direction_free(aligned, "appeared", params, timings)
    if not params.disappeared:
        return dataclasses.replace(aligned, free_cur=free_cur, observed_cur=obs_cur)
    free_ref, obs_ref, _ = direction_free(aligned, "disappeared", params, timings)
    return dataclasses.replace(aligned, free_cur=free_cur, observed_cur=obs_cur,
                               free_ref=free_ref, observed_ref=obs_ref)


def direction_free(aligned: Aligned, kind: str, params: ChangeParams, timings: dict
                   ) -> FreeSpace:
    """:class:`FreeSpace` of one direction's points, timed as ``<kind>_free_space_ms``:
    ``"appeared"``, the current's points against the reference's depth image;
    ``"disappeared"``, the reference's against the current's."""
    reg = aligned.registration
    if kind == "appeared":
        other, base, T = aligned.cur, aligned.ref, reg.T_ref_from_cur
    else:
        other, base, T = aligned.ref, aligned.cur, reg.inverse()
    return timed_free(other, base, params, timings, f"{kind}_",
                      None if reg.is_identity else T)


def timed_free(other: Epoch, base: Epoch, params: ChangeParams, timings: dict, prefix: str,
                base_from_other: np.ndarray | None) -> FreeSpace:
    """:func:`free_and_observed`, timed."""
    t0 = time.perf_counter()
    out = free_and_observed(other, base, params, base_from_other)
    timings[f"{prefix}free_space_ms"] = (time.perf_counter() - t0) * 1e3
    return out


def geometric_filters(other: Epoch, base: Epoch, cand: np.ndarray, params: ChangeParams,
                       timings: dict, prefix: str, free: np.ndarray, observed: np.ndarray
                       ) -> np.ndarray:
    """What the other camera could not see is never a change; then the free-space check
    (against ``base``'s depth image) and the optional NN check (``base.points`` are in
    ``other``'s frame)."""
    t0 = time.perf_counter()
    cand = cand & observed
    if params.free_space:
        cand = cand & free
    t1 = time.perf_counter()
    if params.nn_check_m > 0 and cand.any():
        rows = np.flatnonzero(cand)
        keep = np.zeros_like(cand)
        keep[rows[nn_far(cKDTree(base.points), other.points[rows], params.nn_check_m)]] = True
        cand = keep
    timings[f"{prefix}free_space_ms"] = timings.get(f"{prefix}free_space_ms", 0.0) + \
        (t1 - t0) * 1e3
    timings[f"{prefix}nn_check_ms"] = (time.perf_counter() - t1) * 1e3
    return cand


def nn_far(tree: cKDTree, points: np.ndarray, d: float) -> np.ndarray:
    dist, _ = tree.query(points, k=1, distance_upper_bound=d)
    return ~np.isfinite(dist)


def finish(method: str, params: ChangeParams, aligned: Aligned, app: Direction | None,
            dis: Direction | None, k_ref: int, k_cur: int, timings: dict, t_start: float
            ) -> ChangeSet:
    ref, cur = aligned.ref, aligned.cur
    t0 = time.perf_counter()
    regions_a = () if app is None else app.regions if app.regions is not None else \
        direction_regions("appeared", cur, app, params)
    regions_d = () if dis is None else dis.regions if dis.regions is not None else \
        direction_regions("disappeared", ref, dis, params)
    rows_a = (np.sort(np.concatenate([r.point_index for r in regions_a]))
              if regions_a else np.zeros(0, np.int64))
    rows_d = (np.sort(np.concatenate([r.point_index for r in regions_d]))
              if regions_d else np.zeros(0, np.int64))
    unseen = sum(int((~d.observed).sum()) for d in (app, dis) if d is not None)
    seen_of = (cur.n_points if app is not None else 0) + (ref.n_points if dis is not None else 0)
    timings["regions_ms"] = (time.perf_counter() - t0) * 1e3
    timings["detect_ms"] = (time.perf_counter() - t_start) * 1e3
    changed = bool(regions_a or regions_d)
    return ChangeSet(
        changed=changed,
        appeared=regions_a, disappeared=regions_d,
        appeared_points=cur.points[rows_a].astype(np.float32),
        disappeared_points=ref.points[rows_d].astype(np.float32),
        appeared_index=rows_a, disappeared_index=rows_d,
        appeared_mask=pixel_mask(cur, rows_a), disappeared_mask=pixel_mask(ref, rows_d),
        appeared_mixture=app.mixture if app is not None else None,
        disappeared_mixture=dis.mixture if dis is not None else None,
        k_reference=k_ref, k_current=k_cur,
        greedy_appeared=app.trace if app is not None else None,
        greedy_disappeared=dis.trace if dis is not None else None,
        method=method, params=params, timings_ms=timings,
        outcome="changed" if changed else "no_change",
        registration=aligned.registration,
        unobserved_fraction=unseen / seen_of if seen_of else 0.0, current_points=cur.points,
        noise=ref.noise, limit=reference_limit(ref, params))


def reference_limit(ref: Epoch, params: ChangeParams) -> DetectionLimit:
    """The reference's :func:`robot_change.change.limits.detection_limit` for these params,
    kept in its ``derived`` (one per station, not one per check)."""
    key = ("detection_limit", params.free_space_sigmas, params.free_space_pose_m,
           params.free_space_pose_deg, params.evidence_min_points, params.min_region_points,
           ref.noise)
    return kept(ref.derived, key, lambda: detection_limit(ref.depth, ref.noise, params,
                                                          ref.leaf_m, ref.intrinsics.fx))


def not_at_station_result(method: str, params: ChangeParams, aligned: Aligned, timings: dict,
                    t_start: float) -> ChangeSet:
    """The camera is not where the reference was taken: nothing is compared, nothing
    reported."""
    ref, cur = aligned.ref, aligned.cur
    none = np.zeros(0, np.int64)
    timings["detect_ms"] = (time.perf_counter() - t_start) * 1e3
    return ChangeSet(
        changed=False, appeared=(), disappeared=(),
        appeared_points=np.zeros((0, 3), np.float32),
        disappeared_points=np.zeros((0, 3), np.float32),
        appeared_index=none, disappeared_index=none,
        appeared_mask=np.zeros(cur.depth.shape, bool),
        disappeared_mask=np.zeros(ref.depth.shape, bool),
        appeared_mixture=None, disappeared_mixture=None,
        k_reference=ref.mixture.n_components if ref.mixture is not None else 0, k_current=0,
        greedy_appeared=None, greedy_disappeared=None, method=method, params=params,
        timings_ms=timings, outcome="not_at_station", registration=aligned.registration,
        unobserved_fraction=1.0 - aligned.registration.fitness,
        not_at_station_reason=aligned.reason, current_points=cur.points, noise=ref.noise,
        limit=reference_limit(ref, params))
