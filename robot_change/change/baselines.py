"""The baselines, compared with the same registration and region grouping as ours: the plain
method (the paper's: independent fits, greedy EMD over all components), the nearest-neighbour
threshold, and the geometric check (nearest neighbour plus free space).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from hw.depth import Intrinsics
from robot_change.change.compare import (
    Current,
    Direction,
    Reference,
    align,
    finish,
    fit_own,
    geometric_filters,
    nn_far,
    not_at_station_result,
)
from robot_change.change.epoch import Epoch
from robot_change.change.greedy import greedy_trace
from robot_change.change.params import ChangeParams
from robot_change.change.results import ChangeSet
from robot_change.errors import InputError
from robot_change.mixture.model import Mixture

__all__ = [
    "detect_geometric",
    "detect_nn_threshold",
    "detect_plain",
]


def _plain_direction(base_mix: Mixture, other: Epoch, other_mix: Mixture, params, timings,
                     prefix):
    t0 = time.perf_counter()
    candidates = np.ones(other_mix.n_components, dtype=bool)
    trace = greedy_trace(base_mix, other_mix, candidates, other.n_points, params)
    t1 = time.perf_counter()
    post = other_mix.responsibilities(other.points)
    if trace.change.size:
        cand = post[:, trace.change].sum(axis=1) > params.posterior_threshold
    else:
        cand = np.zeros(other.n_points, dtype=bool)
    timings[f"{prefix}greedy_ms"] = (t1 - t0) * 1e3
    timings[f"{prefix}segment_ms"] = (time.perf_counter() - t1) * 1e3
    return cand, other_mix, post, trace


#: detect_plain's default parameters (frozen, built once)
_PLAIN_PARAMS = ChangeParams(novelty=False, free_space=False)


def detect_plain(reference: Reference, current: Current, params: ChangeParams = _PLAIN_PARAMS,
                 *, intrinsics: Intrinsics | None = None) -> ChangeSet:
    """The plain method (the paper's): independent fits of both clouds, greedy EMD over all
    components both ways deciding what changed (``params.greedy`` is forced on: without it
    every component would count as changed), posterior segmentation; the free-space / NN
    checks only if ``params`` switches them on (off by default here).  Registered first, as
    :func:`detect_changes` is."""
    params = params.replace(greedy=True)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    aligned = align(reference, current, params, intrinsics, timings)
    if not aligned.at_station:
        return not_at_station_result("plain", params, aligned, timings, t_start)
    ref, cur = aligned.ref, aligned.cur
    mixes = []
    for name, ep in (("reference", ref), ("current", cur)):
        m = ep.mixture
        if m is None:
            t0 = time.perf_counter()
            m = fit_own(ep, params)
            timings[f"{name}_fit_ms"] = (time.perf_counter() - t0) * 1e3
        mixes.append(m)
    ref_mix, cur_mix = mixes
    free_a, obs_a = aligned.free_cur, aligned.observed_cur
    cand, mix, post, trace = _plain_direction(ref_mix, cur, cur_mix, params, timings,
                                              "appeared_")
    cand = geometric_filters(cur, ref, cand, params, timings, "appeared_", free_a, obs_a)
    app = Direction(cand, post, mix, trace, obs_a)
    dis = None
    if params.disappeared:
        free_d, obs_d = aligned.free_ref, aligned.observed_ref
        cand, mix, post, trace = _plain_direction(cur_mix, ref, ref_mix, params, timings,
                                                  "disappeared_")
        cand = geometric_filters(ref, cur, cand, params, timings, "disappeared_", free_d,
                                  obs_d)
        dis = Direction(cand, post, mix, trace, obs_d)
    return finish("plain", params, aligned, app, dis, ref_mix.n_components,
                   cur_mix.n_components, timings, t_start)


#: detect_nn_threshold's default parameters (frozen, built once)
_NN_THRESHOLD_PARAMS = ChangeParams(free_space=False, nn_check_m=0.05)


def detect_nn_threshold(reference: Reference, current: Current,
                        params: ChangeParams = _NN_THRESHOLD_PARAMS, *,
                        intrinsics: Intrinsics | None = None,
                        initial_pose: np.ndarray | None = None) -> ChangeSet:
    """Baseline: a current point is appeared when no reference point is within
    ``params.nn_check_m`` (a reference point disappeared likewise); no mixture, and the
    free-space check only when ``params.free_space``.  Same registration and region grouping
    as ours."""
    if params.nn_check_m <= 0 and not params.free_space:
        raise InputError("detect_nn_threshold needs params.nn_check_m > 0 (the threshold, m) "
                         "or the free-space check")
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    method = ("free_space" if params.nn_check_m <= 0 else "geometric") if params.free_space \
        else "nn"
    aligned = align(reference, current, params, intrinsics, timings, initial_pose)
    if not aligned.at_station:
        return not_at_station_result(method, params, aligned, timings, t_start)
    ref, cur = aligned.ref, aligned.cur
    t0 = time.perf_counter()
    if params.nn_check_m > 0:
        app = nn_far(cKDTree(ref.points), cur.points, params.nn_check_m)
        dis = nn_far(cKDTree(cur.points), ref.points, params.nn_check_m) \
            if params.disappeared else None
    else:  # free-space check alone
        app = np.ones(cur.n_points, dtype=bool)
        dis = np.ones(ref.n_points, dtype=bool) if params.disappeared else None
    timings["nn_ms"] = (time.perf_counter() - t0) * 1e3
    no_nn = params.replace(nn_check_m=0.0)
    free_a, obs_a = aligned.free_cur, aligned.observed_cur
    app_d = Direction(geometric_filters(cur, ref, app, no_nn, timings, "appeared_", free_a,
                                          obs_a), None, None, None, obs_a)
    dis_d = None
    if dis is not None:
        free_d, obs_d = aligned.free_ref, aligned.observed_ref
        dis_d = Direction(geometric_filters(ref, cur, dis, no_nn, timings, "disappeared_",
                                              free_d, obs_d), None, None, None, obs_d)
    return finish(method, params, aligned, app_d, dis_d,
                   ref.mixture.n_components if ref.mixture is not None else 0,
                   cur.mixture.n_components if cur.mixture is not None else 0,
                   timings, t_start)


#: detect_geometric's default parameters (frozen, built once)
_GEOMETRIC_PARAMS = ChangeParams(nn_check_m=0.05)


def detect_geometric(reference: Reference, current: Current,
                     params: ChangeParams = _GEOMETRIC_PARAMS, *,
                     intrinsics: Intrinsics | None = None) -> ChangeSet:
    """Baseline without a mixture: the 5 cm nearest-reference-point check plus the free-space
    check on every point (ALGORITHM.md section 3's bar for the mixture method)."""
    return detect_nn_threshold(reference, current, params.replace(free_space=True),
                               intrinsics=intrinsics)
