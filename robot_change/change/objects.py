"""Changed points completed to the objects they lie on.

An object moved by less than its own size stands partly where it stood: there the other epoch
saw a surface at the same depth, the free-space check has nothing to say, and only the part
that left its old place is found.  The foot of an object on a table lies within the free-space
margin of the table behind it and is not found either.  What a robot needs is the object.

So the epoch's depth image is cut into surface segments, on cells of ``object_cell_px`` x
``object_cell_px`` pixels (vertex and normal maps made as the registration's finest level):
neighbouring cells (4-neighbourhood) join when both have a normal, they lie on one surface (no
depth step), and their normals agree within ``object_fold_deg`` or the surface between them
bends outwards (convex, as round an object's top edge); they part where it folds inwards (an
object's foot on a table, an object against a wall), and a cell on such a fold joins nothing. A
cell without a normal (a rim, a thin face) joins a neighbour's segment whose tangent plane it
lies on. Then each pixel on a fold or a depth edge (its cell in no segment) joins the segment
around it (within 2 cells, each segment stood for by its nearest cell) whose tangent plane its
own point lies nearest to: the pixels of an object's foot join the object, those of the table
beside it the table.

A segment is claimed when the pixels of changed points make up at least ``object_min_share``
of the pixels of its points: an object found in part is completed, while a sliver on a wall or
a table, a small part of a large segment, stays as it is. The larger a segment is in view, the
more of it must be found: at least the share of the image it covers (a table top, a floor or a
wall filling half the view, half of it), so that the strips of a registration slid along a
wall do not claim the place itself. Every changed point counts, however small its group (a
moved object's found strips along its edges are often a few points each), and only points the
other camera observed are claimed. A point is claimed when more of its pixels lie in claimed
segments than in other segments (pixels in no segment do not vote). Both kernels have NumPy
twins in tests/test_objects.py.

Then each epoch's segments are judged against the other epoch's changed points as completed
(:func:`claim_counterparts`): an object moved by less than its own size may have left only
one epoch with evidence (its new place stands where the old one stood, within the free-space
margin), and a surface standing where the other epoch's changed surface stood is that
object's other place.  A pixel lands on the other image (through the registration) on the
same surface when the reading there lies within the free-space margin of it and the two
cells' normals agree within ``object_fold_deg``; a segment is claimed when more than
``object_counterpart_share`` of its pixels that land on the same surface land on changed
pixels of the other epoch (its changed pixels less a band of ``free_space_pose_radius_px``
along their outline: a changed object's foot is claimed with it, and is table), and those make
up the share a segment needs above.  An object moved towards the camera hides its old place
behind its new one (moved away: the new behind the old), and nothing of the hidden place is
seen through: a segment is also claimed when nearly all its landing pixels
(``object_hidden_share``) lie on or hidden behind the other's changed pixels, and it has the
shape of the changed segment that hides it (``object_hidden_shape``: an object added before
another hides that one too, and table pieces at an object's feet hide behind it).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from robot_change.arrays import readonly_view
from robot_change.change.epoch import Epoch, kept, pair_sigma_table
from robot_change.change.free_space import free_space_views, land_pixel
from robot_change.change.params import ChangeParams
from robot_change.change.registration.pyramid import surface_level
from robot_change.change.registration.surfaces import (
    SEGMENT_OFF,
    SEGMENT_SPAN,
    SEGMENT_STEP,
    level_segments,
)
from robot_change.cloud.chain import CloudParams
from robot_change.noise.kernels import margin_at

#: Counterparts are counted on every second row and column: shares of a segment, a quarter of
#: the work (a segment of fewer than ~4 pixels in a 2 x 2 block is never claimed so).
_COUNTERPART_STEP = 2

__all__ = [
    "claim_counterparts",
    "complete_objects",
    "surface_segments",
]


@numba.njit(cache=True, nogil=True)
def _near_segments(cells, normal, i, j, radius, out):
    """The cells around (i, j) that stand for the segments there: rings 1..``radius`` of
    cells, each ring in row-major order, the first cell with a normal of each segment, at
    most ``out.shape[0]`` segments; their (row, column) into ``out`` (S, 2) int32.  Returns
    how many."""
    h, w = cells.shape
    n = 0
    for d in range(1, radius + 1):
        for a in range(i - d, i + d + 1):
            if a < 0 or a >= h:
                continue
            for b in range(j - d, j + d + 1):
                if b < 0 or b >= w or max(abs(a - i), abs(b - j)) != d:
                    continue
                lab = cells[a, b]
                if lab < 0 or (normal[a, b, 0] == 0.0 and normal[a, b, 1] == 0.0
                               and normal[a, b, 2] == 0.0):
                    continue
                seen = False
                for k in range(n):
                    if cells[out[k, 0], out[k, 1]] == lab:
                        seen = True
                        break
                if not seen and n < out.shape[0]:
                    out[n, 0] = a
                    out[n, 1] = b
                    n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _pixels_kernel(depth, pixel_voxel, cells, vertex, normal, f, fx, fy, cx, cy, max_step,
                   max_off, radius):
    """Each pixel's segment: ``depth`` (H, W) uint16 mm, ``pixel_voxel`` (H, W) int32 (only
    pixels with a point, >= 0, are placed), ``cells`` (h, w) int64 segment of each cell of
    ``f`` x ``f`` pixels (-1: none), ``vertex`` / ``normal`` (h, w, 3) float32 the cells'
    points (m) and unit normals (0: none).  A pixel whose point (p, depth z) lies within
    ``max_step * z`` of its cell's point and within ``max_off * z`` of its tangent plane, or
    whose cell has a segment but no normal, takes its cell's segment.  Any other pixel (on a
    fold, on a depth edge, or behind the surface its cell was made of) takes, of the segments
    within ``radius`` cells (each stood for by its nearest cell with a normal,
    :func:`_near_segments`, at most 4), the one whose cell lies within ``max_step * z`` of p
    and whose tangent plane p is nearest to, if within ``max_off * z``; else its cell's when
    its cell's point lies within ``max_step * z`` of p (-1 for none: a pixel across a depth
    edge from its cell, a wall's pixel in the cell of an object's rim, is on neither).
    Returns (H, W) int64."""
    height, width = depth.shape
    h, w = cells.shape
    out = np.full((height, width), -1, dtype=np.int64)
    near = np.zeros((4, 2), dtype=np.int32)
    plane = np.zeros((4, 6))  # a near segment's cell: normal, point
    label = np.zeros(4, dtype=np.int64)
    ray_x = np.empty(width)  # x / z of each column's ray
    for c in range(width):
        ray_x[c] = (c - cx) / fx
    for i in range(min(h, height // f)):
        for j in range(min(w, width // f)):
            own = cells[i, j]
            nx = normal[i, j, 0]
            ny = normal[i, j, 1]
            nz = normal[i, j, 2]
            flat = nx == 0.0 and ny == 0.0 and nz == 0.0
            n_near = -1  # not gathered yet
            for r in range(i * f, i * f + f):
                ray_y = (r - cy) / fy
                for c in range(j * f, j * f + f):
                    if pixel_voxel[r, c] < 0 or depth[r, c] == 0:
                        continue
                    z = depth[r, c] * 0.001
                    px = ray_x[c] * z
                    py = ray_y * z
                    lim = max_step * z
                    best = -1  # a pixel across a depth edge from its cell is not its surface
                    if own >= 0:
                        dx = px - vertex[i, j, 0]
                        dy = py - vertex[i, j, 1]
                        dz = z - vertex[i, j, 2]
                        if dx * dx + dy * dy + dz * dz <= lim * lim:
                            if flat or abs(nx * dx + ny * dy + nz * dz) <= max_off * z:
                                out[r, c] = own
                                continue
                            best = own
                    if n_near < 0:
                        n_near = _near_segments(cells, normal, i, j, radius, near)
                        for k in range(n_near):
                            a = near[k, 0]
                            b = near[k, 1]
                            for m in range(3):
                                plane[k, m] = normal[a, b, m]
                                plane[k, 3 + m] = vertex[a, b, m]
                            label[k] = cells[a, b]
                    best_off = max_off * z
                    for k in range(n_near):
                        dx = px - plane[k, 3]
                        dy = py - plane[k, 4]
                        dz = z - plane[k, 5]
                        if dx * dx + dy * dy + dz * dz > lim * lim:
                            continue
                        off = abs(plane[k, 0] * dx + plane[k, 1] * dy + plane[k, 2] * dz)
                        if off <= best_off:
                            best_off = off
                            best = label[k]
                    out[r, c] = best
    return out


def surface_segments(epoch: Epoch, params: ChangeParams) -> np.ndarray:
    """(H, W) int64 surface segment of each pixel of ``epoch``'s depth image that has a point
    (-1: none), cut on cells of ``params.object_cell_px`` pixels, then pixel by pixel where a
    cell is on a fold or an edge (module docstring)."""
    f = params.object_cell_px
    level = surface_level(epoch.depth, epoch.intrinsics, f,
                          epoch.registration_params(params.registration), epoch.derived)
    intr = epoch.intrinsics
    cells = level_segments(level, params.object_fold_deg)
    max_step, max_off = SEGMENT_STEP / level.fx, SEGMENT_OFF / level.fx
    # read-only whichever epoch it is (a reference's are, a current's not): one compile
    return _pixels_kernel(readonly_view(epoch.depth), readonly_view(epoch.pixel_voxel), cells,
                          level.vertex, level.normal, f, intr.fx, intr.fy, intr.cx, intr.cy,
                          max_step, max_off, SEGMENT_SPAN)


def _segment_pixels(epoch: Epoch, params: ChangeParams
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of ``epoch`` in a segment and with a point: their segments (P,) int32 and
    points (P,) int32, each segment's count of them (S,), each point's (M,), and the
    segments as an image (H, W) int32 (-1: none, or no point).  A function of the image and
    the cloud alone, so it is kept in ``epoch.derived``: a station's reference pays for it
    once."""
    reg = epoch.registration_params(params.registration)
    key = ("segment_pixels", params.object_cell_px, params.object_fold_deg, reg.band_m,
           reg.band_slope, reg.near_m, reg.max_depth_m)

    def make() -> tuple:
        image = surface_segments(epoch, params).astype(np.int32)
        image[epoch.pixel_voxel < 0] = -1
        on = image.ravel() >= 0
        segment, point = image.ravel()[on], epoch.pixel_voxel.ravel()[on].astype(np.int32)
        size = np.bincount(segment, minlength=int(segment.max()) + 1 if segment.size else 0)
        return segment, point, size, np.bincount(point, minlength=epoch.n_points), image

    return kept(epoch.derived, key, make)


def _claim(epoch: Epoch, found: np.ndarray, size: np.ndarray, params: ChangeParams
           ) -> np.ndarray:
    """(S,) bool: the segments whose ``found`` (S,) pixels make up at least
    ``params.object_min_share`` of their ``size`` (S,) pixels, and at least the share of the
    image each covers: a table top that fills half the image is claimed when half of it is."""
    return (found > 0) & (found >= np.maximum(params.object_min_share,
                                              size / epoch.depth.size) * size)


def _joined(claimed: np.ndarray, segment: np.ndarray, point: np.ndarray,
            per_point: np.ndarray, n_points: int) -> np.ndarray:
    """(M,) bool: the points with more of their pixels in ``claimed`` (S,) segments than in
    other segments (pixels in no segment do not vote)."""
    inside = np.bincount(point[claimed[segment]], minlength=n_points)
    return 2 * inside > per_point


def _cell_normals(epoch: Epoch, params: ChangeParams) -> np.ndarray:
    """(H / f, W / f, 3) unit normals of ``epoch``'s cells of ``params.object_cell_px`` pixels
    (0: none), as the segments are cut on them."""
    return surface_level(epoch.depth, epoch.intrinsics, params.object_cell_px,
                         epoch.registration_params(params.registration), epoch.derived).normal


def complete_objects(epoch: Epoch, changed: np.ndarray, observed: np.ndarray,
                     params: ChangeParams) -> np.ndarray:
    """(M,) bool: ``changed`` (M,) bool points of ``epoch`` with the rest of the surface
    segments their pixels make up at least ``params.object_min_share`` of, and at least the
    share of the image each covers (module docstring); only ``observed`` (M,) bool points
    are added.  Unchanged when ``params.object_completion`` is off or nothing changed."""
    if not params.object_completion or not changed.any():
        return changed
    segment, point, size, per_point, _ = _segment_pixels(epoch, params)
    found = np.bincount(segment, weights=changed[point], minlength=len(size))
    claimed = _claim(epoch, found, size, params)
    return changed | (observed & _joined(claimed, segment, point, per_point, epoch.n_points))


@numba.njit(cache=True, nogil=True, inline="always")
def _inside_changed(other_pixel_voxel, other_changed, v, u, radius):
    """Whether every pixel within ``radius`` of (``v``, ``u``) (a square window, clipped to
    the image) belongs to a changed point of the other epoch."""
    h, w = other_pixel_voxel.shape
    for i in range(max(v - radius, 0), min(v + radius + 1, h)):
        for j in range(max(u - radius, 0), min(u + radius + 1, w)):
            k = other_pixel_voxel[i, j]
            if k < 0 or not other_changed[k]:
                return False
    return True


@numba.njit(cache=True, nogil=True)
def _counterparts_kernel(segments, n_segments, own_depth, rot, trans, fx, fy, cx, cy, window,
                         min_m, max_m, other_depth, other_pixel_voxel, other_changed, radius,
                         own_normal, other_normal, f, noise, sigmas, pose_m, cos_fold, step,
                         hidden_gap_m, other_segments, n_other):
    """Per segment: how many of its pixels (of every ``step``-th row and column) land on the
    same surface of the other image, how many on its changed surface (of the same surface),
    how many land hidden behind the reading, and, where that reading is a
    changed surface of one of the other's segments (``other_segments`` (H, W) int32, -1:
    none; ``n_other`` of them), the pair of segments.

    ``segments`` (H, W) int32, each pixel's segment (-1: none); ``own_depth``,
    ``other_depth`` (H, W) uint16 mm; each pixel lands in the other image by
    :func:`robot_change.change.free_space.land_pixel` (``rot``, ``trans`` .. ``max_m`` as
    there).  The same surface: a reading there within the free-space margin of the pixel's
    depth z in the other frame (``sigmas`` sigmas of the difference of two readings,
    ``noise`` the sigma table, ``pose_m``: robot_change.noise.kernels.margin_at), and the two
    cells' normals (``own_normal``, ``other_normal`` (H / f, W / f, 3), 0: none; this one's
    turned by ``rot``) within ``acos(cos_fold)``.  Hidden: the reading nearer than z by more
    than that margin and by at most ``hidden_gap_m``.  A
    changed surface: every pixel within ``radius`` belongs to a point (``other_pixel_voxel``
    (H, W) int32) of ``other_changed`` (M',) bool.
    Returns (same, found, hidden) (n_segments,) int64 and the hidden pixels'
    pairs (K,) int64, each this segment * n_other + the other's segment hiding it, in scan
    order."""
    same = np.zeros(n_segments, dtype=np.int64)
    found = np.zeros(n_segments, dtype=np.int64)
    hidden = np.zeros(n_segments, dtype=np.int64)
    h, w = own_depth.shape
    pairs = np.empty(((h + step - 1) // step) * ((w + step - 1) // step), dtype=np.int64)
    n_pairs = 0
    cell = np.arange(max(h, w)) // f  # pixel -> cell, without a division per pixel
    for r in range(0, h, step):
        for c in range(0, w, step):
            s = segments[r, c]
            if s < 0:
                continue
            v, u, z = land_pixel(own_depth[r, c], r, c, rot, trans, fx, fy, cx, cy, window,
                                 min_m, max_m)
            if v < 0:
                continue
            reading = other_depth[v, u]
            if reading == 0:
                continue
            gap = z - reading * 0.001
            margin = margin_at(noise, z, sigmas, pose_m)
            if -gap > margin:
                continue
            if gap > margin:
                if gap <= hidden_gap_m:
                    hidden[s] += 1
                    if _inside_changed(other_pixel_voxel, other_changed, v, u, radius):
                        b = other_segments[v, u]
                        if b >= 0:
                            pairs[n_pairs] = s * n_other + b
                            n_pairs += 1
                continue
            ra, ca, rb, cb = cell[r], cell[c], cell[v], cell[u]
            if rb >= other_normal.shape[0] or cb >= other_normal.shape[1]:
                continue  # past the last whole cell (an image not a multiple of f)
            a0, a1, a2 = own_normal[ra, ca, 0], own_normal[ra, ca, 1], own_normal[ra, ca, 2]
            b0, b1, b2 = (other_normal[rb, cb, 0], other_normal[rb, cb, 1],
                          other_normal[rb, cb, 2])
            if (a0 == 0 and a1 == 0 and a2 == 0) or (b0 == 0 and b1 == 0 and b2 == 0):
                continue
            dot = (rot[0, 0] * a0 + rot[0, 1] * a1 + rot[0, 2] * a2) * b0 + \
                (rot[1, 0] * a0 + rot[1, 1] * a1 + rot[1, 2] * a2) * b1 + \
                (rot[2, 0] * a0 + rot[2, 1] * a1 + rot[2, 2] * a2) * b2
            if dot < cos_fold:
                continue
            same[s] += 1
            if _inside_changed(other_pixel_voxel, other_changed, v, u, radius):
                found[s] += 1
    return same, found, hidden, pairs[:n_pairs]


def _extents(points: np.ndarray) -> np.ndarray | None:
    """(2,) the two largest spreads (4 standard deviations, m) of a segment's ``points``
    (N, 3) along their principal axes (a face's length and width, whatever the frame); None
    for fewer than 10 points."""
    if len(points) < 10:
        return None
    lam = np.linalg.eigvalsh(np.cov(np.asarray(points, dtype=np.float64).T))
    return 4.0 * np.sqrt(np.maximum(lam[1:], 1e-12))


def claim_counterparts(epoch: Epoch, changed: np.ndarray, observed: np.ndarray, other: Epoch,
                       other_changed: np.ndarray, other_from_own: np.ndarray | None,
                       params: ChangeParams) -> np.ndarray:
    """(M,) bool: ``changed`` (M,) bool points of ``epoch`` with the surface segments that
    stand where a changed surface of the ``other`` epoch stood (module docstring): of a
    segment's pixels that land, moved by ``other_from_own`` ((4, 4); None: the same camera),
    on the same surface of ``other``'s image (a reading within the free-space margin, the
    cells' normals within ``object_fold_deg``), more than ``params.object_counterpart_share``
    land on its ``other_changed`` (M',) bool points more than the pose window inside their
    outline, and those make up the share :func:`complete_objects` asks of a segment.  Or,
    for an object moved towards or away from the camera (one of its places hides the other):
    more than ``params.object_hidden_share`` of its landing pixels lie on or hidden (up to
    ``object_hidden_gap_m``) behind changed points, those make up the share, and the segment
    has the shape of the changed segment that hides it most (:func:`_extents`, within
    ``object_hidden_shape`` of each other).  Only ``observed`` (M,) bool points are added.
    Unchanged when ``params.object_counterparts`` or ``params.object_completion`` is off or
    nothing of ``other`` changed."""
    if not (params.object_counterparts and params.object_completion) or \
            not other_changed.any():
        return changed
    segment, point, size, per_point, image = _segment_pixels(epoch, params)
    cp = other.cloud_params or CloudParams()
    T = np.eye(4) if other_from_own is None else np.asarray(other_from_own, dtype=np.float64)
    intr = epoch.intrinsics
    o_segment, o_point, o_size, _, o_image = _segment_pixels(other, params)
    same, found, hidden, hidden_pairs = _counterparts_kernel(
        image, len(size), readonly_view(np.ascontiguousarray(epoch.depth)),
        np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), intr.fx, intr.fy,
        intr.cx, intr.cy, free_space_views(other, params)[2], cp.near_m(other.noise),
        float(cp.max_depth_m), readonly_view(np.ascontiguousarray(other.depth)),
        readonly_view(np.ascontiguousarray(other.pixel_voxel, dtype=np.int32)),
        np.ascontiguousarray(other_changed, dtype=np.bool_),
        params.free_space_pose_radius_px, _cell_normals(epoch, params),
        _cell_normals(other, params), params.object_cell_px, pair_sigma_table(other, epoch),
        params.free_space_sigmas, params.free_space_pose_m,
        math.cos(math.radians(params.object_fold_deg)), _COUNTERPART_STEP,
        float(params.object_hidden_gap_m), o_image, len(o_size))
    claimed = (found > params.object_counterpart_share * same) & \
        _claim(epoch, found * _COUNTERPART_STEP ** 2, size, params)
    # hidden behind its other place: nothing of it still seen unchanged where it stood, and
    # the shape of what hides it (an object added before another hides it too)
    hidden_own, hiding = np.divmod(hidden_pairs, max(len(o_size), 1))
    hidden_found = np.bincount(hidden_own, minlength=len(size))
    both = found + hidden_found
    candidates = (~claimed) & (hidden_found > 0) & \
        (both > params.object_hidden_share * (same + hidden)) & \
        _claim(epoch, both * _COUNTERPART_STEP ** 2, size, params)
    for s in np.flatnonzero(candidates):
        b = int(np.argmax(np.bincount(hiding[hidden_own == s])))  # what hides most of it
        own = _extents(epoch.points[point[segment == s]])
        front = _extents(other.points[o_point[o_segment == b]])
        if own is not None and front is not None and \
                (np.maximum(own / front, front / own) <= params.object_hidden_shape).all():
            claimed[s] = True
    if not claimed.any():
        return changed
    return changed | (observed & _joined(claimed, segment, point, per_point, epoch.n_points))
