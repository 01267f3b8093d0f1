"""Temporal depth fusion: the per-pixel median of the non-zero readings of N frames, where a
pixel needs readings in at least ``min_valid`` of them.

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.  The kernels are
numba-compiled (``cache=True, nogil=True``), single-threaded and without fastmath, so the NumPy
twins in ``tests/test_filters.py`` give identical results.
"""

from __future__ import annotations

import numba
import numpy as np

from robot_change import validate
from robot_change.errors import InputError

__all__ = [
    "fuse_depth",
]


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
