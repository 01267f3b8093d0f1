"""Table stations: a table seen with the floor beside or before it (docs/algorithm.md,
"Registration", step 7c).

Where every object on a table moved, the moved objects can line up at a pose slid along the
wall, and they outvote what pins the slide: the table's ends and legs, a few cells.  Which
pose is right is a question of what moves: objects on a table do, the table, its legs, the
floor and the walls do not.  So here

* **the table** (:func:`support_plane`): of the reference's planes, one with another parallel
  to it 0.3-1.3 m farther from the camera (a table top over the floor);
* **what stands on it** (:func:`objects_on_table`): the cells of a view that stand above the
  table plane over the table's outline (the convex hull of the table's cells in its plane),
  the objects' feet included;
* **the structure** (:func:`structure_levels`): both views with what stands on the table
  left without normals, on which step 7e judges the estimate's slide;
* **the structure's say** (:func:`structure_search`): the cells of either view, objects left
  out, that the other view sees through; ICP on the structure alone from the estimate and
  from where that count is least along the structure's slide, and the end replaces the
  estimate when the structure contradicts it much less, and hardly at all.
"""

from __future__ import annotations

import math
import weakref

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from .agreement import slides_along, through_counts
from .icp import Pairs, best_of, icp_level
from .params import RegistrationParams
from .pyramid import Level
from .rigid import invert
from .surfaces import level_segments
from .table_top import ON_PLANE_M, first_distinct, plane_frame, planes_of

#: The reference's table plane per level object, and what stands on its table per finest
#: level object (a station's reference keeps its pyramid: made once, not every check).
_SUPPORT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_ON_TABLE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: How many of a view's largest planes are looked at, and the least share of its cells with
#: a normal each must hold (the floor before a station's table held 0.06-0.12 of them).
_PLANES = 4
_MIN_PLANE_FRACTION = 0.05
#: How far a table top stands above the floor beneath it, metres.
_TABLE_HEIGHT_M = (0.3, 1.3)
#: How far inside the table's outline an object's foot must stand, metres (a wall behind the
#: table stands on its edge).
_OUTLINE_MARGIN_M = 0.02
#: A cell within table_object_m of the table plane whose normal lies farther than 45 degrees
#: from the plane's is an object's foot (the table top's cells face along its normal).
_FOOT_COS = math.cos(math.radians(45.0))
#: A surface segment above the table stands on it when this share of its cells do.
_SEGMENT_INSIDE = 0.25
#: Surface segments part where the surface folds inwards by more than this (degrees), as
#: the change detection cuts them (ChangeParams.object_fold_deg).
_FOLD_DEG = 20.0
#: The structure's search runs ICP from this many more starts, apart by more than
#: _DISTINCT_M (metres) from each other and from its first end: ICP's basin on a table's
#: legs and ends is a few centimetres wide, and the lowest count need not lie in it.
_STARTS = 3
_DISTINCT_M = 0.015


def support_plane(level: Level) -> tuple[np.ndarray, float] | None:
    """The table plane of a view (one ``level`` of its pyramid, kept per level object): (n
    (3,) unit normal towards the camera, d m), n . p + d = 0, or None.  Of the view's
    ``_PLANES`` largest planes (:func:`~.table_top.planes_of`) holding at least
    ``_MIN_PLANE_FRACTION`` of its cells each, a plane is a table when another, its normal
    within 5 degrees, lies ``_TABLE_HEIGHT_M`` farther from the camera (the floor beneath
    it); the largest such.  No gravity is assumed: a view without the floor has none."""
    if level in _SUPPORT:
        return _SUPPORT[level]
    planes = [(n, d, f) for n, d, f in planes_of(level, _PLANES) if f >= _MIN_PLANE_FRACTION]
    lo, hi = _TABLE_HEIGHT_M
    best = None
    for n, d, frac in planes:
        if any(float(n @ m) > math.cos(math.radians(5.0)) and lo <= e - d <= hi
               for m, e, _ in planes) and (best is None or frac > best[2]):
            best = (n, d, frac)
    out = None if best is None else (best[0], best[1])
    _SUPPORT[level] = out
    return out


def objects_on_table(level: Level, plane: tuple[np.ndarray, float],
                     params: RegistrationParams) -> np.ndarray:
    """(h, w) bool: the cells of ``level`` that stand on the table ``plane`` (n, d in this
    view's frame).  A cell standing more than ``table_object_m`` above the plane, or an
    object's foot (lower, its normal more than 45 degrees from the plane's), is on the
    table when it lies inside the table's outline (the convex hull, in the plane, of
    the largest 4-connected group of cells on it, shrunk by ``_OUTLINE_MARGIN_M``), and so is
    every such cell of a surface segment (:func:`~.surfaces.level_segments`) of which at
    least ``_SEGMENT_INSIDE`` stands so: an object at the view's edge hides the table beyond
    it, and its far side stands outside the outline seen.  All False when the view holds
    too little of the table."""
    n, d = plane
    z = level.vertex[:, :, 2]
    height = level.vertex @ n + d
    labels, count = ndimage.label((z > 0) & (np.abs(height) < ON_PLANE_M))
    out = np.zeros(z.shape, dtype=bool)
    if count == 0:
        return out
    table = labels == 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    F = plane_frame(n, d)
    flat = ((level.vertex - F[:3, 3]) @ F[:3, :3])[:, :, :2]  # (h, w, 2) plane coordinates
    # the hull of the region's rim cells is the region's (its inner cells lie between them),
    # at a tenth of the points
    rim = table & ~ndimage.binary_erosion(table)
    try:
        hull = ConvexHull(flat[rim].astype(np.float64))
    except (QhullError, ValueError):  # too few cells, or all on a line
        return out
    # an object's foot, lower than table_object_m, is told by its normal: it faces sideways
    sideways = np.abs(level.normal @ n) < _FOOT_COS
    above = (z > 0) & ((height > params.table_object_m)
                       | (sideways & (height > -ON_PLANE_M) & level.has_normal))
    out[above] = np.all(flat[above].astype(np.float64) @ hull.equations[:, :2].T
                        + hull.equations[:, 2] <= -_OUTLINE_MARGIN_M, axis=1)
    segment = level_segments(level, _FOLD_DEG)
    on = above & (segment >= 0)
    if not on.any():
        return out
    n_above = np.bincount(segment[on], minlength=int(segment.max()) + 1)
    n_inside = np.bincount(segment[on & out], minlength=len(n_above))
    standing = (n_inside > 0) & (n_inside >= _SEGMENT_INSIDE * n_above)
    return out | (on & standing[np.maximum(segment, 0)])


def station_objects(ref_levels: list[Level], cur_levels: list[Level], T: np.ndarray,
                    params: RegistrationParams) -> tuple[np.ndarray, np.ndarray] | None:
    """What stands on the table (:func:`objects_on_table`) in the finest levels of the
    reference (kept with it) and of the current (its table plane the reference's moved by
    ``T`` (4, 4), T_ref_from_cur): ((h, w) bool, (h, w) bool), or None where the reference
    shows no table (:func:`support_plane`) or nothing stands on it in either view."""
    plane = support_plane(ref_levels[params.search_level])
    if plane is None:
        return None
    n_ref, d_ref = plane
    # the plane in the current frame: n . (R p + t) + d = 0
    R, t = T[:3, :3], T[:3, 3]
    rl = ref_levels[-1]
    kept = _ON_TABLE.get(rl)
    if kept is None or kept[0] != params.table_object_m:
        mask = objects_on_table(rl, plane, params)
        mask.setflags(write=False)
        kept = _ON_TABLE[rl] = (params.table_object_m, mask)
    obj_c = objects_on_table(cur_levels[-1], (R.T @ n_ref, d_ref + float(n_ref @ t)), params)
    if not kept[1].any() and not obj_c.any():
        return None
    return kept[1], obj_c


def structure_levels(ref_levels: list[Level], cur_levels: list[Level], T: np.ndarray,
                     params: RegistrationParams) -> tuple[Level, Level] | None:
    """The finest levels of both views with what stands on the table (:func:`station_objects`)
    left without normals (nothing pairs with it, nothing judges it): the structure, which
    does not move; None where that is not a table station."""
    objects = station_objects(ref_levels, cur_levels, T, params)
    if objects is None:
        return None
    return (ref_levels[-1].without(objects[0], points=False),
            cur_levels[-1].without(objects[1], points=False))


def _coarser(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``mask`` (h, w) bool of a level on the next coarser level (``shape`` (h // 2, w // 2)):
    a cell is set when any of the 2 x 2 cells it merges is."""
    h, w = shape
    return mask[:2 * h, :2 * w].reshape(h, 2, w, 2).any(axis=(1, 3))


def _in_reach(T: np.ndarray, A: np.ndarray, params: RegistrationParams) -> list[np.ndarray]:
    """``T`` (4, 4) moved along the least constrained translation of ``A`` (6, 6),
    ``final_search_step_m`` apart out to ``final_search_reach_m`` each way; when the next one
    is weak too (its eigenvalue below ``fine_search_ratio`` of the strongest's: a table seen
    with little of the wall behind it), over a grid on both, 2 steps apart."""
    lam, vecs = np.linalg.eigh(A[3:, 3:])
    if not lam[1] < params.fine_search_ratio * lam[2]:
        return slides_along(T, A, params.final_search_step_m, params.final_search_reach_m, 1)
    step = 2 * params.final_search_step_m
    k = int(math.floor(params.final_search_reach_m / step + 1e-9))
    poses = []
    for a in range(-k, k + 1):
        for b in range(-k, k + 1):
            pose = T.copy()
            pose[:3, 3] += step * (a * vecs[:, 0] + b * vecs[:, 1])
            poses.append(pose)
    return poses


def _structure_through(rs: Level, cs: Level, rl: Level, cl: Level,
                       poses: list[np.ndarray], params: RegistrationParams) -> np.ndarray:
    """(n,) the cells of the structure of both views (``rs``, ``cs``: the objects emptied)
    that the other view (``cl``, ``rl``, whole) sees through at each of the ``poses``
    (T_ref_from_cur)."""
    if not poses:
        return np.zeros(0, dtype=np.int64)
    return sum(through_counts(own.vertex, other.vertex, Ms[:, :3, :3].copy(), Ms[:, :3, 3].copy(),
                              other.fx, other.fy, other.cx, other.cy, *params.through_args())
               for own, other, Ms in ((cs, rl, np.array(poses)),
                                      (rs, cl, np.array([invert(T) for T in poses]))))


def structure_search(ref_levels: list[Level], cur_levels: list[Level], T: np.ndarray,
                     A: np.ndarray, params: RegistrationParams, min_cos: float):
    """The finest level's ICP (:func:`~.icp.icp_level`'s tuple) on the structure alone (the
    objects on the table without normals) that replaces the estimate ``T``, or None (not a
    table station, nothing stands on the table, or the structure does not say so).

    When ``T``'s structure is seen through in more than ``station_through_min`` of the two
    views' cells with a normal: ICP on the structure from ``T``; then along its end's least
    constrained translation (or two, :func:`_in_reach`) the ``_STARTS`` poses where the
    structure is seen through least (middle level; apart by ``_DISTINCT_M``) are starts for
    more.  The end seen through least wins when that is in at most ``station_through_max``
    of the cells, in fewer than ``station_through_ratio`` times ``T``'s, and in fewer by at
    least ``station_through_min`` of the cells.  ``A`` (6, 6): ``T``'s normal matrix, for
    an end that has none."""
    if params.station_through_ratio <= 0:
        return None
    objects = station_objects(ref_levels, cur_levels, T, params)
    if objects is None:
        return None
    obj_r, obj_c = objects
    rl, cl, li = ref_levels[-1], cur_levels[-1], len(ref_levels) - 1
    rs, cs = rl.without(obj_r, points=True), cl.without(obj_c, points=True)
    cells = rl.n_normals + cl.n_normals
    at_T = int(_structure_through(rs, cs, rl, cl, [T], params)[0])
    least = params.station_through_min * cells  # the least gain worth a move
    if at_T <= least:
        return None
    # ICP on the structure alone from T: its slide is the structure's weakest direction,
    # which the moved objects may have turned the estimate's away from
    rn, cn = rl.without(obj_r, points=False), cl.without(obj_c, points=False)
    pairs = Pairs(cn)
    first = icp_level(rn, cn, T, params, li, min_cos, pairs)
    T0, A0 = first[0], first[5]
    # along that slide at the middle level (a cell an object when any of its finer ones is)
    rm, cm = ref_levels[params.search_level], cur_levels[params.search_level]
    rms, cms = (L.without(_coarser(obj, L.vertex.shape[:2]), points=True)
                for L, obj in ((rm, obj_r), (cm, obj_c)))
    poses = _in_reach(T0, A0 if A0 is not None else A, params)
    counts = _structure_through(rms, cms, rm, cm, poses, params)
    starts = first_distinct([T0] + [poses[i] for i in np.argsort(counts, kind="stable")],
                            1 + _STARTS, lambda a, b: np.linalg.norm(a[:3, 3] - b[:3, 3])
                            > _DISTINCT_M)[1:]  # the lowest, apart from T0 and each other
    ends = [first] + [icp_level(rn, cn, start, params, li, min_cos, pairs) for start in starts]
    scores = _structure_through(rs, cs, rl, cl, [e[0] for e in ends], params)
    best = int(np.argmin(scores))
    if scores[best] > params.station_through_max * cells or at_T - scores[best] < least or \
            scores[best] >= params.station_through_ratio * at_T:
        return None
    return best_of(ends, best)
