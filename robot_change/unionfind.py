"""Union-find over array indices (numba): the connected components of voxels
(robot_change.change.regions) and of cell grids (robot_change.change.registration.surfaces).
Their users' NumPy twins in the tests check them."""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["find_root", "forest_labels", "union_sets"]


@numba.njit(cache=True, nogil=True)
def find_root(parent, i):
    """The root of ``i``'s set in the union-find forest ``parent`` (M,) int64, compressing
    the path to it."""
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@numba.njit(cache=True, nogil=True)
def union_sets(parent, i, j):
    """Join the sets of ``i`` and ``j`` (the smaller root stays the root)."""
    a = find_root(parent, i)
    b = find_root(parent, j)
    if a != b:
        if a < b:
            parent[b] = a
        else:
            parent[a] = b


@numba.njit(cache=True, nogil=True)
def forest_labels(parent):
    """(M,) int64 labels 0..C-1 of a union-find forest, numbered in order of each set's first
    member."""
    m = parent.shape[0]
    labels = np.empty(m, dtype=np.int64)
    remap = np.full(m, -1, dtype=np.int64)
    count = 0
    for i in range(m):
        r = find_root(parent, i)
        if remap[r] < 0:
            remap[r] = count
            count += 1
        labels[i] = remap[r]
    return labels
