"""Depth image <-> points in the camera optical frame (ALGORITHM.md section 1).

Camera optical frame: x right, y down, z forward, metres; pixel (row v, column u) with depth z
back-projects to ``x = ((u - cx) / fx) * z``, ``y = ((v - cy) / fy) * z``.  Pixel centres are at
integer coordinates (a centred VGA principal point is 319.5, 239.5).

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.  The kernels are
numba-compiled, single-threaded and without fastmath, so the NumPy twins in the tests give
bit-identical results.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from hw.depth import Intrinsics
from robot_change import validate
from robot_change.errors import InputError

__all__ = ["check_points", "depth_kernel_args", "depth_to_points", "project_points"]

#: Largest depth a uint16 millimetre image can hold, in metres.
MAX_DEPTH_M = 65.535
#: How an error about a depth array in metres says to convert it.
FROM_METRES = ("convert metres (NaN, inf or 0: no reading) with np.where(np.isfinite(z) & "
               "(z > 0) & (z < 65.535), np.round(z * 1000), 0).astype(np.uint16)")


@numba.njit(cache=True, nogil=True)
def _depth_to_points_kernel(depth, fx, fy, cx, cy, min_mm, max_mm):
    """(H, W) uint16 mm -> ((N, 3) float32 m, (N,) int32 flat pixel index), row-major order.

    A pixel is kept when ``min_mm <= depth <= max_mm`` and ``depth > 0``.  Arithmetic in
    float64: ``z = d / 1000``, ``x = ((u - cx) / fx) * z``, ``y = ((v - cy) / fy) * z`` (the
    ray slopes once per column and row, so a pixel costs one division, not three).

    A counting pass sizes the output (one spare row); then per image row the coordinates of
    every pixel go into row buffers in a branch-free loop the compiler vectorises (the two
    divisions per pixel dominate), and a second branch-free loop appends each pixel and
    advances the output position only for kept pixels (the spare row absorbs the last write).
    """
    height, width = depth.shape
    count = 0
    for v in range(height):
        row = depth[v]
        for u in range(width):
            d = row[u]
            count += (d > 0) & (d >= min_mm) & (d <= max_mm)
    points = np.empty((count + 1, 3), dtype=np.float32)
    pixels = np.empty(count + 1, dtype=np.int32)
    du = np.empty(width, dtype=np.float64)
    xs = np.empty(width, dtype=np.float32)
    ys = np.empty(width, dtype=np.float32)
    zs = np.empty(width, dtype=np.float32)
    keep = np.empty(width, dtype=np.int64)
    for u in range(width):
        du[u] = (u - cx) / fx
    i = 0
    for v in range(height):
        if i == count:
            break
        row = depth[v]
        dv = (v - cy) / fy
        for u in range(width):
            d = row[u]
            z = d / 1000.0
            xs[u] = du[u] * z
            ys[u] = dv * z
            zs[u] = z
            keep[u] = (d > 0) & (d >= min_mm) & (d <= max_mm)
        base = v * width
        for u in range(width):
            points[i, 0] = xs[u]
            points[i, 1] = ys[u]
            points[i, 2] = zs[u]
            pixels[i] = base + u
            i += keep[u]
    return points[:count], pixels[:count]


@numba.njit(cache=True, nogil=True)
def _project_kernel(points, fx, fy, cx, cy):
    """(N, 3) float32/float64 m -> (N, 2) float64 pixel coordinates (u, v); NaN where z <= 0
    or the point is not finite."""
    n = points.shape[0]
    out = np.empty((n, 2), dtype=np.float64)
    for i in range(n):
        x = np.float64(points[i, 0])
        y = np.float64(points[i, 1])
        z = np.float64(points[i, 2])
        if z > 0.0 and math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
            out[i, 0] = fx * x / z + cx
            out[i, 1] = fy * y / z + cy
        else:
            out[i, 0] = np.nan
            out[i, 1] = np.nan
    return out


def _check_intrinsics(intrinsics: object) -> Intrinsics:
    if not isinstance(intrinsics, Intrinsics):
        raise InputError(
            f"intrinsics must be a hw.depth.Intrinsics, got {type(intrinsics).__name__}; build one "
            "with Intrinsics(width, height, fx, fy, cx, cy) or Intrinsics.openni_default()"
        )
    return intrinsics


def _check_depth_range(min_depth_m: float, max_depth_m: float) -> tuple[float, float]:
    owner = "depth_to_points"
    lo = validate.number(owner, "min_depth_m", min_depth_m, 0.0, MAX_DEPTH_M, unit=" metres")
    hi = validate.number(owner, "max_depth_m", max_depth_m, lo, math.inf, low_open=True,
                         unit=" metres (beyond min_depth_m)")
    return lo, hi


def depth_to_points(
    depth: np.ndarray,
    intrinsics: Intrinsics,
    *,
    min_depth_m: float = 0.3,
    max_depth_m: float = 5.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project the valid pixels of a depth image.

    Parameters
    ----------
    depth : (H, W) uint16
        Depth in millimetres, 0 = no reading.
    intrinsics : hw.depth.Intrinsics
        For an image of exactly W x H pixels.
    min_depth_m, max_depth_m : float
        Keep pixels with ``min_depth_m <= z <= max_depth_m`` (metres; the millimetre value is
        compared with ``ceil(min * 1000)`` and ``floor(max * 1000)``).

    Returns
    -------
    points : (N, 3) float32
        Metres, camera optical frame (x right, y down, z forward), row-major pixel order.
    pixels : (N,) int32
        Flat pixel index ``row * W + col`` of each point.
    """
    return _depth_to_points_kernel(*depth_kernel_args(depth, intrinsics, min_depth_m, max_depth_m))


def depth_kernel_args(
    depth: np.ndarray, intrinsics: Intrinsics, min_depth_m: float, max_depth_m: float
) -> tuple[np.ndarray, float, float, float, float, np.uint16, np.uint16]:
    """Validate a depth image, its intrinsics and the depth limits for a back-projecting kernel.

    Returns ``(depth (H, W) uint16 C-contiguous, fx, fy, cx, cy, min_mm, max_mm)``: a pixel is
    kept when ``d > 0`` and ``min_mm <= d <= max_mm`` (``ceil(min * 1000)`` and
    ``floor(max * 1000)``; limits that keep nothing come back as 65535 and 0).
    Raises :class:`InputError` naming the problem.
    """
    if not isinstance(depth, np.ndarray):
        raise InputError(
            f"depth must be a numpy array (H, W) of uint16 millimetres, got "
            f"{type(depth).__name__}"
        )
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise InputError(
            f"depth must be a 2-D uint16 array of millimetres, got {depth.dtype} of shape "
            f"{depth.shape}; {FROM_METRES}"
        )
    intrinsics = _check_intrinsics(intrinsics)
    height, width = depth.shape
    if (width, height) != (intrinsics.width, intrinsics.height):
        raise InputError(
            f"depth is {width}x{height} but the intrinsics are for "
            f"{intrinsics.width}x{intrinsics.height}; pass intrinsics for this resolution "
            "(Intrinsics.scaled)"
        )
    if height * width >= 2**31:
        raise InputError(f"depth image {width}x{height} has too many pixels for int32 indices")
    lo, hi = _check_depth_range(min_depth_m, max_depth_m)
    min_mm = max(1, math.ceil(round(lo * 1000.0, 6)))
    max_mm = min(65535, math.floor(round(hi * 1000.0, 6)))
    return (
        np.ascontiguousarray(depth),
        float(intrinsics.fx),
        float(intrinsics.fy),
        float(intrinsics.cx),
        float(intrinsics.cy),
        np.uint16(min_mm) if min_mm <= max_mm else np.uint16(65535),
        np.uint16(max_mm) if min_mm <= max_mm else np.uint16(0),
    )


def check_points(
    points: object, name: str = "points", *, allow_float64: bool = False
) -> np.ndarray:
    """Validate an (N, 3) float32 point array (float64 too when ``allow_float64``) and return it
    C-contiguous.  Raises :class:`InputError` naming the problem and the fix."""
    if not isinstance(points, np.ndarray):
        raise InputError(
            f"{name} must be a numpy array of shape (N, 3), got {type(points).__name__}"
        )
    allowed = (np.float32, np.float64) if allow_float64 else (np.float32,)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(
            f"{name} must have shape (N, 3) (x, y, z in metres), got shape {points.shape}"
        )
    if points.dtype not in allowed:
        wanted = " or ".join(np.dtype(t).name for t in allowed)
        raise InputError(
            f"{name} must be {wanted}, got {points.dtype}; convert with "
            f"{name}.astype(np.float32)"
        )
    return np.ascontiguousarray(points)


def project_points(points: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """Project camera-frame points to pixel coordinates.

    Parameters
    ----------
    points : (N, 3) float32 or float64
        Metres, camera optical frame.
    intrinsics : hw.depth.Intrinsics

    Returns
    -------
    (N, 2) float64
        ``(u, v)`` = (column, row) in pixels, ``u = fx * x / z + cx``, ``v = fy * y / z + cy``;
        NaN for points with ``z <= 0`` or non-finite coordinates.  Not clipped to the image.
    """
    points = check_points(points, allow_float64=True)
    intrinsics = _check_intrinsics(intrinsics)
    return _project_kernel(
        points,
        float(intrinsics.fx),
        float(intrinsics.fy),
        float(intrinsics.cx),
        float(intrinsics.cy),
    )
