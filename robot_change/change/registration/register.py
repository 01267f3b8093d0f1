"""register_depth: the current view registered to the station's reference, coarse to fine
(docs/algorithm.md, "Registration"): ICP per level (:mod:`.icp`), at the coarsest level also
with a wide cut, the search along weak directions at the middle level and, for an estimate
weak along a translation and not a table top, once more at the end (:mod:`.agreement`), then
at a table station on what does not stand on the table (:mod:`.table_station`; its slide
judged on that alone too), and on a table top the table-plane tracks, the trimming and the
checks of :mod:`.table_top`; an end the views contradict starts again from restarts round
the initial pose.
"""

from __future__ import annotations

import functools
import math
import time
from typing import NamedTuple

import numpy as np

from hw.depth import Intrinsics
from robot_change.errors import InputError
from robot_change.noise.profile import NoiseProfile

from .agreement import (
    best_pose,
    better_end,
    final_agreement,
    fine_search,
    score_poses,
    slide_peaks,
    slide_support,
    weak_search,
)
from .icp import Pairs, best_of, icp_level, weak_names
from .params import RegistrationParams
from .pyramid import Level, check_depth, kept_levels
from .result import AXES, Registration, identity_registration
from .rigid import invert, rigid, rotation_angle_deg, rpy_deg_to_rotation
from .table_station import structure_levels, structure_search
from .table_top import (
    TablePlane,
    in_plane_names,
    table_planes,
    table_pose_weak,
    table_starts,
    without_changed_objects,
)

#: Two coarsest-level ends this near (metres, degrees) are one: the levels after them end
#: alike, and step 7d's passes give up the later.
_SAME_M = 0.002
_SAME_DEG = 0.1


class _Pass(NamedTuple):
    """Where a coarse-to-fine pass ends: ``T`` (4, 4) (None: given up), its ICP iterations
    (every run counted), whether the last level converged, the last normal matrix's
    eigenvalues per unit weight ``lam_n`` (6,) and eigenvectors ``vec`` (6, 6), the matrix
    ``A`` (6, 6) or None, and a table top's (reference, current) planes or None."""

    T: np.ndarray | None
    iterations: int
    converged: bool
    lam_n: np.ndarray
    vec: np.ndarray
    A: np.ndarray | None
    planes: tuple[TablePlane, TablePlane] | None


#: the default parameters (frozen, built once)
_DEFAULT_PARAMS = RegistrationParams()


def register_depth(reference: np.ndarray, current: np.ndarray, intrinsics: Intrinsics,
                   params: RegistrationParams = _DEFAULT_PARAMS, *,
                   initial: np.ndarray | None = None, keep: dict | None = None,
                   keep_current: dict | None = None, noise: NoiseProfile | None = None
                   ) -> Registration:
    """Estimate ``T_ref_from_cur``, the rigid transform that maps the current camera frame
    into the reference camera frame, from the two depth images.

    Parameters
    ----------
    reference, current : (H, W) uint16 mm
        The reference's (fused) depth image and the current one, same intrinsics.
    intrinsics : hw.depth.Intrinsics
    params : RegistrationParams
    initial : (4, 4) float64, optional
        Starting estimate (identity by default: the robot believes it is at its station).
    keep : dict, optional
        Where the reference's pyramid is kept between calls (a station's reference, checked
        against many frames, builds it once): an epoch's ``derived``
        (robot_change.change.epoch.Epoch), which belongs to ``reference`` alone.
    keep_current : dict, optional
        Where the current's pyramid is left (for the epoch made of ``current``: the object
        completion's segments start from its finest level).
    noise : robot_change.noise.profile.NoiseProfile, optional
        The camera's noise (instead of ``params.noise``; with ``min_depth_m`` unset, its near
        range too).  A check passes parameters that hold its reference's
        (:meth:`robot_change.change.epoch.Epoch.registration_params`).

    Returns
    -------
    Registration
        With ``enabled=False``, ``initial`` (the identity by default) taken as it is, with
        fitness 1: for a camera bolted in place, or a transform from elsewhere.
    """
    if not isinstance(params, RegistrationParams):
        raise InputError(f"params must be a RegistrationParams, got {type(params).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise InputError(f"intrinsics must be a hw.depth.Intrinsics, got "
                         f"{type(intrinsics).__name__}")
    ref = check_depth("reference", reference, intrinsics)
    cur = check_depth("current", current, intrinsics)
    T = np.eye(4) if initial is None else np.array(initial, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(
            T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6) or np.linalg.det(T[:3, :3]) < 0 \
            or not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError("initial must be a finite (4, 4) rigid transform (a rotation, no "
                         "scale or mirror, and the last row 0, 0, 0, 1)")
    if not params.enabled:
        return identity_registration(T)
    if noise is not None:
        params = params.replace(noise=noise)
    t0 = time.perf_counter()
    ref_levels = kept_levels(ref, intrinsics, params, keep)
    cur_levels = kept_levels(cur, intrinsics, params, keep_current)
    min_cos = math.cos(math.radians(params.max_normal_angle_deg))
    coarse_ends: list[np.ndarray] = []
    end = _finished(ref_levels, cur_levels, _coarse_to_fine(
        ref_levels, cur_levels, T, params, min_cos, coarse_ends), params, min_cos, T)
    if 0 < params.restart_end_through < end[2][4]:  # its judgement's seen-through share
        end = _restarted_end(ref_levels, cur_levels, T, end, params, min_cos, coarse_ends)
    est, weak, (fit, rmse, n_pairs, n_cells, through, behind) = end
    return Registration(est.T, fit, rmse, weak, est.lam_n, n_pairs, n_cells, est.iterations,
                        est.converged, (time.perf_counter() - t0) * 1e3, through, behind)


def _finished(ref_levels: list[Level], cur_levels: list[Level], end: _Pass,
              params: RegistrationParams, min_cos: float, start: np.ndarray
              ) -> tuple[_Pass, tuple[str, ...], tuple]:
    """A pass's ``end`` judged (:func:`_judge`) and, weak along a translation and not a
    table top, searched at the end (steps 7b, 7c; the final search also round ``start``
    (4, 4), the initial pose), then at a table station judged on its structure (step 7e):
    (the end, moved where a search moved it; the weak direction names; the judgement:
    fitness, rmse_m, inlier pairs, current cells with a normal, seen-through share, behind
    share)."""
    T, iterations, converged, lam_n, vec, A, planes = end
    weak, judged = _judge(ref_levels[-1], cur_levels[-1], T, A, lam_n, vec, planes, params,
                          min_cos)
    # for an estimate weak along a translation: the final search along it, then, at a table
    # station, the structure's say; not on a table top, whose in-plane pose has its own
    # starts (step 6b): scored whole, objects moved on it line up a slide away
    searches = []
    if planes is None:
        if params.final_search_reach_m > 0:
            searches.append(functools.partial(_final_search, start=start))
        searches.append(structure_search)
    for search in searches:
        if A is None or not any(a in weak for a in AXES[3:]):
            break
        found = search(ref_levels, cur_levels, T, A, params, min_cos)
        if found is not None:
            searched = tuple(a for a in weak if a in AXES[3:])
            T, n_it, converged, lam_n, vec, A = found
            iterations += n_it
            weak, judged = _judge(ref_levels[-1], cur_levels[-1], T, A, lam_n, vec, planes,
                                  params, min_cos)
            # where along that line the estimate stands a search's score chose, not the
            # geometry: it stays said (a wrong end can look pinned once there)
            weak = tuple(dict.fromkeys(weak + searched))
    if planes is None and not any(a in weak for a in AXES[3:]):
        weak = weak + _structure_slide(ref_levels, cur_levels, T, A, params, min_cos, judged[3])
    return _Pass(T, iterations, converged, lam_n, vec, A, planes), weak, judged


def _coarse_to_fine(ref_levels: list[Level], cur_levels: list[Level], T: np.ndarray,
                    params: RegistrationParams, min_cos: float,
                    seen: list[np.ndarray] | None = None) -> _Pass:
    """Steps 1-6c from the estimate ``T`` (4, 4): ICP per level, coarse to fine, with the
    coarsest level's wide cut, the table-plane tracks, the middle level's
    searches and a table top's trimming.  With ``seen`` (the coarsest level's ends of earlier
    passes, (4, 4) each): the pass is given up, T None, where its coarsest end is one of
    them (:func:`_same_pose`: the levels after it would end where that pass did), and its
    end is added to them otherwise."""
    iterations = 0
    converged = False
    lam_n = np.zeros(6)
    vec = np.eye(6)
    tracks: list[np.ndarray] = []  # estimates from the table-plane starts, to search_level
    planes: tuple[TablePlane, TablePlane] | None = None  # a table top's, when it is one
    for li, (rl, cl) in enumerate(zip(ref_levels, cur_levels, strict=True)):
        pairs = Pairs(cl)
        start = T
        T, n_it, converged, lam_n, vec, A = icp_level(rl, cl, start, params, li, min_cos, pairs)
        iterations += n_it
        if li == 0 and params.wide_cut_m > 0:
            wide = icp_level(rl, cl, start, params, li, min_cos, pairs, params.wide_cut_m)
            iterations += wide[1]
            if best_pose(rl, cl, [T, wide[0]], params, min_cos) == 1:  # narrow wins ties
                T, n_it, converged, lam_n, vec, A = wide
        if li == 0 and seen is not None:
            if any(_same_pose(T, other) for other in seen):
                return _Pass(None, iterations, converged, lam_n, vec, A, planes)
            seen.append(T)
        if li == 0 and (params.table_starts > 0 or params.trim_rounds > 0):
            planes = table_planes(ref_levels, cur_levels, params)
            if planes is not None and params.table_starts > 0:
                tracks = table_starts(ref_levels, cur_levels, planes, params)
        if tracks and li <= params.search_level:
            ends = [icp_level(rl, cl, st, params, li, min_cos, pairs) for st in tracks]
            iterations += sum(e[1] for e in ends)
            tracks = [e[0] for e in ends]
        if li == params.search_level and params.search_reach_m > 0 and A is not None:
            moved = weak_search(rl, cl, T, A, params, min_cos)
            if moved is not None:
                T, n_it, converged, lam_n, vec, A = icp_level(rl, cl, moved, params, li,
                                                              min_cos, pairs)
                iterations += n_it
            # a table top's in-plane pose has starts of its own, on a finer grid
            slid = None if planes is not None else _slide(rl, cl, T, A, params, li, min_cos,
                                                          pairs)
            if slid is not None:
                T, n_it, converged, lam_n, vec, A = slid
                iterations += n_it
        if tracks and li == params.search_level:
            # the table-plane tracks against the main one, on the score taken both ways
            scores = score_poses(rl, cl, [T] + [e[0] for e in ends], params, min_cos, True,
                                 params.table_hole_weight)
            best = int(np.argmax(scores))  # the first of equal scores: the main track
            if best > 0:
                T, n_it, converged, lam_n, vec, _ = ends[best - 1]
            tracks = []
    for _round in range(params.trim_rounds if planes is not None else 0):
        for li in range(params.search_level, len(ref_levels)):
            rl, cl = without_changed_objects(ref_levels[li], cur_levels[li], planes, T, params,
                                             li, min_cos)
            T, n_it, converged, lam_n, vec, A = icp_level(rl, cl, T, params, li, min_cos,
                                                          Pairs(cl))
            iterations += n_it
    return _Pass(T, iterations, converged, lam_n, vec, A, planes)


def _restart_starts(start: np.ndarray, params: RegistrationParams) -> list[np.ndarray]:
    """(4, 4) poses: ``start`` moved by ``restart_step_m`` along and turned by
    ``restart_step_deg`` about each axis of the current camera, both ways (up to 12)."""
    starts = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            if params.restart_step_m > 0:
                starts.append(start @ rigid(t=sign * params.restart_step_m * np.eye(3)[axis]))
            if params.restart_step_deg > 0:
                angles = [0.0, 0.0, 0.0]
                angles[axis] = sign * params.restart_step_deg
                starts.append(start @ rigid(rpy_deg_to_rotation(*angles)))
    return starts


def _restarted_end(ref_levels: list[Level], cur_levels: list[Level], start: np.ndarray,
                   end: tuple, params: RegistrationParams, min_cos: float,
                   coarse_ends: list[np.ndarray]) -> tuple:
    """Step 7d, for an ``end`` (:func:`_finished`'s triple, from ``start`` (4, 4)) that more
    than ``restart_end_through`` of one view is seen through at: the coarse-to-fine passes
    again from :func:`_restart_starts` of ``start``, each given up where its coarsest end is
    one of ``coarse_ends`` (its own pass's, and theirs as they come); the best of their
    ends, scored both ways at the finest level (with ``table_hole_weight``), replaces ``end``
    (finished in turn) when it scores higher by more than ``final_search_margin`` of the two
    views' cells with a normal and is seen through in less than ``restart_end_ratio`` of
    ``end``'s share.  Every pass's iterations are counted."""
    rl, cl = ref_levels[-1], cur_levels[-1]
    est, weak, judged = end
    passes = [_coarse_to_fine(ref_levels, cur_levels, st, params, min_cos, coarse_ends)
              for st in _restart_starts(start, params)]
    iterations = est.iterations + sum(p.iterations for p in passes)
    kept = (est._replace(iterations=iterations), weak, judged)
    ends = [p for p in passes if p.T is not None]
    if not ends:
        return kept
    best = better_end(rl, cl, est.T, [p.T for p in ends], params, min_cos)
    if best is None or final_agreement(rl, cl, ends[best].T, params, min_cos)[4] >= \
            params.restart_end_ratio * judged[4]:
        return kept
    return _finished(ref_levels, cur_levels, ends[best]._replace(iterations=iterations),
                     params, min_cos, start)


def _same_pose(T: np.ndarray, other: np.ndarray) -> bool:
    """Whether two (4, 4) poses lie within ``_SAME_M`` and ``_SAME_DEG`` of each other."""
    D = invert(other) @ T
    return bool(np.linalg.norm(D[:3, 3]) < _SAME_M and rotation_angle_deg(D[:3, :3]) < _SAME_DEG)


def _judge(rl: Level, cl: Level, T: np.ndarray, A: np.ndarray | None, lam_n: np.ndarray,
           vec: np.ndarray, planes: tuple[TablePlane, TablePlane] | None,
           params: RegistrationParams, min_cos: float):
    """What the finest levels (``rl``, ``cl``) say of the estimate ``T``: (weak direction
    names, (fitness, rmse_m, inlier pairs, current cells with a normal, seen-through share,
    behind share))."""
    fit, rmse, n_pairs, n_cells, through, behind = final_agreement(rl, cl, T, params, min_cos)
    weak = weak_names(lam_n, vec, params.weak_eigenvalue)
    # on a table top the objects that changed were left out of the estimate and the table's
    # own checks judge what stayed: their contradiction does not contest the slide
    slide = _unsupported_slide(rl, cl, T, A, params, min_cos, n_cells, contested=planes is None)
    if planes is not None and table_pose_weak(rl, cl, T, planes, weak + slide, params,
                                              min_cos):
        weak = weak + in_plane_names(planes[1])
    weak = tuple(dict.fromkeys(weak + slide))
    return weak, (fit, rmse, n_pairs, n_cells, through, behind)


def _final_search(ref_levels: list[Level], cur_levels: list[Level], T: np.ndarray,
                  A: np.ndarray, params: RegistrationParams, min_cos: float, *,
                  start: np.ndarray):
    """The finest level's ICP (:func:`icp_level`'s tuple) from the best peak of ``T`` slid
    along its least constrained translation, round ``T`` and round the initial pose
    ``start`` (:func:`slide_peaks`, at ``search_level``) when it ends scoring higher than
    ``T`` both ways by more than ``final_search_margin`` of the two views' cells with a
    normal; None otherwise."""
    mid = params.search_level
    starts = slide_peaks(ref_levels[mid], cur_levels[mid], T, A, params, min_cos, start)
    rl, cl, li = ref_levels[-1], cur_levels[-1], len(ref_levels) - 1
    pairs = Pairs(cl)
    ends = [icp_level(rl, cl, st, params, li, min_cos, pairs) for st in starts]
    best = better_end(rl, cl, T, [e[0] for e in ends], params, min_cos) if ends else None
    return None if best is None else best_of(ends, best)


def _slide(rl: Level, cl: Level, T: np.ndarray, A: np.ndarray | None,
           params: RegistrationParams, li: int, min_cos: float, pairs: Pairs):
    """Level ``li``'s ICP (:func:`icp_level`'s tuple) from the best of ``T`` slid along its
    least constrained direction (:func:`fine_search`), when it ends scoring higher than ``T``;
    None otherwise."""
    if A is None:
        return None
    moved = fine_search(rl, cl, T, A, params, min_cos)
    if moved is None:
        return None
    end = icp_level(rl, cl, moved, params, li, min_cos, pairs)
    return end if best_pose(rl, cl, [T, end[0]], params, min_cos) == 1 else None


def _structure_slide(ref_levels: list[Level], cur_levels: list[Level], T: np.ndarray,
                     A: np.ndarray | None, params: RegistrationParams, min_cos: float,
                     n_cells: int) -> tuple[str, ...]:
    """Step 7e, at a table station (:func:`~.table_station.structure_levels`): the
    :data:`AXES` name of ``T``'s least constrained translation when what does not stand on
    the table leaves it unsupported or contested (:func:`_unsupported_slide` on the structure
    alone), else (): every object on the table may have moved and lined up there.  Said,
    not searched: a search on it moved right estimates (docs/algorithm.md)."""
    structure = structure_levels(ref_levels, cur_levels, T, params)
    if structure is None:
        return ()
    return _unsupported_slide(*structure, T, A, params, min_cos, n_cells, contested=True)


def _unsupported_slide(rl: Level, cl: Level, T: np.ndarray, A: np.ndarray | None,
                       params: RegistrationParams, min_cos: float, n_cells: int, *,
                       contested: bool) -> tuple[str, ...]:
    """The :data:`AXES` name of the least constrained translation of the finest level's normal
    matrix ``A`` (6, 6), when what faces along it (:func:`slide_support`) does not pin it at
    ``T``: fewer than ``slide_support_share`` of the ``n_cells`` current cells with a normal
    fit, or (``contested``) more than ``slide_contested_share`` of those judged contradict;
    else ()."""
    if A is None:
        return ()
    direction = np.linalg.eigh(A[3:, 3:])[1][:, 0]
    fit, contradict = slide_support(rl, cl, T, direction, params, min_cos)
    if fit >= params.slide_support_share * n_cells and (
            not contested or contradict <= params.slide_contested_share * (fit + contradict)):
        return ()
    return (AXES[3 + int(np.argmax(np.abs(direction)))],)
