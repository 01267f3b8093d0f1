"""Surface segments of a cell grid (a pyramid level's vertex and normal maps): cells join
along one surface and part where it folds inwards, as at an object's foot on a table
(robot_change.change.objects, docs/algorithm.md change detection step 5; the table stations'
objects, :mod:`.table_station`).  The kernel has a NumPy twin in tests/test_objects.py.
"""

from __future__ import annotations

import math
import weakref

import numba
import numpy as np

from robot_change.unionfind import forest_labels, union_sets

from .pyramid import Level

#: :func:`level_segments` per level object: (fold_deg, segments).
_SEGMENTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

#: One cell step spans z / fx metres (fx of the level): neighbours join up to SEGMENT_STEP
#: times that apart along the surface (~76 degrees, as the normals allow) and SEGMENT_OFF
#: times that off it; a fold is judged across SEGMENT_SPAN cells (so a pixel of a fold
#: finds a cell off it within as many).
SEGMENT_STEP = 4.0
SEGMENT_OFF = 1.0
SEGMENT_SPAN = 2


@numba.njit(cache=True, nogil=True)
def pair_geometry(vertex, normal, i, j, a, b):
    """Cells (i, j) and (a, b) with d = p_ij - p_ab: the normals' cosine, the bend
    (n_ij - n_ab) . d (> 0: convex), |d|^2, and d along each cell's normal."""
    cos = 0.0
    bend = 0.0
    dist2 = 0.0
    off_ij = 0.0
    off_ab = 0.0
    for k in range(3):
        d = vertex[i, j, k] - vertex[a, b, k]
        cos += normal[i, j, k] * normal[a, b, k]
        bend += (normal[i, j, k] - normal[a, b, k]) * d
        dist2 += d * d
        off_ij += normal[i, j, k] * d
        off_ab += normal[a, b, k] * d
    return cos, bend, dist2, off_ij, off_ab


@numba.njit(cache=True, nogil=True)
def cell_segments(vertex, normal, cos_fold, max_step, max_off, span):
    """Surface segments of a cell grid: ``vertex`` (h, w, 3) float32 m (z = 0: empty) and
    ``normal`` (h, w, 3) float32 unit normals facing the camera (0: none).  A cell is on an
    inward fold when the cells ``span`` away on either side, along a row, a column or a
    diagonal, are concave ((n_a - n_b) . (p_a - p_b) < 0) with a normals' cosine below
    ``cos_fold`` (and no depth step between them); it joins nothing.  Right and lower
    neighbours join when both have a normal and are on no fold, they are at most
    ``max_step * z`` apart and each lies within ``max_off * z`` of the other's tangent plane,
    and their normals' cosine is at least ``cos_fold`` or the pair is convex.  Returns (h, w)
    int64 labels 0..C-1 in row-major order of each segment's first cell.  Then a cell with a
    point but no normal (an object's rim, a thin face), on no fold, takes the label of its
    first neighbour (left, up, right, down) that has one, is at most ``max_step * z`` away and
    whose tangent plane it lies within ``max_off * z`` of; -1 for the cells left."""
    h, w, _ = vertex.shape
    parent = np.arange(h * w)
    has = np.zeros((h, w), dtype=np.bool_)
    for i in range(h):
        for j in range(w):
            has[i, j] = normal[i, j, 0] != 0.0 or normal[i, j, 1] != 0.0 or \
                normal[i, j, 2] != 0.0
    # a cell on an inward fold joins nothing: along a fold the normals turn from one surface
    # to the other a few degrees a cell, and neighbour by neighbour would join them
    fold = np.zeros((h, w), dtype=np.bool_)
    for i in range(h):
        for j in range(w):
            if not has[i, j]:
                continue
            for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
                a0 = i - span * di
                b0 = j - span * dj
                a1 = i + span * di
                b1 = j + span * dj
                if a0 < 0 or a1 >= h or b0 < 0 or b0 >= w or b1 < 0 or b1 >= w or \
                        not has[a0, b0] or not has[a1, b1]:
                    continue
                cos, bend, dist2, _, _ = pair_geometry(vertex, normal, a0, b0, a1, b1)
                lim = 2 * span * max_step * vertex[i, j, 2]
                if cos < cos_fold and bend < 0.0 and dist2 <= lim * lim:
                    fold[i, j] = True
                    break
    for i in range(h):
        for j in range(w):
            if fold[i, j]:
                has[i, j] = False
    for i in range(h):
        for j in range(w):
            if not has[i, j]:
                continue
            lim = max_step * vertex[i, j, 2]
            for di, dj in ((0, 1), (1, 0)):
                a = i + di
                b = j + dj
                if a >= h or b >= w or not has[a, b]:
                    continue
                cos, bend, dist2, off_a, off_b = pair_geometry(vertex, normal, i, j, a, b)
                # one surface: no step along the way nor off either cell's tangent plane
                # (a box's top edge and the table just behind it are parallel, a step apart)
                if dist2 > lim * lim or abs(off_a) > max_off * vertex[i, j, 2] or \
                        abs(off_b) > max_off * vertex[i, j, 2]:
                    continue
                if cos >= cos_fold or bend > 0.0:
                    union_sets(parent, i * w + j, a * w + b)
    flat = forest_labels(parent)
    out = np.full((h, w), -1, dtype=np.int64)
    count = 0
    remap = np.full(h * w, -1, dtype=np.int64)
    for i in range(h):
        for j in range(w):
            if has[i, j]:
                lab = flat[i * w + j]
                if remap[lab] < 0:
                    remap[lab] = count
                    count += 1
                out[i, j] = remap[lab]
    # a cell with a point but no normal (an object's rim, a thin face) joins the segment of a
    # neighbour whose tangent plane it lies on (the first of left, up, right, down)
    rim = out.copy()
    for i in range(h):
        for j in range(w):
            if out[i, j] >= 0 or fold[i, j] or vertex[i, j, 2] <= 0.0:
                continue
            for di, dj in ((0, -1), (-1, 0), (0, 1), (1, 0)):
                a = i + di
                b = j + dj
                if a < 0 or b < 0 or a >= h or b >= w or out[a, b] < 0:
                    continue
                _, _, dist2, _, off = pair_geometry(vertex, normal, i, j, a, b)
                lim = max_step * vertex[a, b, 2]
                if dist2 <= lim * lim and abs(off) <= max_off * vertex[a, b, 2]:
                    rim[i, j] = out[a, b]
                    break
    return rim


def level_segments(level: Level, fold_deg: float) -> np.ndarray:
    """(h, w) int64 :func:`cell_segments` of a pyramid ``level``, folding at ``fold_deg``
    degrees (-1: a cell in none); read-only, kept per level object (a current's finest level
    is cut by the registration's table checks and again by the object completion)."""
    kept = _SEGMENTS.get(level)
    if kept is not None and kept[0] == fold_deg:
        return kept[1]
    out = cell_segments(level.vertex, level.normal, math.cos(math.radians(fold_deg)),
                        SEGMENT_STEP / level.fx, SEGMENT_OFF / level.fx, SEGMENT_SPAN)
    out.setflags(write=False)
    _SEGMENTS[level] = (fold_deg, out)
    return out
