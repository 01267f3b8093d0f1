"""Table tops: a station whose reference is mostly one table of at most 2 m (docs/algorithm.md,
"Registration", steps 6b, 6c and 7).

On a table top with the change in view, the moved objects drag ICP into a compromise: the
table pins only height, pitch and roll, and the objects are most of what fixes the pose in the
table's plane.  So here

* **the gate** (:func:`table_planes`): each view's dominant plane; the reference's must hold
  most of its cells and both must span at most ``table_max_extent_m`` (a room's floor is
  larger);
* **starts** (:func:`table_starts`): top-down occupancy grids of the two views on their planes,
  cross-correlated by FFT over in-plane shifts for a few yaws; the best peaks are starts for
  (x, y, yaw) in the plane that compete with the main estimate;
* **trimming the change** (:func:`without_changed_objects`): the objects (cells above the
  table) that contradict the other view more than they fit it get no normal, so ICP runs again
  on the table and the objects that stayed put;
* **saying a weak pose** (:func:`table_pose_weak`, :func:`in_plane_names`): the directions in
  the table's plane are reported weak when the two tables do not overlap at the estimate, no
  object stayed put, or the normal equations flag one of them.

Kernels are ``@njit(cache=True, nogil=True)`` with NumPy twins in
``tests/test_registration.py``.
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from collections.abc import Callable
from typing import Any

import numba
import numpy as np
from scipy import ndimage

from .agreement import agreement_counts, cell_states
from .params import RegistrationParams
from .pyramid import Level
from .result import AXES
from .rigid import invert, rigid

#: A cell within this distance of a view's table plane is on it (metres).
ON_PLANE_M = 0.01
#: :func:`~.agreement.cell_states` judges every cell with this direction and 0 (any normal).
_EVERY_CELL = np.zeros(3)


#: :func:`_dominant_plane` of each level still alive: a station's reference keeps its pyramid
#: between checks (``register_depth(..., keep=)``), and its plane with it.
_PLANES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _dominant_plane(level: Level) -> tuple[np.ndarray, float, float]:
    """The plane holding most cells of ``level``, :func:`planes_of`'s first, made once per
    level object; (n, d, 0) with fraction 0 when there are too few cells."""
    out = _PLANES.get(level)
    if out is None:
        planes = planes_of(level, 1)
        out = _PLANES[level] = planes[0] if planes else (np.array([0.0, 0.0, 1.0]), 0.0, 0.0)
    return out


def planes_of(level: Level, k: int, max_dist_m: float = ON_PLANE_M, min_cos: float = 0.95,
              n_seeds: int = 64) -> list[tuple[np.ndarray, float, float]]:
    """Up to ``k`` planes of ``level``, largest first: each of ``n_seeds`` cells with a
    normal, evenly spaced in image order, proposes the plane through it along its normal; a
    cell supports a plane within ``max_dist_m`` metres of it with a normal within
    acos(min_cos).  The winner is refitted to its supporters (least squares), they are taken
    out, and the next plane is looked for among the cells left, while they are at least
    3 ``n_seeds``.  Each is (n (3,) unit normal, d m, fraction of the cells with a normal
    supporting it), n . p + d = 0 on the plane and d >= 0 (the camera on the positive side)."""
    ok = level.has_normal
    p, q = level.vertex[ok], level.normal[ok]
    total = len(p)
    out = []
    while len(out) < k and len(p) >= 3 * n_seeds:
        seeds = np.linspace(0, len(p) - 1, n_seeds).astype(np.int64)
        sn = q[seeds]                                          # (S, 3)
        sd = -np.einsum("ij,ij->i", sn, p[seeds])              # (S,)
        support = (np.abs(p @ sn.T + sd) < max_dist_m) & (np.abs(q @ sn.T) > min_cos)  # (N, S)
        counts = support.sum(axis=0)
        best = int(np.argmax(counts))
        taken = support[:, best]
        inl = p[taken]
        c = inl.mean(axis=0)
        _u, _s, vt = np.linalg.svd(inl - c, full_matrices=False)
        n = vt[2]
        d = -float(n @ c)
        if d < 0:
            n, d = -n, -d
        out.append((n, d, float(counts[best]) / total))
        p, q = p[~taken], q[~taken]
    return out


def plane_frame(n: np.ndarray, d: float) -> np.ndarray:
    """(4, 4) camera-from-plane transform of the plane n . p + d = 0 (``n`` (3,) unit, ``d``
    m >= 0): origin the camera's foot on the plane, z along ``n`` (towards the camera), x the
    camera's x projected onto the plane (its y when ``n`` is along x)."""
    ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(ex) < 1e-6:  # a plane facing the camera's x: use its y instead
        ex = np.array([0.0, 1.0, 0.0]) - n[1] * n
    ex /= np.linalg.norm(ex)
    F = np.eye(4)
    F[:3, 0] = ex
    F[:3, 1] = np.cross(n, ex)
    F[:3, 2] = n
    F[:3, 3] = -d * n
    return F


@numba.njit(cache=True, nogil=True)
def _plane_grid(vertex, rot, trans, cell_m, lo_x, lo_y, rows, cols, object_m, below_m):
    """Top-down occupancy of a vertex map ``vertex`` (h, w, 3) m on a plane: each cell with a
    reading (z > 0) is moved to plane coordinates q = rot @ p + trans (``rot`` (3, 3),
    ``trans`` (3,): plane-from-camera, q_z the height above the plane, m) and binned by
    (q_x - lo_x, q_y - lo_y) / cell_m into a (rows, cols) grid.  A grid cell is +1 when a
    reading in it stands more than ``object_m`` above the plane, else -1 when one lies within
    (-below_m, object_m] of it, else 0 (nothing seen there).  Returns (rows, cols) float64."""
    out = np.zeros((rows, cols))
    h, w = vertex.shape[0], vertex.shape[1]
    for i in range(h):
        for j in range(w):
            z = vertex[i, j, 2]
            if z <= 0.0:
                continue
            x, y = vertex[i, j, 0], vertex[i, j, 1]
            qx = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
            qy = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
            qz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
            if qz <= -below_m:
                continue
            r = int(math.floor((qx - lo_x) / cell_m))
            c = int(math.floor((qy - lo_y) / cell_m))
            if r < 0 or c < 0 or r >= rows or c >= cols:
                continue
            if qz > object_m:
                out[r, c] = 1.0
            elif out[r, c] == 0.0:
                out[r, c] = -1.0
    return out


def _parabola_peak(before: float, after: float, at: float) -> float:
    """Offset (cells, within +-0.5 for a peak) of the vertex of the parabola through three
    equally spaced samples with ``at`` in the middle; 0 unless it opens downwards."""
    den = before - 2.0 * at + after
    return 0.5 * (before - after) / den if den < 0 else 0.0


@dataclasses.dataclass(frozen=True, eq=False)
class TablePlane:
    """A view's table plane: ``frame`` (4, 4) camera-from-plane (:func:`plane_frame`), ``lo``,
    ``hi`` (2,) the 2-98 % extent of the cells on it in the plane's x and y, metres."""

    frame: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def heights(self, vertex: np.ndarray) -> np.ndarray:
        """(h, w) height above the plane (towards the camera) of each point of ``vertex``
        (h, w, 3), metres."""
        n = self.frame[:3, 2]
        return vertex @ n - float(n @ self.frame[:3, 3])


def table_planes(ref_levels: list[Level], cur_levels: list[Level],
                 params: RegistrationParams) -> tuple[TablePlane, TablePlane] | None:
    """The (reference, current) table planes when the views are of a table top, else None.
    Each view's dominant plane (:func:`_dominant_plane`, coarsest level) must have its
    supporters (2-98 %) span no more than ``table_max_extent_m`` in either plane direction (a
    room's floor is larger).  Whether the station is a table top is the reference's to say:
    its plane must hold ``table_plane_fraction`` of its cells.  The current's plane need only
    be that table seen again, its normal within ``table_max_tilt_deg`` of the reference's: a
    revisit displaced sideways sees less of the table and more of what lies beyond it."""
    planes = []
    for level in (ref_levels[0], cur_levels[0]):
        n, d, frac = _dominant_plane(level)
        if frac == 0.0 or (not planes and frac < params.table_plane_fraction):
            return None
        if planes and float(n @ planes[0].frame[:3, 2]) < math.cos(
                math.radians(params.table_max_tilt_deg)):
            return None  # not the reference's table
        F = plane_frame(n, d)
        v = level.vertex.reshape(-1, 3)
        q = (v[v[:, 2] > 0] - F[:3, 3]) @ F[:3, :3]
        on = q[np.abs(q[:, 2]) < ON_PLANE_M, :2]
        lo, hi = np.percentile(on, 2, axis=0), np.percentile(on, 98, axis=0)
        if float((hi - lo).max()) > params.table_max_extent_m:
            return None  # a floor, not a table top
        planes.append(TablePlane(F, lo, hi))
    return planes[0], planes[1]


def table_starts(ref_levels: list[Level], cur_levels: list[Level],
                 planes: tuple[TablePlane, TablePlane], params: RegistrationParams
                 ) -> list[np.ndarray]:
    """Up to ``params.table_starts`` (4, 4) starting estimates of ``T_ref_from_cur`` for a
    table top whose (reference, current) ``planes`` are :func:`table_planes`'.  Each start
    puts the current plane on the reference's and moves it in the plane by a yaw about its
    normal and a shift: the peaks of the cross-correlation (FFT, cyclic, with a 0.25 m guard
    band round the reference's plane) of the two views' top-down grids (:func:`_plane_grid`,
    finest level, ``table_cell_m`` cells), one grid of the current per yaw, the best distinct
    (apart by > 2.5 table_yaw_step_deg or > 3 cells) of all yaws, best first."""
    Fr, lo, hi = planes[0].frame, planes[0].lo, planes[0].hi
    Fc = planes[1].frame
    rl, cl = ref_levels[-1], cur_levels[-1]
    cell = params.table_cell_m
    to_r = invert(Fr)
    margin = 0.25  # the cyclic correlation's guard band: more than any shift looked for
    lo = lo - margin
    rows, cols = (8 * int(math.ceil(e / cell / 8)) for e in hi + margin - lo)
    args = (cell, float(lo[0]), float(lo[1]), rows, cols, params.table_object_m, 0.03)
    G = np.fft.rfft2(_plane_grid(rl.vertex, to_r[:3, :3].copy(), to_r[:3, 3].copy(), *args))
    to_c = invert(Fc)
    n_yaw = int(math.floor(params.table_yaw_deg / params.table_yaw_step_deg + 1e-9))
    yaws = np.radians(params.table_yaw_step_deg * np.arange(-n_yaw, n_yaw + 1))
    k = params.table_starts
    peaks = []  # (score, yaw, shift_x, shift_y)
    for yaw in yaws:
        M = _in_plane(yaw, 0.0, 0.0) @ to_c
        cc = np.fft.irfft2(G * np.conj(np.fft.rfft2(_plane_grid(
            cl.vertex, M[:3, :3].copy(), M[:3, 3].copy(), *args))), s=(rows, cols))
        flat = cc.ravel()
        for f in np.argpartition(flat, -k)[-k:]:
            r, c = divmod(int(f), cols)
            # sub-cell peak: a parabola through the neighbours along each axis
            dr_ = _parabola_peak(cc[(r - 1) % rows, c], cc[(r + 1) % rows, c], cc[r, c])
            dc_ = _parabola_peak(cc[r, (c - 1) % cols], cc[r, (c + 1) % cols], cc[r, c])
            sr = r - rows if r > rows // 2 else r
            sc = c - cols if c > cols // 2 else c
            peaks.append((float(flat[f]), float(yaw), (sr + dr_) * cell, (sc + dc_) * cell))
    peaks.sort(key=lambda t: -t[0])
    chosen = first_distinct(peaks, k, lambda a, b: abs(a[1] - b[1]) > math.radians(
        2.5 * params.table_yaw_step_deg) or math.hypot(a[2] - b[2], a[3] - b[3]) > 3 * cell)
    return [Fr @ _in_plane(yaw, sx, sy) @ to_c for _score, yaw, sx, sy in chosen]


def first_distinct(items: list, k: int, apart: Callable[[Any, Any], bool]) -> list:
    """Up to ``k`` of ``items``, in their order, each ``apart`` from every one taken before."""
    out: list = []
    for item in items:
        if all(apart(item, other) for other in out):
            out.append(item)
            if len(out) == k:
                break
    return out


def _in_plane(yaw: float, x: float, y: float) -> np.ndarray:
    """(4, 4) a turn by ``yaw`` (radians) about a plane's normal (z) and a shift (``x``, ``y``,
    m) along it."""
    c, s = math.cos(yaw), math.sin(yaw)
    return rigid(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), (x, y, 0.0))


# --------------------------------------------------------------------------- trimming the change


def _object_states(own: Level, other: Level, M: np.ndarray, plane: TablePlane,
                   params: RegistrationParams, max_dist: float, min_cos: float
                   ) -> tuple[np.ndarray, int, np.ndarray]:
    """The objects of ``own`` on its table ``plane`` and what ``other`` says of each cell,
    seen with ``M`` (4, 4) other-from-own: (labels (h, w) int, 0 off any object; the number
    of objects; :func:`~.agreement.cell_states` (h, w) int8).  An object is a 4-connected
    group of cells standing more than ``table_object_m`` above ``plane``."""
    objects, n = ndimage.label((own.vertex[:, :, 2] > 0)
                               & (plane.heights(own.vertex) > params.table_object_m))
    states = cell_states(*own.onto(other, M), max_dist, min_cos, *params.noise_args(),
                         _EVERY_CELL, 0.0)
    return objects, n, states


def _static_object_share(rl: Level, cl: Level, T: np.ndarray,
                         planes: tuple[TablePlane, TablePlane], params: RegistrationParams,
                         min_cos: float) -> float:
    """Of the object cells of both views (reference ``rl``, current ``cl``, one level; their
    table ``planes``), the share that fit the other view at ``T`` (T_ref_from_cur): near 0
    when no object stayed put, 1 on a table where nothing changed.  1 when there is no object
    (a bare table: its weak directions are the normal equations')."""
    fit = total = 0
    for own, other, M, plane in ((rl, cl, invert(T), planes[0]), (cl, rl, T, planes[1])):
        objects, _n, states = _object_states(own, other, M, plane, params,
                                             params.max_distance_m[-1], min_cos)
        on = objects > 0
        total += int(np.count_nonzero(on))
        fit += int(np.count_nonzero(on & (states == 1)))
    return fit / total if total else 1.0


def _changed_objects(own: Level, other: Level, M: np.ndarray, plane: TablePlane,
                     params: RegistrationParams, max_dist: float, min_cos: float) -> np.ndarray:
    """(h, w) bool: the cells of ``own`` in objects that changed, as seen from ``other`` with
    ``M`` (4, 4) other-from-own (:func:`_object_states`).  An object changed when its cells
    that contradict ``other`` are more than ``trim_conflict_share`` of those that contradict
    or fit (and at least 2)."""
    objects, n, states = _object_states(own, other, M, plane, params, max_dist, min_cos)
    out = np.zeros(objects.shape, dtype=bool)
    if n == 0:
        return out
    counts = np.bincount((3 * objects + states).ravel(), minlength=3 * (n + 1)).reshape(-1, 3)
    fits, contradicts = counts[:, 1], counts[:, 2]
    changed = (contradicts > params.trim_conflict_share * (fits + contradicts)) & \
        (contradicts >= 2)
    changed[0] = False  # not an object: the table, and cells with no reading
    return changed[objects]


def without_changed_objects(rl: Level, cl: Level, planes: tuple[TablePlane, TablePlane],
                            T: np.ndarray, params: RegistrationParams, li: int, min_cos: float
                            ) -> tuple[Level, Level]:
    """The two views of level ``li`` (reference, current) with the normals of their changed
    objects' cells (:func:`_changed_objects`, judged at ``T``) set to zero, so ICP pairs
    only the table and the objects that stayed put."""
    return tuple(own.without(_changed_objects(own, other, M, plane, params,
                                              params.max_distance_m[li], min_cos), points=False)
                 for own, other, M, plane in ((rl, cl, invert(T), planes[0]),
                                                  (cl, rl, T, planes[1])))


def _table_holes(own: Level, other: Level, M: np.ndarray, plane: TablePlane,
                 params: RegistrationParams) -> float:
    """Of the cells of ``own`` on its table ``plane`` (within ``ON_PLANE_M``) that land in the
    image of ``other`` when moved by ``M`` (4, 4) other-from-own, the share that land on no
    reading there (:func:`~.agreement.agreement_counts`' holes)."""
    on = (own.vertex[:, :, 2] > 0) & (np.abs(plane.heights(own.vertex)) < ON_PLANE_M)
    _, _, _, compared, holes, _ = agreement_counts(
        *own.without(~on, points=True).onto(other, M), 0.0, 1.0, *params.noise_args(0.0), False)
    return holes / (holes + compared) if holes + compared else 0.0


def table_pose_weak(rl: Level, cl: Level, T: np.ndarray,
                    planes: tuple[TablePlane, TablePlane], weak: tuple[str, ...],
                    params: RegistrationParams, min_cos: float) -> bool:
    """Whether the estimate ``T`` (T_ref_from_cur) of a table top (finest levels ``rl``,
    ``cl``; their table ``planes``) is not to be trusted in the table's plane: one of the
    directions there is already ``weak`` by the normal equations (the three are coupled: a
    slide along the table is nearly a turn about a far axis, and the weakest direction mixes
    them), the two tables do not overlap (``table_outline_holes``), or no object stayed put
    (``table_static_share``)."""
    if any(name in weak for name in in_plane_names(planes[1])):
        return True
    if params.table_outline_holes > 0 and min(
            _table_holes(rl, cl, invert(T), planes[0], params),
            _table_holes(cl, rl, T, planes[1], params)) > params.table_outline_holes:
        return True
    return params.table_static_share > 0 and _static_object_share(
        rl, cl, T, planes, params, min_cos) < params.table_static_share


def in_plane_names(plane: TablePlane) -> tuple[str, ...]:
    """The :data:`AXES` names nearest to the motions that keep a view on its table ``plane``:
    the slides along the plane's two axes and the turn about its normal (camera frame)."""
    F = plane.frame
    names = [AXES[3 + int(np.argmax(np.abs(F[:3, k])))] for k in (0, 1)]
    names.append(AXES[int(np.argmax(np.abs(F[:3, 2])))])
    return tuple(dict.fromkeys(names))
