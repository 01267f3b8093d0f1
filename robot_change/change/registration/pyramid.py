"""Depth pyramids of a depth image: block-averaged vertex maps and their normals, coarse to
fine, and the Kinect's depth noise that weighs every residual.

A cell of the finest level is the mean of the back-projected readings of its ``f x f`` block
that lie within a depth band of the block's centre (a depth edge does not blend fore- and
background); averaging *points* keeps a cell on the surface and smooths out the Kinect's
disparity terraces (ALGORITHM.md section 4).  Coarser levels merge 2 x 2 cells.  Kernels are
``@njit(cache=True, nogil=True)`` with NumPy twins in ``tests/test_registration.py``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numba
import numpy as np

from hw.depth import Intrinsics
from robot_change.arrays import readonly_view
from robot_change.errors import InputError

from .params import RegistrationParams


@numba.njit(cache=True, nogil=True)
def _vertex_level(depth, factor, fx, fy, cx, cy, min_mm, max_mm, band_m, band_slope):
    """Vertex map of one pyramid level: (h, w, 3) float32 metres, h = H // factor.

    Cell (i, j) is the mean of the back-projected readings of its block (rows i*f..i*f+f-1,
    columns j*f..) that lie within ``band_m + band_slope * f * za / fx`` of the anchor za, the
    mean reading of the block's central 2 x 2 pixels (a band symmetric about the surface at the
    centre, so noise does not bias the mean); a cell with no central reading or fewer than
    f*f/4 readings in the band is invalid (z = 0).
    """
    height, width = depth.shape
    h = height // factor
    w = width // factor
    out = np.zeros((h, w, 3), dtype=np.float32)
    count = np.zeros((h, w), dtype=np.int32)
    need = max(1, (factor * factor) // 4)
    half = factor // 2
    for i in range(h):
        for j in range(w):
            # the anchor: mean of the valid readings of the block's central 2 x 2 (1 x 1)
            za = 0.0
            na = 0
            for r in range(i * factor + max(half - 1, 0), i * factor + half + 1):
                for c in range(j * factor + max(half - 1, 0), j * factor + half + 1):
                    d = np.int64(depth[r, c])
                    if d >= min_mm and d <= max_mm:
                        za += d * 0.001
                        na += 1
            if na == 0:
                continue
            za /= na
            band = band_m + band_slope * factor * za / fx
            sx = 0.0
            sy = 0.0
            sz = 0.0
            n = 0
            for r in range(i * factor, i * factor + factor):
                for c in range(j * factor, j * factor + factor):
                    d = np.int64(depth[r, c])
                    if d < min_mm or d > max_mm:
                        continue
                    z = d * 0.001
                    if abs(z - za) > band:
                        continue
                    sx += (c - cx) * z
                    sy += (r - cy) * z
                    sz += z
                    n += 1
            if n >= need:
                out[i, j, 0] = sx / (n * fx)
                out[i, j, 1] = sy / (n * fy)
                out[i, j, 2] = sz / n
                count[i, j] = n
    return out, count


@numba.njit(cache=True, nogil=True)
def _merge_level(vertex, count, band_m, band_slope_per_cell):
    """The next coarser level: each 2 x 2 group of cells of (``vertex`` (h, w, 3), ``count``
    (h, w) readings per cell) becomes one cell, the reading-weighted mean of the group's cells
    that lie within ``band_m + band_slope_per_cell * za`` in depth of the anchor za (the mean
    depth of the group's valid cells); a group with none valid, or fewer than a quarter of
    its readings in the band, is invalid.  Returns (vertex (h//2, w//2, 3), count)."""
    h = vertex.shape[0] // 2
    w = vertex.shape[1] // 2
    out = np.zeros((h, w, 3), dtype=np.float32)
    out_count = np.zeros((h, w), dtype=np.int32)
    for i in range(h):
        for j in range(w):
            za = 0.0
            na = 0
            total = 0
            for r in range(2 * i, 2 * i + 2):
                for c in range(2 * j, 2 * j + 2):
                    if count[r, c] > 0:
                        za += vertex[r, c, 2]
                        na += 1
                        total += count[r, c]
            if na == 0:
                continue
            za /= na
            band = band_m + band_slope_per_cell * za
            sx = 0.0
            sy = 0.0
            sz = 0.0
            n = 0
            for r in range(2 * i, 2 * i + 2):
                for c in range(2 * j, 2 * j + 2):
                    k = count[r, c]
                    if k > 0 and abs(vertex[r, c, 2] - za) <= band:
                        sx += k * vertex[r, c, 0]
                        sy += k * vertex[r, c, 1]
                        sz += k * vertex[r, c, 2]
                        n += k
            if n > 0 and 4 * n >= total:
                out[i, j, 0] = sx / n
                out[i, j, 1] = sy / n
                out[i, j, 2] = sz / n
                out_count[i, j] = n
    return out, out_count


@numba.njit(cache=True, nogil=True)
def _normal_map(vertex, max_step):
    """(h, w, 3) float32 unit normals (facing the camera) from central differences of the
    vertex map; zero where a neighbour is missing or a difference is longer than
    ``max_step * z`` (a depth edge)."""
    h, w, _ = vertex.shape
    out = np.zeros((h, w, 3), dtype=np.float32)
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            z = vertex[i, j, 2]
            if z <= 0.0 or vertex[i, j - 1, 2] <= 0.0 or vertex[i, j + 1, 2] <= 0.0 or \
                    vertex[i - 1, j, 2] <= 0.0 or vertex[i + 1, j, 2] <= 0.0:
                continue
            ax = vertex[i, j + 1, 0] - vertex[i, j - 1, 0]
            ay = vertex[i, j + 1, 1] - vertex[i, j - 1, 1]
            az = vertex[i, j + 1, 2] - vertex[i, j - 1, 2]
            bx = vertex[i + 1, j, 0] - vertex[i - 1, j, 0]
            by = vertex[i + 1, j, 1] - vertex[i - 1, j, 1]
            bz = vertex[i + 1, j, 2] - vertex[i - 1, j, 2]
            lim = max_step * z
            if ax * ax + ay * ay + az * az > lim * lim or bx * bx + by * by + bz * bz > lim * lim:
                continue
            nx = ay * bz - az * by
            ny = az * bx - ax * bz
            nz = ax * by - ay * bx
            norm = math.sqrt(nx * nx + ny * ny + nz * nz)
            if norm <= 0.0:
                continue
            if nx * vertex[i, j, 0] + ny * vertex[i, j, 1] + nz * vertex[i, j, 2] > 0.0:
                norm = -norm
            out[i, j, 0] = nx / norm
            out[i, j, 1] = ny / norm
            out[i, j, 2] = nz / norm
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class Level:
    """One level of a view's pyramid: ``vertex`` (h, w, 3) float32 points (m, camera optical
    frame; z = 0 where the cell is empty), ``normal`` (h, w, 3) float32 unit normals facing the
    camera (zero where there is none), ``factor`` pixels per cell side and the level's
    intrinsics (pixels of the level)."""

    factor: int
    vertex: np.ndarray
    normal: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float

    def without(self, drop: np.ndarray, *, points: bool) -> Level:
        """This level with the cells ``drop`` (h, w) bool emptied (``points``: no reading, so
        they are not counted) or without their normals (ICP pairs none of them)."""
        field = "vertex" if points else "normal"
        return dataclasses.replace(self, **{field: np.where(
            drop[:, :, None], 0.0, getattr(self, field)).astype(np.float32)})

    def onto(self, other: Level, M: np.ndarray) -> tuple:
        """The agreement kernels' first arguments for this level's cells moved by ``M`` (4, 4,
        other-from-own) into the image of ``other``: (vertex, normal, other's vertex and
        normal, rot (3, 3), trans (3,), other's fx, fy, cx, cy)."""
        return (self.vertex, self.normal, other.vertex, other.normal, M[:3, :3].copy(),
                M[:3, 3].copy(), other.fx, other.fy, other.cx, other.cy)

    @property
    def has_normal(self) -> np.ndarray:
        """(h, w) bool: the cells with a normal (the cells that can be paired)."""
        n = self.normal  # three comparisons: ~9 times faster than n.any(axis=2)
        return (n[:, :, 0] != 0) | (n[:, :, 1] != 0) | (n[:, :, 2] != 0)

    @property
    def n_normals(self) -> int:
        """Cells with a normal."""
        return int(np.count_nonzero(self.has_normal))


def levels(depth: np.ndarray, intrinsics: Intrinsics, params: RegistrationParams
           ) -> list[Level]:
    """The pyramid, coarse to fine: the finest level from the image, each coarser one by
    merging 2 x 2 cells of the one below (the factors must double)."""
    finest = int(params.levels[-1])
    vertex, count = _cells(depth, intrinsics, finest, params)
    out = []
    for f in reversed(params.levels):
        if f != finest:
            vertex, count = _merge_level(vertex, count, params.band_m,
                                         params.band_slope * f / intrinsics.fx)
        out.append(_level(vertex, intrinsics, f))
    return out[::-1]


def _cells(depth: np.ndarray, intrinsics: Intrinsics, factor: int, params: RegistrationParams
           ) -> tuple[np.ndarray, np.ndarray]:
    min_mm = int(math.ceil(params.near_m * 1000.0))
    max_mm = int(math.floor(params.max_depth_m * 1000.0))
    return _vertex_level(readonly_view(depth), int(factor), intrinsics.fx, intrinsics.fy,
                         intrinsics.cx, intrinsics.cy, min_mm, max_mm, params.band_m,
                         params.band_slope)


def _level(vertex: np.ndarray, intrinsics: Intrinsics, f: int) -> Level:
    # a difference of two cells spans 2 f pixels; allow surfaces up to ~76 deg
    normal = _normal_map(vertex, 8.0 * f / intrinsics.fx)
    return Level(int(f), vertex, normal, intrinsics.fx / f, intrinsics.fy / f,
                 (intrinsics.cx + 0.5) / f - 0.5, (intrinsics.cy + 0.5) / f - 0.5)


def _levels_key(intrinsics: Intrinsics, params: RegistrationParams) -> tuple:
    """What :func:`levels` depends on besides the image: the key it is kept under."""
    return ("registration_levels", intrinsics, params.levels, params.near_m,
            params.max_depth_m, params.band_m, params.band_slope)


def kept_levels(depth: np.ndarray, intrinsics: Intrinsics, params: RegistrationParams,
                keep: dict | None) -> list[Level]:
    """:func:`levels` of ``depth``, taken from ``keep`` (a dict that belongs to that image
    alone, an epoch's ``derived``) when made there before with the same intrinsics and
    pyramid parameters, and left there (None: made, not kept)."""
    key = _levels_key(intrinsics, params)
    out = keep.get(key) if keep is not None else None
    if out is None:
        out = levels(depth, intrinsics, params)
        if keep is not None:
            keep[key] = out
    return out


def surface_level(depth: np.ndarray, intrinsics: Intrinsics, factor: int,
                  params: RegistrationParams, keep: dict | None = None) -> Level:
    """One level of cells of ``factor`` x ``factor`` pixels made from the image as the finest
    level of :func:`levels` is (vertex and normal maps, ``params``' depth range and band):
    that finest level itself when the registration kept it in ``keep`` (:func:`kept_levels`)
    and its cells are ``factor`` pixels."""
    if keep is not None and int(params.levels[-1]) == factor:
        kept = keep.get(_levels_key(intrinsics, params))
        if kept is not None:
            return kept[-1]
    return _level(_cells(depth, intrinsics, factor, params)[0], intrinsics, factor)


def check_depth(name: str, depth: Any, intrinsics: Intrinsics) -> np.ndarray:
    """``depth`` as a C-contiguous (H, W) uint16 image of ``intrinsics``' size, or an
    InputError naming ``name``."""
    if not isinstance(depth, np.ndarray) or depth.ndim != 2 or depth.dtype != np.uint16:
        raise InputError(f"{name} depth must be an (H, W) uint16 array of millimetres")
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise InputError(f"{name} depth is {depth.shape[1]}x{depth.shape[0]} but the intrinsics "
                         f"are for {intrinsics.width}x{intrinsics.height}")
    return np.ascontiguousarray(depth)
