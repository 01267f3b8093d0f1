"""Voxel keys and the voxel grid (ALGORITHM.md section 1): points -> one centroid per occupied
cubic voxel, found through a hash table over packed int64 keys.

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

import numba
import numpy as np

from robot_change import validate
from robot_change.cloud.geometry import check_points
from robot_change.errors import InputError

__all__ = [
    "KEY_BITS",
    "KEY_MAX_INDEX",
    "KEY_MIN_INDEX",
    "VOXEL_CHUNK",
    "VOXEL_TABLE_MIN_SLOTS",
    "VoxelGrid",
    "pack_keys",
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
        for j in range(m):  # element by element: an array-to-slice copy costs ~2 s of compile
            codes[j] = tmp_codes[j]
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
    p = np.int64(0)  # typed: no literal-0 specialisation of the kernels it goes to
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
