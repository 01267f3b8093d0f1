"""Point-cloud filters (ALGORITHM.md section 1): voxel grid, statistical outlier removal,
RANSAC plane fit and removal, and temporal depth fusion.

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.  The kernels are
numba-compiled (``cache=True, nogil=True``), single-threaded and without fastmath, so the NumPy
twins in the tests give identical results.

Voxel keys
----------
A voxel is ``(ix, iy, iz) = floor(p * (1 / leaf_m))`` with the global origin at the camera.
Each index must lie in ``[-2**20, 2**20 - 1]`` (about +-10 km at a 1 cm leaf) and is packed into
one int64 as ``(iz + 2**20) << 42 | (iy + 2**20) << 21 | (ix + 2**20)``, so sorting by key sorts
by z, then y, then x: the voxels of one row along x (camera frame: a horizontal row across the
image) are consecutive, the long runs on a room's floor, ceiling and facing walls that the
outlier search walks (:func:`_knn_pairs`).  Points outside that range are dropped, never
wrapped.  (Scene files before format version 2 packed x first; see robot_change.change.scene.)
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numba
import numpy as np

from robot_change import validate
from robot_change.cloud.geometry import check_points
from robot_change.errors import InputError

__all__ = [
    "KEY_BITS",
    "KEY_MAX_INDEX",
    "KEY_MIN_INDEX",
    "Plane",
    "VOXEL_CHUNK",
    "VOXEL_TABLE_MIN_SLOTS",
    "VoxelGrid",
    "fit_plane_ransac",
    "fuse_depth",
    "knn_mean_distance",
    "pack_keys",
    "RANSAC_BAIL_SIGMAS",
    "RANSAC_SAMPLE",
    "ransac_sample",
    "ransac_triples",
    "remove_plane",
    "statistical_outliers",
    "unpack_keys",
    "voxel_grid",
    "voxel_table_size",
]

#: Bits per axis in a packed voxel key.
KEY_BITS = 21
_KEY_OFFSET = 1 << (KEY_BITS - 1)
_KEY_FIELD = (1 << KEY_BITS) - 1
#: Smallest and largest voxel index per axis that a key can hold.
KEY_MIN_INDEX = -_KEY_OFFSET
KEY_MAX_INDEX = _KEY_OFFSET - 1

# Fibonacci hashing constant 2**64 / golden ratio.
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)


# --------------------------------------------------------------------------------------------
# voxel keys


def pack_keys(indices: np.ndarray) -> np.ndarray:
    """(M, 3) integer voxel indices -> (M,) int64 packed keys (see the module docstring).
    Raises :class:`InputError` for indices outside ``[KEY_MIN_INDEX, KEY_MAX_INDEX]``."""
    indices = np.asarray(indices)
    if indices.ndim != 2 or indices.shape[1] != 3 or indices.dtype.kind not in "iu":
        raise InputError(f"voxel indices must be an (M, 3) integer array, got {indices.dtype} "
                         f"of shape {indices.shape}")
    idx = indices.astype(np.int64)
    if idx.size and (idx.min() < KEY_MIN_INDEX or idx.max() > KEY_MAX_INDEX):
        raise InputError(f"voxel indices must lie in {KEY_MIN_INDEX}..{KEY_MAX_INDEX}")
    biased = idx + _KEY_OFFSET
    return (biased[:, 2] << (2 * KEY_BITS)) | (biased[:, 1] << KEY_BITS) | biased[:, 0]


def unpack_keys(keys: np.ndarray) -> np.ndarray:
    """(M,) int64 packed keys -> (M, 3) int64 voxel indices ``(ix, iy, iz)``."""
    keys = np.asarray(keys, dtype=np.int64)
    out = np.empty((keys.shape[0], 3), dtype=np.int64)
    out[:, 0] = (keys & _KEY_FIELD) - _KEY_OFFSET
    out[:, 1] = ((keys >> KEY_BITS) & _KEY_FIELD) - _KEY_OFFSET
    out[:, 2] = ((keys >> (2 * KEY_BITS)) & _KEY_FIELD) - _KEY_OFFSET
    return out


# --------------------------------------------------------------------------------------------
# voxel grid


@dataclasses.dataclass(frozen=True, eq=False)
class VoxelGrid:
    """One point per occupied voxel.

    ``points``: (M, 3) float32 centroids in metres (accumulated in float64).  ``counts``: (M,)
    int32 input points per voxel.  ``keys``: (M,) int64 packed voxel indices, strictly
    increasing.  ``inverse``: (N,) int32, for each input point the row of its voxel, -1 for
    dropped rows (NaN/inf, or a voxel index the key cannot hold).  ``leaf_m``: edge length.
    """

    points: np.ndarray
    counts: np.ndarray
    keys: np.ndarray
    inverse: np.ndarray
    leaf_m: float

    def __len__(self) -> int:
        return int(self.points.shape[0])


#: Points per chunk in :func:`_voxel_kernel`: keys and hash slots of a chunk are computed in one
#: branch-free loop the compiler vectorises, then probed in order.  A chunk plays the part an
#: image row plays in :func:`robot_change.cloud.depth_voxels.depth_voxel_grid`.
VOXEL_CHUNK = 512

#: Smallest hash table of a voxel band, in slots (int32 record numbers: 64 KiB).
VOXEL_TABLE_MIN_SLOTS = 1 << 14

#: Largest radix digit in :func:`_radix_order`: 2**12 int32 counters (16 KiB) stay in L1, and
#: a room's codes (22 bits at a 3 cm leaf, 23-24 at 2 cm) take two passes (at 2 cm, 11-bit
#: digits took three).  int32 counters: the sort ran 2.5x faster than with int64 ones.
_RADIX_DIGIT = 12


def voxel_table_size(row: int) -> tuple[int, int]:
    """Hash table of the voxel kernels for rows (or chunks) of ``row`` points.

    Returns ``(bits, limit)``: the table has ``2**bits`` slots, at least
    :data:`VOXEL_TABLE_MIN_SLOTS` and at least ``4 * row``; a band of rows is closed at the start
    of a row when it already holds more than ``limit - row`` records (``limit`` = slots / 8), so a
    band holds at most ``max(limit, row)`` records and the table is at most a quarter full.
    """
    bits = 1
    while (1 << bits) < max(VOXEL_TABLE_MIN_SLOTS, 4 * row):
        bits += 1
    return bits, (1 << bits) // 8


@numba.njit(cache=True, nogil=True)
def _bit_length(value):
    bits = 0
    while bits < 64 and (value >> bits) != 0:
        bits += 1
    return bits


@numba.njit(cache=True, nogil=True)
def _radix_order(codes, bits):
    """Stable LSD radix argsort of (P,) int64 codes in 0..2**bits - 1.

    Returns (order (P,) int32, scratch (P,) int32); ``codes`` is left sorted.  Digits of at most
    ``_RADIX_DIGIT`` bits, so a room at a 2 or 3 cm leaf (22-24 bits) takes two linear passes.
    """
    m = codes.shape[0]
    order = np.empty(m, dtype=np.int32)
    scratch = np.empty(m, dtype=np.int32)
    for j in range(m):
        order[j] = j
    passes = (bits + _RADIX_DIGIT - 1) // _RADIX_DIGIT
    if passes == 0 or m < 2:
        return order, scratch
    digit = (bits + passes - 1) // passes
    buckets = 1 << digit
    dmask = buckets - 1
    counts = np.empty(buckets, dtype=np.int32)
    tmp_codes = np.empty(m, dtype=np.int64)
    src_codes = codes
    dst_codes = tmp_codes
    src = order
    dst = scratch
    shift = 0
    for _ in range(passes):
        counts[:] = 0
        for j in range(m):
            counts[(src_codes[j] >> shift) & dmask] += 1
        total = 0
        for b in range(buckets):
            c = counts[b]
            counts[b] = total
            total += c
        for j in range(m):
            c = src_codes[j]
            b = (c >> shift) & dmask
            at = counts[b]
            counts[b] = at + 1
            dst_codes[at] = c
            dst[at] = src[j]
        src_codes, dst_codes = dst_codes, src_codes
        src, dst = dst, src
        shift += digit
    if passes % 2 == 1:
        codes[:] = tmp_codes
    return src, dst


@numba.njit(cache=True, nogil=True, inline="always")
def _voxel_slot(key, tshift):
    """Home slot of a packed key: Fibonacci hashing (top bits of key * 2**64 / golden ratio)."""
    return (np.uint64(key) * _HASH_MULT) >> tshift


@numba.njit(cache=True, nogil=True)
def _voxel_insert(key, slot, table, tmask, rec_keys, rec, first, p):
    """Slow path of the voxel kernels: find ``key`` among the records ``first..p-1`` of the
    current band by linear probing from ``slot``, or append record ``p`` for it.

    ``table`` (S,) int32 holds record numbers; a slot whose record is below ``first`` (an earlier
    band, or -1) counts as empty, so a new band needs no clearing.  ``rec_keys`` (P,) int64 and
    ``rec`` (P, 4) float64 (sum x, y, z, count) are the records.  Returns (record, new p).
    """
    while True:
        row = table[slot]
        if row < first:
            table[slot] = p
            at = np.uint64(p)  # unsigned indices: no negative-index fix-up
            rec_keys[at] = key
            rec[at, 0] = 0.0
            rec[at, 1] = 0.0
            rec[at, 2] = 0.0
            rec[at, 3] = 0.0
            return p, p + 1
        if rec_keys[np.uint64(row)] == key:
            return row, p
        slot = (slot + np.uint64(1)) & tmask


@numba.njit(cache=True, nogil=True, inline="always")
def _band_workspace(n, tbits):
    """Scratch of the voxel kernels for up to ``n`` points: (per-point records (n,) int32,
    table mask, hash shift, empty table (2**tbits,) int32, record keys (n,) int64, records
    (n, 4) float64).  At most one record per point; pages never touched cost nothing."""
    return (np.empty(n, dtype=np.int32), np.uint64((1 << tbits) - 1), np.uint64(64 - tbits),
            np.full(1 << tbits, -1, dtype=np.int32), np.empty(n, dtype=np.int64),
            np.empty((n, 4), dtype=np.float64))


@numba.njit(cache=True, nogil=True, inline="always")
def _pack_key(fx, fy, fz, ok):
    """Packed key of floored voxel indices (float64, in the key range when ``ok``), -1 when
    not ``ok``.  The index fits 21 bits, so the int32 conversion vectorises."""
    kx = np.int64(np.int32(fx if ok else 0.0)) + _KEY_OFFSET
    ky = np.int64(np.int32(fy if ok else 0.0)) + _KEY_OFFSET
    kz = np.int64(np.int32(fz if ok else 0.0)) + _KEY_OFFSET
    key = (kz << (2 * KEY_BITS)) | (ky << KEY_BITS) | kx
    return key if ok else np.int64(-1)


@numba.njit(cache=True, nogil=True, inline="always")
def _accumulate_row(keys, slots, xs, ys, zs, n, out, table, tmask, rec_keys, rec, first, p):
    """Add the first ``n`` points of a row (keys (n,) int64, -1 = none; home slots; float64
    coordinates) to the current band's records: a hit in the home slot is the fast path, else
    :func:`_voxel_insert`.  ``out[i]`` gets the record of point i (-1 = none).  Returns
    (new p, points added)."""
    added = 0
    for i in range(n):
        key = keys[i]
        if key < 0:
            out[i] = -1
            continue
        added += 1
        slot = slots[i]
        r = table[slot]
        if not (r >= first and rec_keys[np.uint64(r)] == key):
            r, p = _voxel_insert(key, slot, table, tmask, rec_keys, rec, first, p)
        at = np.uint64(r)  # unsigned indices spare numba's negative-index fix-up
        rec[at, 0] += xs[i]
        rec[at, 1] += ys[i]
        rec[at, 2] += zs[i]
        rec[at, 3] += 1.0
        out[i] = r
    return p, added


@numba.njit(cache=True, nogil=True)
def _merge_records(rec_keys, rec, p):
    """Records -> voxels: (centroids (M, 3) float32, counts (M,) int32, keys (M,) int64
    strictly increasing, record_voxel (p,) int32).

    The records' keys become bit-field codes over their bounding box (same order as the keys)
    and are radix-sorted (stable: the records of one voxel stay in band order); records with
    equal codes are summed in that order and the centroid is ``float32(sum / count)`` in
    float64.  ``rec_keys[:p]`` is overwritten with the sorted codes.
    """
    # the key's three fields: top (bits 42-62), middle (21-41), low (0-20)
    lo_top = np.int64(_KEY_FIELD)
    lo_mid = lo_top
    lo_low = lo_top
    hi_top = np.int64(0)
    hi_mid = hi_top
    hi_low = hi_top
    for j in range(p):
        key = rec_keys[j]
        top = key >> (2 * KEY_BITS)
        mid = (key >> KEY_BITS) & _KEY_FIELD
        low = key & _KEY_FIELD
        lo_top = min(lo_top, top)
        hi_top = max(hi_top, top)
        lo_mid = min(lo_mid, mid)
        hi_mid = max(hi_mid, mid)
        lo_low = min(lo_low, low)
        hi_low = max(hi_low, low)
    b_low = _bit_length(hi_low - lo_low) if p > 0 else 0
    b_mid = _bit_length(hi_mid - lo_mid) if p > 0 else 0
    b_top = _bit_length(hi_top - lo_top) if p > 0 else 0
    codes = rec_keys[:p]
    for j in range(p):
        key = codes[j]
        codes[j] = (
            ((((key >> (2 * KEY_BITS)) & _KEY_FIELD) - lo_top) << (b_mid + b_low))
            | ((((key >> KEY_BITS) & _KEY_FIELD) - lo_mid) << b_low)
            | ((key & _KEY_FIELD) - lo_low)
        )
    order, record_voxel = _radix_order(codes, b_top + b_mid + b_low)
    m = 0
    for j in range(p):
        m += j == 0 or codes[j] != codes[j - 1]
    centroids = np.empty((m, 3), dtype=np.float32)
    counts = np.empty(m, dtype=np.int32)
    keys = np.empty(m, dtype=np.int64)
    mid_mask = (np.int64(1) << b_mid) - 1
    low_mask = (np.int64(1) << b_low) - 1
    v = -1
    sx = 0.0
    sy = 0.0
    sz = 0.0
    sc = 0.0
    for j in range(p + 1):
        if j == p or j == 0 or codes[j] != codes[j - 1]:
            if v >= 0:
                centroids[v, 0] = np.float32(sx / sc)
                centroids[v, 1] = np.float32(sy / sc)
                centroids[v, 2] = np.float32(sz / sc)
                counts[v] = np.int32(sc)
            if j == p:
                break
            v += 1
            code = codes[j]
            keys[v] = (
                (((code >> (b_mid + b_low)) + lo_top) << (2 * KEY_BITS))
                | ((((code >> b_low) & mid_mask) + lo_mid) << KEY_BITS)
                | ((code & low_mask) + lo_low)
            )
            sx = 0.0
            sy = 0.0
            sz = 0.0
            sc = 0.0
        q = np.uint64(order[j])
        sx += rec[q, 0]
        sy += rec[q, 1]
        sz += rec[q, 2]
        sc += rec[q, 3]
        record_voxel[q] = v
    return centroids, counts, keys, record_voxel[:p]


@numba.njit(cache=True, nogil=True)
def _voxel_kernel(points, inv_leaf, chunk, tbits, limit):
    """(N, 3) float32, 1/leaf, chunk length, table bits and band limit (see
    :func:`voxel_table_size`) -> (centroids (M, 3) float32, counts (M,) int32, keys (M,) int64
    sorted, inverse (N,) int32).

    1. The points go in chunks of ``chunk`` consecutive rows.  Per chunk, keys and home hash
       slots are computed first (a loop without branches), then each point is looked up in
       the current band's open-addressing table (a hit in its home slot is the fast path; else
       :func:`_voxel_insert`) and added to that record (sum x, y, z, count in float64).  A
       band is closed at the start of a chunk when it holds more than ``limit - chunk``
       records; its records stay, the next band starts with an (implicitly) empty table.  The
       table stays in L1/L2 where one table for the whole cloud would not.
    2. :func:`_merge_records` sorts and sums the records into voxels; per point, the record it
       went to is replaced by its voxel's row.

    Summation order: a voxel's sum is the sum over bands, in band order, of the sum over its
    points in that band, in point order (the tests' twin does the same).
    """
    n = points.shape[0]
    inverse, tmask, tshift, table, rec_keys, rec = _band_workspace(n, tbits)
    lo = np.float64(-_KEY_OFFSET)
    hi = np.float64(_KEY_OFFSET - 1)
    keys = np.empty(min(n, chunk), dtype=np.int64)
    slots = np.empty(min(n, chunk), dtype=np.uint64)
    xs = np.empty(min(n, chunk), dtype=np.float64)
    ys = np.empty(min(n, chunk), dtype=np.float64)
    zs = np.empty(min(n, chunk), dtype=np.float64)
    first = 0
    p = 0
    for start in range(0, n, chunk):
        if p - first > limit - chunk:
            first = p
        part = points[start:start + chunk]
        part_inverse = inverse[start:start + chunk]
        # 1a. coordinates in float64 (one array per axis, so the next loop vectorises), then
        # keys (-1: a dropped row) and home slots, in a loop without branches
        for i in range(part.shape[0]):
            xs[i] = part[i, 0]
            ys[i] = part[i, 1]
            zs[i] = part[i, 2]
        for i in range(part.shape[0]):
            fx = np.floor(xs[i] * inv_leaf)
            fy = np.floor(ys[i] * inv_leaf)
            fz = np.floor(zs[i] * inv_leaf)
            # NaN fails every comparison, inf fails the range: both dropped
            ok = (lo <= fx) & (fx <= hi) & (lo <= fy) & (fy <= hi) & (lo <= fz) & (fz <= hi)
            keys[i] = _pack_key(fx, fy, fz, ok)
            slots[i] = _voxel_slot(keys[i], tshift)
        # 1b. look up and accumulate
        p, _ = _accumulate_row(keys, slots, xs, ys, zs, part.shape[0], part_inverse, table,
                               tmask, rec_keys, rec, first, p)
    centroids, counts, voxel_keys, record_voxel = _merge_records(rec_keys, rec, p)
    for i in range(n):
        r = inverse[i]
        if r >= 0:
            inverse[i] = record_voxel[r]
    return centroids, counts, voxel_keys, inverse


def voxel_grid(points: np.ndarray, leaf_m: float) -> VoxelGrid:
    """Replace the points in each occupied cubic voxel of edge ``leaf_m`` by their centroid.

    Parameters
    ----------
    points : (N, 3) float32
        Metres.  Rows with NaN/inf, and rows whose voxel index does not fit a key (see the module
        docstring), are dropped (``inverse == -1``).
    leaf_m : float
        Voxel edge in metres, > 0.

    Returns
    -------
    VoxelGrid
        Voxels sorted by packed key; centroids as float32.
    """
    points = check_points(points)
    leaf = validate.positive("voxel_grid", "leaf_m", leaf_m, 1e6, unit=" metres")
    if points.shape[0] >= 2**31:
        raise InputError(f"points: {points.shape[0]} rows is too many for int32 indices")
    bits, limit = voxel_table_size(VOXEL_CHUNK)
    centroids, counts, keys, inverse = _voxel_kernel(points, 1.0 / leaf, VOXEL_CHUNK, bits, limit)
    return VoxelGrid(points=centroids, counts=counts, keys=keys, inverse=inverse, leaf_m=leaf)


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
    a = validate.number("statistical_outliers", "alpha", alpha, 0.0, math.inf, unit=" standard deviations")
    cap = validate.positive("statistical_outliers", "cap_leaves", cap_leaves, unit=" leaf sizes") * leaf
    stat = knn_mean_distance(points, keys, k, cap)
    if stat.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    threshold = stat.mean() + a * stat.std()
    return stat <= threshold


# --------------------------------------------------------------------------------------------
# RANSAC plane


@dataclasses.dataclass(frozen=True, eq=False)
class Plane:
    """A plane ``normal . p + offset = 0`` (metres) and which points lie on it.

    ``normal``: (3,) float64 unit vector, oriented so that the camera origin is on its positive
    side (``offset >= 0``).  ``inliers``: (M,) bool over the points it was fitted to.
    ``n_inliers``: their number.  When no plane was found: ``normal`` and ``offset`` are NaN,
    no inliers (``found`` is False).  ``iterations``: sample triples tried.
    """

    normal: np.ndarray
    offset: float
    inliers: np.ndarray
    n_inliers: int
    iterations: int = 0

    @property
    def found(self) -> bool:
        return self.n_inliers > 0

    @classmethod
    def none(cls, n_points: int, iterations: int = 0) -> "Plane":
        """The result when no plane qualifies."""
        return cls(np.full(3, np.nan), math.nan, np.zeros(n_points, dtype=bool), 0, iterations)

    def distances(self, points: np.ndarray) -> np.ndarray:
        """(N,) float64 signed distances of (N, 3) points to the plane, metres."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.normal + self.offset


#: Points per block when counting plane inliers: a branch-free inner loop the compiler can
#: vectorise, with the "cannot win any more" test between blocks.
_RANSAC_BLOCK = 256

#: Points on which RANSAC scores its hypotheses (preemptive RANSAC): with 4096 the inlier
#: fraction of a hypothesis is known to within about 0.7 % (one standard deviation at 30 %),
#: far finer than the margin between a floor and the next largest plane, and scoring costs
#: 4096 instead of M point tests per triple.  Only the winner is counted on every point.
RANSAC_SAMPLE = 4096


#: Bail-out of a hypothesis while it is scored: after each block it is dropped when its count
#: so far is more than this many standard deviations (plus one point) below what the best
#: plane's inlier fraction predicts for the points scored.  As the sample is in random order,
#: a plane at least as large as the best is dropped with probability below 0.2 %; a typical
#: hypothesis (a few % inliers against a floor's 25 %) is dropped after its first block.
RANSAC_BAIL_SIGMAS = 3.0


@functools.lru_cache(maxsize=8)
def _sample_order(size: int) -> np.ndarray:
    order = np.random.default_rng(0).permutation(size).astype(np.int64)
    order.setflags(write=False)
    return order


def ransac_sample(m: int, size: int = RANSAC_SAMPLE) -> np.ndarray:
    """(min(m, size),) int64 distinct rows on which :func:`fit_plane_ransac` scores hypotheses,
    in a fixed random order (any prefix is a random subset, which the bail-out relies on):
    evenly strided over ``0..m-1`` (``j * m // size``), all rows when ``m <= size``.  A voxel
    cloud is sorted by key, so the stride spreads the sample over space."""
    n = min(m, size)
    order = _sample_order(n)
    if m <= size:
        return order.copy()
    return order * m // size


@numba.njit(cache=True, nogil=True)
def _ransac_kernel(points, sample, triples, distance, up, cos_min, confidence, bail_sigmas):
    """Best plane over the given sample triples, scored on the sample rows.

    ``points`` (M, 3) float32; ``sample`` (S,) int64 rows on which a plane is scored;
    ``triples`` (T, 3) int64 row indices (into ``points``); ``up`` (3,) float64 unit vector or
    all zeros for no constraint; a plane counts only when ``|n . up| >= cos_min``.
    A triple whose cross product is below 1e-12 m^2 (repeated or collinear points) is skipped.
    The plane through the triple is ``n = normalize((p1 - p0) x (p2 - p0))``, ``d = -n . p0``
    (float64); a sample point is an inlier when ``|n . p + d| <= distance``.  The first triple
    with the strictly largest inlier count on the sample wins.  The sample is counted in blocks
    of ``_RANSAC_BLOCK``; after each, a triple stops being counted (and cannot win) when it can
    no longer beat the best count, or when its count is below the bail-out bound
    ``n w - RANSAC_BAIL_SIGMAS sqrt(n w (1 - w)) - 1`` for the ``n`` points counted and the
    best fraction ``w`` so far (:data:`RANSAC_BAIL_SIGMAS`).

    Adaptive stop: after triple t, stop once ``t + 1 >= log(1 - confidence) / log(1 - w**3)``
    with ``w`` = best count / S (the classic RANSAC bound; ``confidence >= 1`` never stops
    early).  Returns (triple index or -1, count on the sample, n (3,), d, triples tried).
    """
    m = sample.shape[0]
    xs = np.empty(m, dtype=np.float64)
    ys = np.empty(m, dtype=np.float64)
    zs = np.empty(m, dtype=np.float64)
    for i in range(m):
        r = sample[i]
        xs[i] = points[r, 0]
        ys[i] = points[r, 1]
        zs[i] = points[r, 2]
    use_up = up[0] != 0.0 or up[1] != 0.0 or up[2] != 0.0
    log_miss = math.log(1.0 - confidence) if confidence < 1.0 else -np.inf
    needed = np.inf
    best_t = -1
    best_count = 0
    best_n = np.zeros(3, dtype=np.float64)
    best_d = 0.0
    tried = 0
    for t in range(triples.shape[0]):
        tried = t + 1
        a = triples[t, 0]
        b = triples[t, 1]
        c = triples[t, 2]
        ax = np.float64(points[a, 0])
        ay = np.float64(points[a, 1])
        az = np.float64(points[a, 2])
        ux = np.float64(points[b, 0]) - ax
        uy = np.float64(points[b, 1]) - ay
        uz = np.float64(points[b, 2]) - az
        vx = np.float64(points[c, 0]) - ax
        vy = np.float64(points[c, 1]) - ay
        vz = np.float64(points[c, 2]) - az
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        if norm >= 1e-12 and not (
            use_up and abs(nx / norm * up[0] + ny / norm * up[1] + nz / norm * up[2]) < cos_min
        ):
            nx /= norm
            ny /= norm
            nz /= norm
            d = -(nx * ax + ny * ay + nz * az)
            count = 0
            start = 0
            while start < m:
                stop = min(m, start + _RANSAC_BLOCK)
                # slices index from 0, so the loop vectorises (no negative-index checks)
                bx = xs[start:stop]
                by = ys[start:stop]
                bz = zs[start:stop]
                block = 0
                for i in range(bx.shape[0]):
                    r = nx * bx[i] + ny * by[i] + nz * bz[i] + d
                    block += abs(r) <= distance
                count += block
                start = stop
                if count + (m - start) <= best_count:
                    count = -1
                    break  # cannot beat the best any more
                if best_count > 0:
                    w = best_count / m
                    expect = start * w
                    if count < expect - bail_sigmas * math.sqrt(expect * (1.0 - w)) - 1.0:
                        count = -1
                        break  # far below the best fraction: bail out
            if count > best_count:
                best_count = count
                best_t = t
                best_n[0] = nx
                best_n[1] = ny
                best_n[2] = nz
                best_d = d
                w3 = (best_count / m) ** 3
                if w3 >= 1.0:
                    needed = 0.0
                elif confidence < 1.0:
                    needed = log_miss / math.log(1.0 - w3)
        if tried >= needed:
            break
    return best_t, best_count, best_n, best_d, tried


@numba.njit(cache=True, nogil=True)
def _plane_inliers(points, normal, offset, distance):
    """(M,) bool ``|n . p + d| <= distance`` (float64, ``n0 x + n1 y + n2 z + d`` in that
    order) and the number of inliers."""
    m = points.shape[0]
    nx = normal[0]
    ny = normal[1]
    nz = normal[2]
    inliers = np.empty(m, dtype=np.bool_)
    count = 0
    for i in range(m):
        r = nx * np.float64(points[i, 0]) + ny * np.float64(points[i, 1]) + nz * np.float64(
            points[i, 2]) + offset
        ok = abs(r) <= distance
        inliers[i] = ok
        count += ok
    return inliers, count


@numba.njit(cache=True, nogil=True)
def _inlier_scatter(points, inliers, count):
    """Centroid (3,) and scatter matrix (3, 3) of the rows where ``inliers`` (``count`` of
    them, > 0): sums in row order, the centroid as sum / count, the scatter as the sums of the
    products of the centred coordinates (float64)."""
    sx = 0.0
    sy = 0.0
    sz = 0.0
    for i in range(points.shape[0]):
        if inliers[i]:
            sx += np.float64(points[i, 0])
            sy += np.float64(points[i, 1])
            sz += np.float64(points[i, 2])
    cx = sx / count
    cy = sy / count
    cz = sz / count
    xx = 0.0
    xy = 0.0
    xz = 0.0
    yy = 0.0
    yz = 0.0
    zz = 0.0
    for i in range(points.shape[0]):
        if inliers[i]:
            dx = np.float64(points[i, 0]) - cx
            dy = np.float64(points[i, 1]) - cy
            dz = np.float64(points[i, 2]) - cz
            xx += dx * dx
            xy += dx * dy
            xz += dx * dz
            yy += dy * dy
            yz += dy * dz
            zz += dz * dz
    centroid = np.empty(3, dtype=np.float64)
    centroid[0] = cx
    centroid[1] = cy
    centroid[2] = cz
    scatter = np.empty((3, 3), dtype=np.float64)
    scatter[0, 0] = xx
    scatter[0, 1] = xy
    scatter[0, 2] = xz
    scatter[1, 0] = xy
    scatter[1, 1] = yy
    scatter[1, 2] = yz
    scatter[2, 0] = xz
    scatter[2, 1] = yz
    scatter[2, 2] = zz
    return centroid, scatter


def _check_up(up: object, max_tilt_deg: object) -> tuple[np.ndarray, float]:
    if up is None and max_tilt_deg is None:
        return np.zeros(3), 0.0
    if up is None or max_tilt_deg is None:
        raise InputError(
            f"up={up!r}, max_tilt_deg={max_tilt_deg!r}: give both (the camera-frame up vector "
            "and the largest angle between it and the plane normal) or neither"
        )
    vec = np.asarray(up, dtype=np.float64)
    norm = float(np.linalg.norm(vec)) if vec.shape == (3,) else 0.0
    if vec.shape != (3,) or not math.isfinite(norm) or norm == 0.0:
        raise InputError(
            f"up={up!r}: must be a non-zero finite 3-vector in the camera frame, e.g. (0, -1, 0) "
            "for a level camera (y points down)"
        )
    tilt = validate.number("fit_plane_ransac", "max_tilt_deg", max_tilt_deg, 0.0, 90.0, unit=" degrees")
    return vec / norm, math.cos(math.radians(tilt))


def _orient(normal: np.ndarray, offset: float) -> tuple[np.ndarray, float]:
    """Flip so that the camera origin is on the positive side (offset >= 0)."""
    if offset < 0.0:
        return -normal, -offset
    return normal, offset


@functools.lru_cache(maxsize=8)
def _triple_uniforms(iterations: int, seed: int) -> np.ndarray:
    """(iterations, 3) float64 uniforms in [0, 1) from ``np.random.default_rng(seed)``, read-only
    and cached: a robot draws with the same seed every frame, only the cloud size changes."""
    u = np.random.default_rng(seed).random((iterations, 3))
    u.setflags(write=False)
    return u


@numba.njit(cache=True, nogil=True)
def _triples_kernel(u, m):
    """(T, 3) uniforms, m >= 3 -> (T, 3) int64 distinct rows: ``a = floor(u0 m)``, ``b`` and
    ``c`` drawn from the m - 1 and m - 2 rows left and shifted past the ones taken."""
    t = u.shape[0]
    out = np.empty((t, 3), dtype=np.int64)
    for i in range(t):
        a = min(np.int64(u[i, 0] * m), m - 1)
        b = min(np.int64(u[i, 1] * (m - 1)), m - 2)
        c = min(np.int64(u[i, 2] * (m - 2)), m - 3)
        b += b >= a
        lo = min(a, b)
        hi = max(a, b)
        c += c >= lo
        c += c >= hi
        out[i, 0] = a
        out[i, 1] = b
        out[i, 2] = c
    return out


def ransac_triples(m: int, iterations: int, seed: int) -> np.ndarray:
    """(iterations, 3) int64 triples of distinct row indices in 0..m-1 (m >= 3), uniform over
    ordered triples of distinct rows, from ``np.random.default_rng(seed).random((iterations,
    3))`` scaled to the cloud size (the uniforms are cached, so a frame does not pay for the
    generator; the first n triples of a longer draw are the triples of a draw of n)."""
    return _triples_kernel(_triple_uniforms(int(iterations), int(seed)), int(m))


def fit_plane_ransac(
    points: np.ndarray,
    distance_m: float,
    iterations: int,
    seed: int,
    *,
    up: object = None,
    max_tilt_deg: float | None = None,
    min_inliers: int = 3,
    confidence: float = 0.999,
    bail_sigmas: float = RANSAC_BAIL_SIGMAS,
) -> Plane:
    """Largest plane by RANSAC, refined by least squares.

    Up to ``iterations`` triples of distinct points, drawn by :func:`ransac_triples` (NumPy's
    ``default_rng(seed)``), are scored in order by :func:`_ransac_kernel` on the fixed subsample
    :func:`ransac_sample` (``RANSAC_SAMPLE`` evenly strided rows in a fixed random order:
    preemptive RANSAC; inliers within ``distance_m``; a triple dropped early when its partial
    count falls ``bail_sigmas`` below the best fraction; with ``up`` and ``max_tilt_deg``, only
    planes whose normal is within ``max_tilt_deg`` of ``up`` count; adaptive stop at
    ``confidence``, with the inlier fraction measured on the subsample).  Only the winner's
    inliers are counted on all points; it needs ``min_inliers`` of them.  It is then refitted to
    its inliers (normal = eigenvector of the smallest eigenvalue of their covariance, through
    their centroid) and its inliers are counted again; the refit is kept when it still meets the
    tilt limit and has at least as many inliers.

    Parameters
    ----------
    points : (M, 3) float32
        Metres, finite.
    distance_m : float
        Inlier distance in metres, > 0.
    iterations : int
        Sample triples, >= 1.
    seed : int
        Seed of the triples; the same seed and points give the same plane.
    up : (3,) array-like or None
        Camera-frame direction the plane normal must be close to (e.g. (0, -1, 0) for the floor
        seen by a level camera).
    max_tilt_deg : float or None
        Largest angle between normal and ``up``, 0..90 degrees.
    min_inliers : int
        A plane needs at least this many inliers, >= 1.
    confidence : float
        Stop drawing triples once a plane at least as large as the best so far would have been
        hit with this probability (adaptive RANSAC); 1.0 tries all ``iterations``.
    bail_sigmas : float
        Bail-out bound of the scoring in standard deviations, >= 0 (:data:`RANSAC_BAIL_SIGMAS`);
        ``math.inf`` counts every triple on the whole sample.

    Returns
    -------
    Plane
        With ``inliers`` over ``points``; :meth:`Plane.none` when fewer than 3 points or no
        plane with ``min_inliers`` qualifies.
    """
    points = check_points(points)
    if not np.all(np.isfinite(points)):
        raise InputError("points contain NaN or inf; filter them first (voxel_grid drops them)")
    dist = validate.positive("fit_plane_ransac", "distance_m", distance_m, unit=" metres")
    validate.whole("fit_plane_ransac", "iterations", iterations, 1, 2**63 - 1)
    validate.whole("fit_plane_ransac", "min_inliers", min_inliers, 1, 2**63 - 1)
    validate.whole("fit_plane_ransac", "seed", seed, 0, 2**63 - 1)
    up_vec, cos_min = _check_up(up, max_tilt_deg)
    try:
        conf = float(confidence)
    except (TypeError, ValueError):
        conf = math.nan
    if not 0.0 < conf <= 1.0:
        raise InputError(f"confidence={confidence!r}: must be a probability in (0, 1], e.g. "
                         "0.999 (1 tries every iteration)")
    try:
        bail = float(bail_sigmas)
    except (TypeError, ValueError):
        bail = math.nan
    if not bail >= 0.0:
        raise InputError(f"bail_sigmas={bail_sigmas!r}: must be a number of standard deviations "
                         ">= 0 (math.inf: no bail-out)")
    m = points.shape[0]
    if m < 3:
        return Plane.none(m)
    triples = ransac_triples(m, iterations, seed)
    sample = ransac_sample(m)
    best_t, _, normal, offset, tried = _ransac_kernel(points, sample, triples, dist, up_vec,
                                                      cos_min, conf, bail)
    if best_t < 0:
        return Plane.none(m, tried)
    inliers, count = _plane_inliers(points, normal, float(offset), dist)
    if count < min_inliers or count < 3:
        return Plane.none(m, tried)
    normal, offset = _orient(normal, float(offset))
    # least-squares refit on the inliers
    centroid, scatter = _inlier_scatter(points, inliers, count)
    _, vectors = np.linalg.eigh(scatter)
    refit = vectors[:, 0]
    refit = refit / np.linalg.norm(refit)
    if refit @ normal < 0:
        refit = -refit
    refit_offset = -float(refit @ centroid)
    refit_inliers, refit_count = _plane_inliers(points, refit, refit_offset, dist)
    tilt_ok = not up_vec.any() or abs(float(refit @ up_vec)) >= cos_min
    if tilt_ok and refit_count >= count:
        normal, offset = _orient(refit, refit_offset)
        inliers = refit_inliers
        count = refit_count
    return Plane(normal=normal, offset=float(offset), inliers=inliers, n_inliers=int(count),
                 iterations=int(tried))


def remove_plane(
    points: np.ndarray,
    distance_m: float,
    iterations: int,
    seed: int,
    **options: object,
) -> tuple[np.ndarray, Plane]:
    """Fit the largest plane (:func:`fit_plane_ransac`, same arguments) and drop its inliers.
    Returns ``(points without the plane (K, 3) float32, plane)``."""
    plane = fit_plane_ransac(
        points, distance_m, iterations, seed, **options  # type: ignore[arg-type]
    )
    return points[~plane.inliers], plane


# --------------------------------------------------------------------------------------------
# temporal fusion


@numba.njit(cache=True, nogil=True)
def _fuse_kernel(stack, min_valid):
    """(N, H, W) uint16 -> (H, W) uint16 per-pixel median of the non-zero values.

    Row by row and without sorting: the rank of reading i at a pixel is the number of valid
    readings j smaller than it, or equal with j < i (so ranks 0..c-1 follow the sorted order).
    The median is the reading of rank c // 2 (odd c) or the integer mean of ranks c // 2 - 1
    and c // 2 (even c).  The inner loops run along the row, branch-free, and vectorise; the
    work is O(N^2) per pixel, which for the ~10 frames of a fusion beats sorting.
    """
    n, height, width = stack.shape
    out = np.zeros((height, width), dtype=np.uint16)
    valid = np.zeros(width, dtype=np.int32)
    rank = np.zeros(width, dtype=np.int32)
    low = np.zeros(width, dtype=np.int32)
    high = np.zeros(width, dtype=np.int32)
    for v in range(height):
        valid[:] = 0
        low[:] = 0
        high[:] = 0
        for f in range(n):
            row = stack[f, v]
            for u in range(width):
                valid[u] += row[u] > 0
        for i in range(n):
            a = stack[i, v]
            rank[:] = 0
            for j in range(n):
                b = stack[j, v]
                if j < i:
                    for u in range(width):
                        rank[u] += (b[u] > 0) & (b[u] <= a[u])
                elif j > i:
                    for u in range(width):
                        rank[u] += (b[u] > 0) & (b[u] < a[u])
            for u in range(width):
                c = valid[u]
                h = c // 2
                value = np.int32(a[u])
                if value > 0 and rank[u] == h:
                    high[u] = value
                if value > 0 and rank[u] == h - 1:
                    low[u] = value
        row_out = out[v]
        for u in range(width):
            c = valid[u]
            if c >= min_valid and c > 0:
                if c % 2 == 1:
                    row_out[u] = high[u]
                else:
                    row_out[u] = (low[u] + high[u]) // 2
    return out


def fuse_depth(stack: np.ndarray, min_valid: int) -> np.ndarray:
    """Temporal fusion of depth frames taken from a standing camera.

    Parameters
    ----------
    stack : (N, H, W) uint16
        Depth in millimetres, 0 = no reading.
    min_valid : int
        A pixel needs at least this many non-zero readings, 1..N.

    Returns
    -------
    (H, W) uint16
        Per pixel, the median of its non-zero readings (even count: ``(a + b) // 2`` of the two
        middle ones); 0 where fewer than ``min_valid`` readings.
    """
    if not isinstance(stack, np.ndarray) or stack.dtype != np.uint16 or stack.ndim != 3:
        described = (f"{stack.dtype} array of shape {stack.shape}"
                     if isinstance(stack, np.ndarray) else type(stack).__name__)
        raise InputError(
            f"stack must be an (N, H, W) uint16 array of depth frames in millimetres, got a "
            f"{described}; build it with np.stack([frame.depth for frame in frames])"
        )
    n = stack.shape[0]
    if n == 0:
        raise InputError("stack holds no frames; fuse at least one depth frame")
    validate.whole("fuse_depth", "min_valid", min_valid, 1, n,
                   unit=" (the number of frames in the stack)")
    return _fuse_kernel(np.ascontiguousarray(stack), int(min_valid))
