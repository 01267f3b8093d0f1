"""The free-space check: which points of one epoch the other epoch's depth image sees through
(ALGORITHM.md section 3), projected through the registration, with the pose tolerance, the
hole filling and the sensing window; and which points the other camera could see at all.

Kernels are ``@njit(cache=True, nogil=True)`` with NumPy twins in ``tests/test_change.py``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from hw.depth import Intrinsics
from robot_change.arrays import readonly_view
from robot_change.change.epoch import Epoch, kept, pair_sigma_table
from robot_change.change.params import ChangeParams
from robot_change.cloud.chain import CloudParams
from robot_change.errors import InputError
from robot_change.noise.kernels import margin_at

__all__ = [
    "FreeSpace",
    "Votes",
    "free_and_observed",
    "free_space_views",
    "core_votes_at_poses",
    "free_space_votes",
    "land_pixel",
    "open_mask",
    "other_views",
    "sensing_window",
]


#: How a pixel is seen through (:func:`_free_space_kernel`): by a reading beyond it, or by a
#: hole that opens onto something beyond it.
_THROUGH_READING = 1
_THROUGH_HOLE = 2


class Votes(NamedTuple):
    """Free-space evidence per point (:func:`free_space_votes`), (M,) int32 each."""

    votes: np.ndarray
    total: np.ndarray
    unseen: np.ndarray
    core: np.ndarray


class FreeSpace(NamedTuple):
    """One direction's free-space check over a view's points (:func:`free_and_observed`),
    (M,) bool each: seen through, observed by the other camera, seen through in the core."""

    free: np.ndarray
    observed: np.ndarray
    core: np.ndarray


@numba.njit(cache=True, nogil=True)
def _filter_columns(src, radius, take_min):
    """One 1-D pass of :func:`_window_filter` down the columns of ``src`` (H, W) uint16: the
    min (``take_min``) or max over rows ``[r - radius, r + radius]`` clipped to the image, by
    van Herk / Gil-Werman (prefix and suffix extrema in blocks of ``2 radius + 1`` rows: three
    comparisons a pixel whatever the radius; the inner loops run along a row, so they
    vectorise).  Values are taken as they are: the min's caller maps "no reading" (0) to
    65535 first."""
    h, w = src.shape
    k = 2 * radius + 1
    n = h + 2 * radius
    ident = np.uint16(65535) if take_min else np.uint16(0)
    pre = np.empty((n, w), dtype=np.uint16)
    suf = np.empty((n, w), dtype=np.uint16)
    out = np.empty((h, w), dtype=np.uint16)
    for b0 in range(0, n, k):
        b1 = min(b0 + k, n)
        for i in range(b0, b1):  # prefix extrema within the block
            r = i - radius
            for c in range(w):
                v = src[r, c] if 0 <= r < h else ident
                if i > b0:
                    v = min(pre[i - 1, c], v) if take_min else max(pre[i - 1, c], v)
                pre[i, c] = v
        for i in range(b1 - 1, b0 - 1, -1):  # suffix extrema within the block
            r = i - radius
            for c in range(w):
                v = src[r, c] if 0 <= r < h else ident
                if i < b1 - 1:
                    v = min(suf[i + 1, c], v) if take_min else max(suf[i + 1, c], v)
                suf[i, c] = v
    for r in range(h):
        for c in range(w):
            if take_min:
                out[r, c] = min(suf[r, c], pre[r + 2 * radius, c])
            else:
                out[r, c] = max(suf[r, c], pre[r + 2 * radius, c])
    return out


@numba.njit(cache=True, nogil=True)
def _window_filter(depth, radius, take_min):
    """Square-window min (``take_min``: readings > 0 only, 0 where the window has none) or
    max of a (H, W) uint16 depth image, window (2 radius + 1)^2, separable: columns, then
    rows (as the columns of the transpose)."""
    src = depth.copy()  # a read-only image and a writable one: one type of src
    if take_min:  # no reading (0) never wins a min: 65535 until the end
        for r in range(src.shape[0]):
            for c in range(src.shape[1]):
                if src[r, c] == 0:
                    src[r, c] = 65535
    tmp = np.ascontiguousarray(_filter_columns(src, radius, take_min).T)
    out = np.ascontiguousarray(_filter_columns(tmp, radius, take_min).T)
    if take_min:
        for r in range(out.shape[0]):
            for c in range(out.shape[1]):
                if out[r, c] == 65535:
                    out[r, c] = 0
    return out


def sensing_window(depth: np.ndarray, min_fraction: float = 0.05) -> tuple[int, int, int, int]:
    """(row0, row1, col0, col1), inclusive: the part of a depth image the sensor delivers.

    Depth cameras leave strips along the image border without readings (a Kinect's right
    columns, cropped images); rows and columns at the border with fewer than ``min_fraction``
    readings are outside the window.  A point that lands there was not observed, rather than
    seen through.  The whole image when it has no readings at all.
    """
    valid = depth > 0
    rows = np.flatnonzero(valid.mean(axis=1) >= min_fraction)
    cols = np.flatnonzero(valid.mean(axis=0) >= min_fraction)
    if rows.size == 0 or cols.size == 0:
        return 0, depth.shape[0] - 1, 0, depth.shape[1] - 1
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


@numba.njit(cache=True, nogil=True, inline="always")
def land_pixel(d_mm, r, c, rot, trans, fx, fy, cx, cy, window, min_m, max_m):
    """Where the reading ``d_mm`` (mm) of pixel (``r``, ``c``) lands in the other camera
    (``rot`` (3, 3), ``trans`` (3,) map this camera's frame into the other's; same
    intrinsics): (row, column, depth in the other frame (m)); row -1 when the other camera
    could not have seen it (behind it, outside its sensing ``window`` (row0, row1, col0,
    col1, inclusive), or outside its depth range ``min_m``..``max_m``)."""
    z = d_mm * 0.001
    x = (c - cx) * z / fx
    y = (r - cy) * z / fy
    px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
    py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
    pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
    if pz < min_m or pz > max_m:
        return -1, -1, pz
    u = int(math.floor(fx * px / pz + cx + 0.5))
    v = int(math.floor(fy * py / pz + cy + 0.5))
    if v < window[0] or v > window[1] or u < window[2] or u > window[3]:
        return -1, -1, pz
    return v, u, pz


@numba.njit(cache=True, nogil=True)
def _warp_kernel(own_depth, pixel_voxel, rot, trans, fx, fy, cx, cy, width, window, min_m,
                 max_m, row0=0, row1=-1):
    """Where each pixel of this epoch's depth image that belongs to a point lands in the other
    epoch's image (:func:`land_pixel`).

    ``own_depth`` (H, W) uint16 mm; ``pixel_voxel`` (H, W) int32, the point of each pixel (-1:
    none, e.g. the removed floor: not warped); (``rot`` (3, 3), ``trans`` (3,)) maps this
    camera's frame into the other's (same intrinsics, image ``width`` pixels wide).  Returns
    ``target`` (P,) int64, the flat index of the other image's pixel the reading projects to
    (-1 for no reading or no point here; -2 when the other camera could not have seen it:
    behind it, outside its sensing ``window`` (row0, row1, col0, col1, inclusive), or outside
    its depth range ``min_m``..``max_m``) and ``z_other`` (P,) float64, its depth in the other
    frame (m).  Only rows ``row0`` to ``row1`` (exclusive; -1: the last) are looked at: the
    caller's rows with a point.
    """
    h, w = own_depth.shape
    target = np.full(h * w, -1, dtype=np.int64)
    z_other = np.zeros(h * w)
    for r in range(row0, h if row1 < 0 else row1):
        for c in range(w):
            d = own_depth[r, c]
            if d == 0 or pixel_voxel[r, c] < 0:
                continue
            p = r * w + c
            v, u, pz = land_pixel(d, r, c, rot, trans, fx, fy, cx, cy, window, min_m, max_m)
            if v < 0:
                target[p] = -2
                continue
            target[p] = v * width + u
            z_other[p] = pz
    return target, z_other


@numba.njit(cache=True, nogil=True)
def _free_space_kernel(pixel_voxel, target, z_other, near_other, far_other, other, width,
                       shadow_bf, n_points, noise, sigmas, pose_m, no_reading_is_free,
                       sensor_min_m, hole_needs_far_edge, own, rot_back, trans_back, fx, fy,
                       cx, cy, dropout_px, p0, p1):
    """Per pixel whether the other image sees through it (``_THROUGH_READING``: a reading
    beyond it; ``_THROUGH_HOLE``: a hole that opens beyond it; 0: not), and per point how many
    pixels it has and how many of them the other camera could not have seen.

    ``pixel_voxel`` (P,) int32 row of each pixel's point (-1 none); ``target`` (P,) and
    ``z_other`` (P,) from :func:`_warp_kernel`; ``near_other`` (P',) the other image's
    nearest reading in the pose window (0: none there), ``far_other`` (P',) its farthest
    reading in the hole window (0: none).  A pixel that lands on no reading of ``other`` (P',
    uint16 mm, the other image, ``width`` pixels a row) nearer than ``sensor_min_m`` plus the
    margin was not observed (too near for the other camera).  The other reading is
    ``near_other``, else ``far_other``; with neither, the pixel is seen through when
    ``no_reading_is_free`` and, with ``hole_needs_far_edge``, the first reading to its left
    or right along its row lies beyond z by more than the margin, unless it may lie in a
    projector shadow: such a first reading nearer than z by more than the margin and no
    farther away than the shadow such a surface casts at depth z, ``shadow_bf`` (1/z_near -
    1/z) pixels (``shadow_bf`` = baseline x fx, m px; 0: no shadows), and, with
    ``sensor_min_m``, unless this epoch's camera did not see the stretch of the other
    camera's ray nearer than that empty (:func:`_near_ray_clear`; ``own`` (P,) uint16 mm this
    epoch's image, (``rot_back``, ``trans_back``) the other camera's frame into this one's,
    ``dropout_px`` the widest hole taken for a dropout); only pixels ``p0`` to ``p1``
    (exclusive) are looked at, the caller's span with a point.  Seen through: reading > z + the
    margin, ``sigmas`` sigmas of the difference of two readings at z (``noise`` the sigma
    table, robot_change.noise.kernels.margin_at, ``pose_m`` what the registration leaves;
    metres, z = ``z_other``).
    """
    through = np.zeros(pixel_voxel.shape[0], dtype=np.int8)
    total = np.zeros(n_points, dtype=np.int32)
    unseen = np.zeros(n_points, dtype=np.int32)
    # the first reading left and right of each pixel of ``other`` (mm, pixels away; 0: none),
    # filled a row at a time when a pixel of that row is first asked about: a row's walk is
    # O(width) once, however many holes of it the points land on
    row_filled = np.zeros(other.shape[0] // width, dtype=np.bool_)
    left_mm = np.empty(other.shape[0], dtype=np.uint16)
    left_px = np.empty(other.shape[0], dtype=np.int32)
    right_mm = np.empty(other.shape[0], dtype=np.uint16)
    right_px = np.empty(other.shape[0], dtype=np.int32)
    for p in range(p0, p1):
        v = pixel_voxel[p]
        if v < 0:
            continue
        total[v] += 1
        q = target[p]
        if q < 0:
            unseen[v] += 1
            continue
        z = z_other[p]
        margin = margin_at(noise, z, sigmas, pose_m)
        if other[q] == 0 and z < sensor_min_m + margin:  # too near for the other camera
            unseen[v] += 1
            continue
        d1 = near_other[q]
        if d1 == 0:
            d1 = far_other[q]
        if d1 == 0:
            if not no_reading_is_free:
                continue
            if (shadow_bf > 0.0 or hole_needs_far_edge) and not row_filled[q // width]:
                _fill_row(other, width, q // width, left_mm, left_px, right_mm, right_px)
                row_filled[q // width] = True
            if hole_needs_far_edge and not (left_mm[q] * 0.001 > z + margin
                                            or right_mm[q] * 0.001 > z + margin):
                continue
            if _casts_shadow(left_mm[q], left_px[q], z, margin, shadow_bf) \
                    or _casts_shadow(right_mm[q], right_px[q], z, margin, shadow_bf):
                continue
            if sensor_min_m > 0.0 and not _near_ray_clear(
                    q, width, own, rot_back, trans_back, fx, fy, cx, cy, sensor_min_m,
                    noise, sigmas, pose_m, dropout_px, shadow_bf):
                continue
            through[p] = _THROUGH_HOLE
            continue
        if d1 * 0.001 > z + margin:
            through[p] = _THROUGH_READING
    return through, total, unseen


@numba.njit(cache=True, nogil=True)
def _read_through_kernel(own, pixels, rots, transs, fx, fy, cx, cy, width, window, min_m, max_m,
                         near_other, far_other, other, noise, sigmas, pose_m, sensor_min_m):
    """(K, N) bool: for each of K poses (``rots`` (K, 3, 3), ``transs`` (K, 3), this camera's
    frame into the other's) whether each of the N ``pixels`` (flat indices into ``own``, the
    (P,) uint16 mm image of this epoch, ``width`` pixels a row) is seen through by a *reading*
    of the other image: :func:`_free_space_kernel`'s ``_THROUGH_READING`` at that pose (the
    pixel lands by :func:`land_pixel`; not when the other camera could not see it or it lies
    too near for it; the other reading is ``near_other``, else ``far_other``; through when
    farther than the margin), every pose in one pass."""
    n_pose = rots.shape[0]
    out = np.zeros((n_pose, pixels.shape[0]), dtype=np.bool_)
    for i in range(pixels.shape[0]):
        p = pixels[i]
        d = own[p]
        if d == 0:
            continue
        r = p // width
        c = p - r * width
        for k in range(n_pose):
            v, u, z = land_pixel(d, r, c, rots[k], transs[k], fx, fy, cx, cy, window, min_m,
                                 max_m)
            if v < 0:
                continue
            q = v * width + u
            margin = margin_at(noise, z, sigmas, pose_m)
            if other[q] == 0 and z < sensor_min_m + margin:
                continue
            d1 = near_other[q]
            if d1 == 0:
                d1 = far_other[q]
            if d1 > 0 and d1 * 0.001 > z + margin:
                out[k, i] = True
    return out


@numba.njit(cache=True, nogil=True)
def _near_ray_clear(q, width, own, rot_back, trans_back, fx, fy, cx, cy, sensor_min_m,
                    noise, sigmas, pose_m, dropout_px, shadow_bf):
    """Whether this epoch's camera saw the stretch of the other camera's ray through its
    pixel ``q`` (flat, ``width`` pixels a row) nearer than ``sensor_min_m`` empty: ``own``
    (flat uint16 mm, this epoch's image) reads beyond each of its samples (0.4, 0.6, 0.8 and
    1.0 x ``sensor_min_m`` from the other camera) by more than the margin, or has a hole
    there that a dropout or a projector shadow explains (:func:`_hole_explained`).  A sample
    with a surface before it, or in a hole nothing explains, may hold a surface too near for
    the other camera to read: the other's hole is then no evidence of free space.  Samples
    behind this camera or outside its image say nothing; with none left the stretch was not
    seen, and is not clear.  (``rot_back`` (3, 3), ``trans_back`` (3,)) map the other
    camera's frame into this one's."""
    ray_x = (q % width - cx) / fx
    ray_y = (q // width - cy) / fy
    height = own.shape[0] // width
    seen = 0
    for k in range(4):
        s = sensor_min_m * (0.4 + 0.2 * k)
        x = (rot_back[0, 0] * ray_x + rot_back[0, 1] * ray_y + rot_back[0, 2]) * s + trans_back[0]
        y = (rot_back[1, 0] * ray_x + rot_back[1, 1] * ray_y + rot_back[1, 2]) * s + trans_back[1]
        z = (rot_back[2, 0] * ray_x + rot_back[2, 1] * ray_y + rot_back[2, 2]) * s + trans_back[2]
        if z <= 0.05:
            continue
        c = int(math.floor(fx * x / z + cx + 0.5))
        r = int(math.floor(fy * y / z + cy + 0.5))
        if c < 0 or c >= width or r < 0 or r >= height:
            continue
        seen += 1
        i = r * width + c
        if own[i] == 0:
            if not _hole_explained(own, width, i, dropout_px, shadow_bf, noise, sigmas,
                                   pose_m):
                return False
        elif own[i] * 0.001 <= z + margin_at(noise, z, sigmas, pose_m):
            return False
    return seen > 0


@numba.njit(cache=True, nogil=True)
def _hole_explained(depth, width, i, dropout_px, shadow_bf, noise, sigmas, pose_m):
    """Whether the run of pixels with no reading along the row of pixel ``i`` of ``depth``
    (flat uint16 mm, ``width`` pixels a row) is a dropout (``dropout_px`` pixels or fewer) or
    a projector shadow: a nearer reading on one side, a farther one (by more than the margin
    at its depth) on the other, no farther apart than the shadow the nearer casts on the
    farther, ``shadow_bf`` (1/z_near - 1/z_far) pixels (``shadow_bf`` = baseline x fx).  A run
    that meets the image's border is not explained: a surface too near for the camera to
    read may stand there."""
    row0 = i - i % width
    a = i
    while a > row0 and depth[a - 1] == 0:
        a -= 1
    b = i + 1
    while b < row0 + width and depth[b] == 0:
        b += 1
    if a == row0 or b == row0 + width:  # the run is [a, b)
        return False
    if b - a <= dropout_px:
        return True
    z_far = max(depth[a - 1], depth[b]) * 0.001
    return _casts_shadow(min(depth[a - 1], depth[b]), b - a, z_far,
                         margin_at(noise, z_far, sigmas, pose_m), shadow_bf)


@numba.njit(cache=True, nogil=True)
def _fill_row(other, width, row, left_mm, left_px, right_mm, right_px):
    """Row ``row`` of ``other`` (flat uint16 mm, ``width`` pixels a row): for each pixel, the
    first reading to its left and to its right (mm, 0: none) and how many pixels away, into
    ``left_mm``, ``left_px``, ``right_mm``, ``right_px`` (flat, like ``other``)."""
    start = row * width
    last = -1
    for c in range(width):
        left_mm[start + c] = other[start + last] if last >= 0 else 0
        left_px[start + c] = c - last if last >= 0 else 0
        if other[start + c] > 0:
            last = c
    last = -1
    for c in range(width - 1, -1, -1):
        right_mm[start + c] = other[start + last] if last >= 0 else 0
        right_px[start + c] = last - c if last >= 0 else 0
        if other[start + c] > 0:
            last = c


@numba.njit(cache=True, nogil=True, inline="always")
def _casts_shadow(near_mm, distance_px, z, margin, shadow_bf):
    """Whether a reading ``near_mm`` (0: none), ``distance_px`` pixels along the row from a
    pixel with no reading, can shadow from the projector a surface at depth ``z`` (m) there:
    nearer by more than ``margin`` (m), and the shadow it casts, ``shadow_bf`` (1/z_near -
    1/z) pixels wide (``shadow_bf`` = baseline x fx), reaches that far."""
    if near_mm == 0 or shadow_bf <= 0.0:
        return False
    z_near = near_mm * 0.001
    return z_near < z - margin and distance_px <= shadow_bf * (1.0 / z_near - 1.0 / z) + 1.0


def open_mask(mask: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool: the morphological opening of ``mask`` (H, W) bool by a square of side
    ``2 radius + 1``: what fits no such square is dropped, the rest kept whole (the square is
    clipped at the image's border; radius 0: the mask as it is)."""
    if radius <= 0:
        return mask.copy()
    out = np.zeros_like(mask)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if not rows.size:
        return out
    # the mask's bounding box and ``radius`` around it: every window that matters lies inside
    # (or is clipped by the image's border, as it would be whole)
    h, w = mask.shape
    r0, r1 = max(rows[0] - radius, 0), min(rows[-1] + radius + 1, h)
    c0, c1 = max(cols[0] - radius, 0), min(cols[-1] + radius + 1, w)
    part = mask[r0:r1, c0:c1]
    # read-only, as other_views' image: the kernel compiles for one argument type
    inside = readonly_view(np.ascontiguousarray(~part, dtype=np.uint16))
    core = _window_filter(inside, radius, False) == 0  # eroded: every pixel around is in mask
    out[r0:r1, c0:c1] = _window_filter(
        readonly_view(np.ascontiguousarray(core, dtype=np.uint16)), radius, False) > 0
    return out


def other_views(other_depth: np.ndarray, pose_radius: int, hole_radius: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the free-space check reads of the other epoch's (H, W) uint16 depth image:
    ``near`` (its nearest reading within ``pose_radius`` pixels, 0: none), ``far`` (its
    farthest within ``hole_radius``), both (H, W) uint16 mm, and its :func:`sensing_window`
    as a (4,) int64 array.  A function of the image alone: a reference's is computed once
    (:func:`free_and_observed` keeps it in the epoch's ``derived``)."""
    other = readonly_view(np.ascontiguousarray(other_depth))
    near = _window_filter(other, int(pose_radius), True) if pose_radius > 0 else other
    far = _window_filter(other, int(hole_radius), False) if hole_radius > 0 else other
    return near, far, np.array(sensing_window(other), dtype=np.int64)


def free_space_votes(pixel_voxel: np.ndarray, own_depth: np.ndarray, other_depth: np.ndarray,
                     n_points: int, noise: np.ndarray, sigmas: float = 3.0, pose_m: float = 0.0,
                     pose_radius: int = 0, hole_radius: int = 0,
                     no_reading_is_free: bool = True, *,
                     intrinsics: Intrinsics | None = None,
                     other_from_own: np.ndarray | None = None,
                     depth_range_m: tuple[float, float] = (0.0, 65.535),
                     shadow_baseline_m: float = 0.0,
                     sensor_min_m: float = 0.0,
                     hole_needs_far_edge: bool = False,
                     views: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                     edge_px: int = 0) -> Votes:
    """Free-space evidence per point of one epoch against the other epoch's depth image.

    Each of the point's pixels (``pixel_voxel == v``) is back-projected with its own reading,
    moved into the other camera by ``other_from_own`` ((4, 4), the registration; identity when
    not given, and then the pixel is its own projection) and projected into the other image
    (same ``intrinsics``).  There the other epoch saw *through* the point when its reading is
    farther by more than ``sigmas`` sigmas of the difference of two readings at z, k sqrt(2
    sigma(z)^2 + ``pose_m``^2) (z = the depth in the other frame, m; ``noise`` the (n,) sigma
    table of one reading, :func:`robot_change.change.epoch.pair_sigma_table`).  The reading used
    is the *nearest* one of the other image within ``pose_radius`` pixels (a square window: a
    small residual pose error does not make static edges look seen through); where that
    window has no reading, the *farthest* reading within ``hole_radius`` pixels (projector
    shadows and dropouts border the surface behind them);
    with none there either, the pixel counts as seen through when ``no_reading_is_free``
    (open space beyond the sensor's range) and, with ``hole_needs_far_edge``, the first
    reading along its row on one side lies beyond the point (the hole opens onto something
    farther), unless a nearer reading along its row could cast a projector shadow that wide
    on it (``shadow_baseline_m``: the projector's distance from the camera, 7.5 cm on a
    Kinect, PrimeSense or Xtion; 0: no shadows; a near object's shadow on a far surface is
    wider than ``hole_radius``), and, with ``sensor_min_m``, only when this camera saw the
    other camera's ray empty up to ``sensor_min_m`` from it (a surface that near leaves a
    hole the other camera cannot read; a hole of this image on that stretch is taken for a
    dropout when no wider than ``2 hole_radius`` pixels).  A pixel that lands behind the
    other camera, outside the part of its image it has readings in (:func:`sensing_window`),
    outside ``depth_range_m``, or on no reading nearer than ``sensor_min_m`` plus the margin
    (the camera reads nothing that near) was not observed by it.  ``views``:
    :func:`other_views` of ``other_depth`` with these radii, when already at hand.

    Returns
    -------
    Votes: votes, total, unseen, core : (n_points,) int32
        Pixels seen through, pixels, pixels the other camera could not observe, and pixels
        seen through in the core of what is seen through: by a reading of the other image
        (a hole it has is no measurement: a real camera leaves them beside every edge, on
        dark and shiny surfaces, wider than any shadow), opened (:func:`open_mask`) by
        ``edge_px``, so that what is narrower than ``2 edge_px + 1`` pixels -- flying pixels
        along a depth edge, an edge that a residual pose error or lens distortion moved by a
        few pixels, a pixel that flickered -- has no core.
    """
    if pixel_voxel.ndim != 2 or pixel_voxel.shape != own_depth.shape or \
            own_depth.shape != other_depth.shape:
        raise InputError(f"pixel_voxel {pixel_voxel.shape}, own depth {own_depth.shape} and "
                         f"other depth {other_depth.shape} must be the same (H, W)")
    for name, a in (("own_depth", own_depth), ("other_depth", other_depth)):
        if a.dtype != np.uint16:
            raise InputError(f"{name} must be uint16 millimetres, got {a.dtype}")
    height, width = own_depth.shape
    noise = np.ascontiguousarray(noise, dtype=np.float64)
    if noise.ndim != 1 or noise.size < 2 or not np.all(noise > 0):
        raise InputError("noise must be a (n,) table of positive sigmas, metres "
                         "(robot_change.noise.profile.NoiseProfile.kernel_table)")
    if intrinsics is None:
        intrinsics = Intrinsics(width, height, 525.0, 525.0, (width - 1) / 2, (height - 1) / 2)
    T = np.eye(4) if other_from_own is None else np.asarray(other_from_own, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError("other_from_own must be a finite (4, 4) rigid transform")
    near, far, window = views if views is not None else other_views(other_depth, pose_radius,
                                                                    hole_radius)
    own = readonly_view(np.ascontiguousarray(own_depth))
    pv = readonly_view(np.ascontiguousarray(pixel_voxel, dtype=np.int32))
    rows = np.flatnonzero((pv >= 0).any(axis=1))  # only rows with a point are looked at
    row0, row1 = (int(rows[0]), int(rows[-1]) + 1) if rows.size else (0, 0)
    if other_from_own is None:  # the pixel grid is shared: each pixel is its own projection
        target = np.where(own.ravel() > 0, np.arange(own.size), -1)
        z_other = own.ravel() * 0.001
    else:
        target, z_other = _warp_kernel(own, pv, T[:3, :3].copy(), T[:3, 3].copy(),
                                       intrinsics.fx, intrinsics.fy, intrinsics.cx,
                                       intrinsics.cy, width, window,
                                       float(depth_range_m[0]), float(depth_range_m[1]),
                                       row0, row1)
    other = readonly_view(np.ascontiguousarray(other_depth))
    back = np.linalg.inv(T)  # the other camera's frame into this one's
    through, total, unseen = _free_space_kernel(
        pv.ravel(), target, z_other, near.ravel(), far.ravel(), other.ravel(), width,
        float(shadow_baseline_m) * intrinsics.fx, int(n_points), noise, float(sigmas),
        float(pose_m), bool(no_reading_is_free), float(sensor_min_m), bool(hole_needs_far_edge),
        own.ravel(), back[:3, :3].copy(), back[:3, 3].copy(), intrinsics.fx, intrinsics.fy,
        intrinsics.cx, intrinsics.cy, 2 * int(hole_radius), row0 * width, row1 * width)
    # the rows with a point and ``edge_px`` around them (no pixel beyond is seen through)
    r0, r1 = max(row0 - int(edge_px), 0), min(row1 + int(edge_px), height)
    span = slice(r0 * width, r1 * width)
    flat, seen = pv.ravel()[span], through[span]
    votes = np.bincount(flat[seen > 0], minlength=int(n_points)).astype(np.int32)
    read = (seen == _THROUGH_READING).reshape(r1 - r0, width)
    if edge_px > 0:
        read = open_mask(read, int(edge_px))
    core = np.bincount(flat[read.ravel()], minlength=int(n_points)).astype(np.int32)
    return Votes(votes, total, unseen, core)


def core_votes_at_poses(pixel_voxel: np.ndarray, own_depth: np.ndarray, other_depth: np.ndarray,
                        n_points: int, noise: np.ndarray, sigmas: float, pose_m: float,
                        poses: np.ndarray, *, intrinsics: Intrinsics,
                        views: tuple[np.ndarray, np.ndarray, np.ndarray],
                        depth_range_m: tuple[float, float] = (0.0, 65.535),
                        sensor_min_m: float = 0.0, edge_px: int = 0) -> np.ndarray:
    """(K, n_points) int32: :func:`free_space_votes`' ``core`` at each of the K ``poses`` (K, 4,
    4) (``other_from_own``; the other arguments as there, ``views`` the other image's
    :func:`other_views`), in one pass over the pixels with a point.  The same counts as K
    calls, at a fraction of the cost (tests/test_change.py)."""
    height, width = own_depth.shape
    pv = np.ascontiguousarray(pixel_voxel, dtype=np.int32)
    out = np.zeros((len(poses), int(n_points)), dtype=np.int32)
    rows = np.flatnonzero((pv >= 0).any(axis=1))
    if not rows.size:
        return out
    r0 = max(int(rows[0]) - int(edge_px), 0)
    r1 = min(int(rows[-1]) + 1 + int(edge_px), height)
    flat = pv.ravel()[r0 * width:r1 * width]
    pixels = np.flatnonzero(flat >= 0)
    poses = np.asarray(poses, dtype=np.float64)
    near, far, window = views
    through = _read_through_kernel(
        readonly_view(np.ascontiguousarray(own_depth)).ravel(), pixels + r0 * width,
        np.ascontiguousarray(poses[:, :3, :3]), np.ascontiguousarray(poses[:, :3, 3]),
        intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, width, window,
        float(depth_range_m[0]), float(depth_range_m[1]), near.ravel(), far.ravel(),
        readonly_view(np.ascontiguousarray(other_depth)).ravel(), noise, float(sigmas),
        float(pose_m), float(sensor_min_m))
    for k in range(len(poses)):
        read = np.zeros(flat.shape, dtype=bool)
        read[pixels] = through[k]
        read = read.reshape(r1 - r0, width)
        if edge_px > 0:
            read = open_mask(read, int(edge_px))
        out[k] = np.bincount(flat[read.ravel()], minlength=int(n_points))
    return out


def free_space_views(base: Epoch, params: ChangeParams
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`other_views` of ``base``'s depth image with the check's radii, made once and
    kept in ``base.derived`` (a station's reference: once for all its checks)."""
    radii = (params.free_space_pose_radius_px, params.free_space_hole_radius_px)
    return kept(base.derived, ("free_space_views", *radii),
                lambda: other_views(base.depth, *radii))


def free_and_observed(other: Epoch, base: Epoch, params: ChangeParams,
                      base_from_other: np.ndarray | None) -> FreeSpace:
    """:class:`FreeSpace` over ``other``'s points: those ``base``'s depth image sees through
    (free), those ``base``'s camera could see at all (observed: the majority of their pixels
    land inside its image and within its depth range and its camera's reliable range,
    ``noise.max_range_m``), and those seen through in the core of what is
    (:func:`free_space_votes`, the cameras' ``edge_px``) at the registration's estimate and
    at every pose ``free_space_pose_deg`` about it (turned about the base camera's x and y
    axes): a registration a little off moves an edge by several pixels, and the strip along
    it is seen through at the estimate, not at the pose a little the other way."""
    cp = base.cloud_params or CloudParams()
    T = np.eye(4) if base_from_other is None else np.asarray(base_from_other, dtype=np.float64)
    depth_range = (cp.near_m(base.noise), min(cp.max_depth_m, base.noise.max_range_m))

    votes, total, unseen, core_votes = free_space_votes(
        other.pixel_voxel, other.depth, base.depth, other.n_points, pair_sigma_table(base, other),
        params.free_space_sigmas, params.free_space_pose_m, params.free_space_pose_radius_px,
        params.free_space_hole_radius_px, params.free_space_no_reading_is_free,
        intrinsics=other.intrinsics, other_from_own=base_from_other, depth_range_m=depth_range,
        shadow_baseline_m=base.noise.shadow_baseline_m, sensor_min_m=base.noise.min_range_m,
        hole_needs_far_edge=params.free_space_hole_needs_far_edge,
        views=free_space_views(base, params),
        edge_px=max(base.noise.edge_px, other.noise.edge_px))
    observed = (total > 0) & (2 * unseen < total)
    need = params.free_space_min_fraction * np.maximum(total - unseen, 1)
    free = observed & (votes >= need)
    core = free & (core_votes >= need)
    if core.any() and params.free_space_pose_deg > 0:
        # each pixel's point where that point is core, else -1 (the table's last entry)
        table = np.full(core.size + 1, -1, dtype=np.int32)
        table[:-1][core] = np.flatnonzero(core)
        angle = math.radians(params.free_space_pose_deg)
        poses = []
        for axis in (0, 1):
            for sign in (-1.0, 1.0):
                turn = np.eye(4)
                turn[:3, :3] = _axis_rotation(axis, sign * angle)
                poses.append(turn @ T)
        at_poses = core_votes_at_poses(
            table[other.pixel_voxel], other.depth, base.depth, other.n_points,
            pair_sigma_table(base, other), params.free_space_sigmas, params.free_space_pose_m,
            np.array(poses), intrinsics=other.intrinsics, views=free_space_views(base, params),
            depth_range_m=depth_range, sensor_min_m=base.noise.min_range_m,
            edge_px=max(base.noise.edge_px, other.noise.edge_px))
        core &= (at_poses >= need).all(axis=0)
    return FreeSpace(free, observed, core)


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    """(3, 3): a turn by ``angle`` (radians) about the camera's x (0) or y (1) axis."""
    c, s = math.cos(angle), math.sin(angle)
    if axis == 0:
        return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
