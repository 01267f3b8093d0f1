"""Statistical outlier removal on the voxel grid (ALGORITHM.md section 1): the mean distance of
each voxel point to its k nearest neighbours among the 26 adjacent voxels (capped), and the
points whose mean lies beyond ``alpha`` standard deviations of the cloud's.

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.  The kernels are
numba-compiled (``cache=True, nogil=True``), single-threaded and without fastmath, so the NumPy
twins in ``tests/test_filters.py`` give identical results.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from robot_change import validate
from robot_change.cloud.geometry import check_points
from robot_change.cloud.voxels import (
    _KEY_FIELD,
    KEY_BITS,
)
from robot_change.errors import InputError

__all__ = [
    "knn_mean_distance",
    "statistical_outliers",
]


# --------------------------------------------------------------------------------------------
# statistical outlier removal on the voxel grid


@numba.njit(cache=True, nogil=True, inline="always")
def _push_best(best, i, k, d):
    """Insert d into row i of best (ascending, k long), dropping the largest: a branch-free
    min/max pass (the values are unchanged, only placed)."""
    row = np.uint64(i)  # an unsigned index spares numba's negative-index fix-up
    for j in range(k):
        b = best[row, j]
        best[row, j] = min(b, d)
        d = max(b, d)


@numba.njit(cache=True, nogil=True, inline="always")
def _knn_pairs(xs, ys, zs, ix, col_key, col_start, n_col, best, k):
    """Push the squared distance of every pair of adjacent voxels into both k-best rows.

    Each unordered pair is visited once.  Sorted keys group the voxels into rows along x
    (equal z and y, ``col_key = key >> KEY_BITS``; rows ``col_start[c]:col_start[c + 1]``,
    ascending ``ix``).  Per row: the pairs inside it (consecutive voxels whose x index differs
    by one), then the 4 "forward" rows at (z, y) offsets (0, +1), (+1, -1), (+1, 0), (+1, +1).
    Their keys increase with the row, so one pointer per direction walks forward through the
    row keys (no search, no hash); a neighbour row is then merge-joined with this one over x (a
    pointer into it moves forward while its x is below x - 1; the up to three voxels from
    there with x <= x + 1 are the neighbours).  A target row key reached only through a carry
    or borrow between the y and z fields is rejected by comparing the y fields.  Rows along x
    are the long ones in a room view: 1.1-1.6x faster than along z on our frames
    (docs/benchmarks.md).

    Inlined, so that a constant ``k`` (the default 4, see :func:`_knn_mean_kernel`) unrolls
    the k-best insertions.
    """
    dz1 = np.int64(1) << KEY_BITS
    # per direction: row key offset, y field difference, pointer into the rows
    offsets = np.array([1, dz1 - 1, dz1, dz1 + 1], dtype=np.int64)
    dys = np.array([1, -1, 0, 1], dtype=np.int64)
    cptr = np.zeros(4, dtype=np.int64)
    for c in range(n_col):
        a0 = col_start[c]
        a1 = col_start[c + 1]
        ck = col_key[c]
        for i in range(a0, a1 - 1):
            if ix[i + 1] == ix[i] + 1:
                dx = xs[i] - xs[i + 1]
                dy = ys[i] - ys[i + 1]
                dz = zs[i] - zs[i + 1]
                d2 = dx * dx + dy * dy + dz * dz
                _push_best(best, i, k, d2)
                _push_best(best, i + 1, k, d2)
        for r in range(4):
            target = ck + offsets[r]
            q = cptr[r]
            while q < n_col and col_key[q] < target:
                q += 1
            cptr[r] = q
            if q == n_col or col_key[q] != target:
                continue
            if (target & _KEY_FIELD) - (ck & _KEY_FIELD) != dys[r]:
                continue  # a carry or borrow between the y and z fields
            b1 = col_start[q + 1]
            j = col_start[q]
            for i in range(a0, a1):
                xi = ix[i]
                while j < b1 and ix[np.uint64(j)] < xi - 1:
                    j += 1
                x = xs[i]
                y = ys[i]
                z = zs[i]
                p = j
                # unsigned indices: no negative-index fix-up in the innermost loop
                while p < b1 and ix[np.uint64(p)] <= xi + 1:
                    at = np.uint64(p)
                    dx = x - xs[at]
                    dy = y - ys[at]
                    dz = z - zs[at]
                    d2 = dx * dx + dy * dy + dz * dz
                    _push_best(best, i, k, d2)
                    _push_best(best, p, k, d2)
                    p += 1


@numba.njit(cache=True, nogil=True, inline="always")
def _knn_mean_body(points, keys, k, cap):
    """:func:`_knn_mean_kernel`, inlined there for a constant k = 4 and for any k."""
    m = keys.shape[0]
    cap2 = cap * cap
    best = np.full((m, k), cap2, dtype=np.float64)
    xs = np.empty(m, dtype=np.float64)
    ys = np.empty(m, dtype=np.float64)
    zs = np.empty(m, dtype=np.float64)
    ix = np.empty(m, dtype=np.int64)
    col_key = np.empty(m, dtype=np.int64)
    col_start = np.empty(m + 1, dtype=np.int64)
    n_col = 0
    for i in range(m):
        xs[i] = points[i, 0]
        ys[i] = points[i, 1]
        zs[i] = points[i, 2]
        key = keys[i]
        ix[i] = key & _KEY_FIELD
        column = key >> KEY_BITS
        if n_col == 0 or column != col_key[n_col - 1]:
            col_key[n_col] = column
            col_start[n_col] = i
            n_col += 1
    col_start[n_col] = m
    _knn_pairs(xs, ys, zs, ix, col_key, col_start, n_col, best, k)
    out = np.empty(m, dtype=np.float64)
    for i in range(m):
        s = 0.0
        for j in range(k):
            s += math.sqrt(best[i, j])
        out[i] = s / k
    return out


@numba.njit(cache=True, nogil=True)
def _knn_mean_kernel(points, keys, k, cap):
    """Mean of the k smallest min(distance, cap) to points in the 26 adjacent voxels, missing
    neighbours counting as cap.  ``keys`` strictly increasing.  Returns (M,) float64.

    The pairs are found row by row along x (:func:`_knn_pairs`).  The k best are kept per point
    as squared distances (capped at cap**2), ascending; a pair's distance is inserted into
    both points' rows, and as insertion only places values, the order in which pairs arrive
    does not change the result.  ``sqrt`` is taken of those k at the end, which gives the same
    numbers as capping the distances (``sqrt(x * x) == x`` in IEEE arithmetic), summed in
    ascending order.  k = 4 (the default of :func:`statistical_outliers`) runs a copy of the
    pair loop compiled for that constant, with the insertions unrolled (1.4x faster).
    """
    if k == 4:
        return _knn_mean_body(points, keys, 4, cap)
    return _knn_mean_body(points, keys, k, cap)


def _check_cloud_keys(points: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    points = check_points(points)
    if not isinstance(keys, np.ndarray) or keys.dtype != np.int64 or keys.ndim != 1:
        raise InputError("keys must be the (M,) int64 keys of a VoxelGrid (VoxelGrid.keys)")
    if keys.shape[0] != points.shape[0]:
        raise InputError(
            f"keys has {keys.shape[0]} rows but points has {points.shape[0]}; pass the points "
            "and keys of the same VoxelGrid"
        )
    if keys.shape[0] > 1 and not np.all(keys[1:] > keys[:-1]):
        raise InputError("keys must be strictly increasing, as VoxelGrid returns them; pass a "
                         "VoxelGrid's points and keys unchanged (or subset them with a mask)")
    if not np.all(np.isfinite(points)):
        raise InputError("points contain NaN or inf; pass voxel_grid(...).points")
    return points, np.ascontiguousarray(keys)


def knn_mean_distance(
    points: np.ndarray, keys: np.ndarray, k: int, cap_m: float
) -> np.ndarray:
    """Per-point outlier statistic on a voxel cloud.

    Parameters
    ----------
    points : (M, 3) float32
        Voxel centroids (``VoxelGrid.points``, or a masked subset of them).
    keys : (M,) int64
        Their packed voxel keys, strictly increasing (``VoxelGrid.keys``).
    k : int
        Neighbours averaged, 1..26.
    cap_m : float
        Distances above ``cap_m`` count as ``cap_m``; so does each missing neighbour.

    Returns
    -------
    (M,) float64
        Mean over the k smallest of ``min(distance, cap_m)`` to the points in the 26 adjacent
        voxels (Chebyshev voxel distance 1), in metres.
    """
    points, keys = _check_cloud_keys(points, keys)
    validate.whole("knn_mean_distance", "k", k, 1, 26, unit=" (the 26 adjacent voxels)")
    cap = validate.positive("knn_mean_distance", "cap_m", cap_m, unit=" metres")
    return _knn_mean_kernel(points, keys, int(k), cap)


def statistical_outliers(
    points: np.ndarray,
    keys: np.ndarray,
    leaf_m: float,
    k: int = 4,
    alpha: float = 2.0,
    cap_leaves: float = 2.0,
) -> np.ndarray:
    """Statistical outlier removal on a voxel cloud; returns the (M,) bool inlier mask.

    The statistic of a point is :func:`knn_mean_distance` with ``cap_m = cap_leaves * leaf_m``;
    a point is an outlier when it is above ``mean + alpha * std`` of that statistic over the
    cloud (PCL's rule, with the neighbour search restricted to the 26 adjacent voxels).

    Defaults, for one point per voxel (PCL's k = 50 assumes the raw cloud's density):

    * ``k = 4``: a point inside a surface has 8 neighbours in its plane, on a straight edge 5,
      at a convex corner 3, on a one-voxel-wide line 2, an isolated speck 0.  k = 4 gives
      surfaces and their edges the same statistic (about one leaf), so object outlines survive;
      lines and corners score higher, specks and pairs score the cap.
    * ``cap_leaves = 2``: adjacent centroids are up to 2*sqrt(3) leaves apart, so 2 leaves keeps a
      single far neighbour (or a gap) from dominating the mean while a missing neighbour still
      costs more than any present one at a typical distance of 1-1.4 leaves.
    * ``alpha = 2``: the statistic is concentrated near one leaf (measured mean 0.82-1.06
      leaves, std 0.08-0.21 on the TUM office frame, the table-top frames and a carpet scene at
      1 and 2 cm), so mean + 2 std lay at 0.97-1.47 leaves: below the 1.75 leaves of a pair of
      specks and the 2 of an isolated one, which were dropped on every frame measured.  On the
      table-top frames (2 cm leaf) alpha = 1, PCL's value, dropped up to 13 % of an object's
      pixels and 7 % of the table's (edges, rims, handles); alpha = 2 at most 2.6 % and 2.0 %;
      alpha = 3 0.4 % and 0.1 %, but it lets points with two neighbours (veil pixels along
      depth edges, ~1.5-1.6 leaves) through on the noisier room frame (threshold 1.67 leaves
      at 1 cm).

    Parameters
    ----------
    points : (M, 3) float32, keys : (M,) int64
        A voxel grid's centroids and keys (or a masked subset of both).
    leaf_m : float
        The voxel grid's leaf size in metres.
    k : int
        Neighbours, 1..26.
    alpha : float
        Threshold in standard deviations, >= 0.
    cap_leaves : float
        Distance cap in leaf sizes, > 0.
    """
    leaf = validate.positive("statistical_outliers", "leaf_m", leaf_m, 1e6, unit=" metres")
    a = validate.number("statistical_outliers", "alpha", alpha, 0.0, math.inf,
                        unit=" standard deviations")
    cap = validate.positive("statistical_outliers", "cap_leaves", cap_leaves,
                            unit=" leaf sizes") * leaf
    stat = knn_mean_distance(points, keys, k, cap)
    if stat.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    threshold = stat.mean() + a * stat.std()
    return stat <= threshold
