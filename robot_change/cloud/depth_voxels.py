"""Depth image straight to a voxel grid (ALGORITHM.md section 1, first two steps in one pass).

:func:`depth_voxel_grid` gives what :func:`robot_change.cloud.geometry.depth_to_points`
followed by :func:`robot_change.cloud.voxels.voxel_grid` gives (the same float32 points in the
same voxels, summed in float64 in point order), without writing the (N, 3) points out and
reading them back: each image row is back-projected into row buffers and goes straight into the
voxel hash.  The one
difference is where the hash bands end (at image rows here, at chunks of points there), which
can move a centroid by one float32 rounding step.  On a dense VGA frame this saves about a fifth
of the two steps' time (docs/benchmarks.md).

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.
"""

from __future__ import annotations

import dataclasses

import numba
import numpy as np

from hw.depth import Intrinsics
from robot_change import validate
from robot_change.cloud.geometry import depth_kernel_args
from robot_change.cloud.voxels import (
    _KEY_OFFSET,
    VoxelGrid,
    _accumulate_row,
    _band_workspace,
    _merge_records,
    _pack_key,
    _voxel_slot,
    voxel_table_size,
)

__all__ = ["DepthVoxels", "depth_voxel_grid"]


@dataclasses.dataclass(frozen=True, eq=False)
class DepthVoxels:
    """A depth image's voxel grid.

    ``points`` (M, 3) float32 centroids, ``counts`` (M,) int32, ``keys`` (M,) int64 strictly
    increasing, ``leaf_m``: as in :class:`~robot_change.cloud.voxels.VoxelGrid`.  Which pixel went
    where, in two steps (so the kernel need not rewrite every pixel): ``pixel_record`` (H * W,)
    int32, row-major, the hash record of each pixel (-1: no point), and ``record_voxel`` (R,)
    int32, the voxel of each record; :meth:`pixel_voxel` composes them.  ``n_points``: pixels
    that became points (valid, within the depth limits, and a key could hold them).
    """

    points: np.ndarray
    counts: np.ndarray
    keys: np.ndarray
    leaf_m: float
    pixel_record: np.ndarray
    record_voxel: np.ndarray
    n_points: int

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def pixel_voxel(self) -> np.ndarray:
        """(H * W,) int32: the voxel of each pixel, -1 for a pixel without a point."""
        out = np.full(self.pixel_record.shape, -1, dtype=np.int32)
        has = self.pixel_record >= 0
        out[has] = self.record_voxel[self.pixel_record[has]]
        return out

    def grid(self) -> VoxelGrid:
        """The same voxels as a :class:`~robot_change.cloud.voxels.VoxelGrid` whose ``inverse`` is
        :meth:`pixel_voxel` (per pixel, not per point)."""
        return VoxelGrid(points=self.points, counts=self.counts, keys=self.keys,
                         inverse=self.pixel_voxel(), leaf_m=self.leaf_m)


@numba.njit(cache=True, nogil=True)
def _depth_voxel_kernel(depth, fx, fy, cx, cy, min_mm, max_mm, inv_leaf, tbits, limit):
    """(H, W) uint16 mm -> (centroids (M, 3) float32, counts (M,) int32, keys (M,) int64 sorted,
    pixel record (H * W,) int32 (-1: no point), record voxel (R,) int32, points kept).

    Per image row: a branch-free loop (vectorised) back-projects every pixel exactly as
    :func:`robot_change.cloud.geometry._depth_to_points_kernel` does (float64, then float32), and
    computes its key exactly as :func:`robot_change.cloud.voxels._voxel_kernel` does, with -1 for a
    pixel that is not kept; a second loop looks the keys up and accumulates, with an image row
    as the row of the band rule (see :func:`robot_change.cloud.voxels._voxel_kernel`).
    """
    height, width = depth.shape
    inverse, tmask, tshift, table, rec_keys, rec = _band_workspace(height * width, tbits)
    du = np.empty(width, dtype=np.float64)
    for u in range(width):
        du[u] = (u - cx) / fx
    xs = np.empty(width, dtype=np.float64)
    ys = np.empty(width, dtype=np.float64)
    zs = np.empty(width, dtype=np.float64)
    keys = np.empty(width, dtype=np.int64)
    slots = np.empty(width, dtype=np.uint64)
    lo = np.float64(-_KEY_OFFSET)
    hi = np.float64(_KEY_OFFSET - 1)
    first = 0
    p = np.int64(0)  # typed: no literal-0 specialisation of the kernels it goes to
    kept = 0
    for v in range(height):
        if p - first > limit - width:
            first = p
        row = depth[v]
        dv = (v - cy) / fy
        for u in range(width):
            d = row[u]
            z = d / 1000.0
            x32 = np.float32(du[u] * z)
            y32 = np.float32(dv * z)
            z32 = np.float32(z)
            xs[u] = x32
            ys[u] = y32
            zs[u] = z32
            kfx = np.floor(np.float64(x32) * inv_leaf)
            kfy = np.floor(np.float64(y32) * inv_leaf)
            kfz = np.floor(np.float64(z32) * inv_leaf)
            ok = ((d > 0) & (d >= min_mm) & (d <= max_mm)
                  & (lo <= kfx) & (kfx <= hi) & (lo <= kfy) & (kfy <= hi)
                  & (lo <= kfz) & (kfz <= hi))
            keys[u] = _pack_key(kfx, kfy, kfz, ok)
            slots[u] = _voxel_slot(keys[u], tshift)
        base = v * width
        p, added = _accumulate_row(keys, slots, xs, ys, zs, width, inverse[base:base + width],
                                   table, tmask, rec_keys, rec, first, p)
        kept += added
    centroids, counts, voxel_keys, record_voxel = _merge_records(rec_keys, rec, p)
    return centroids, counts, voxel_keys, inverse, record_voxel, kept


def depth_voxel_grid(
    depth: np.ndarray,
    intrinsics: Intrinsics,
    leaf_m: float,
    *,
    min_depth_m: float = 0.3,
    max_depth_m: float = 5.0,
) -> DepthVoxels:
    """Back-project the valid pixels of a depth image and replace the points in each voxel of
    edge ``leaf_m`` by their centroid.

    Parameters
    ----------
    depth : (H, W) uint16
        Millimetres, 0 = no reading.
    intrinsics : hw.depth.Intrinsics
        For a W x H image.
    leaf_m : float
        Voxel edge in metres, > 0.
    min_depth_m, max_depth_m : float
        Depth limits as in :func:`robot_change.cloud.geometry.depth_to_points`.

    Returns
    -------
    DepthVoxels
        The same keys and counts as ``voxel_grid(depth_to_points(...)[0], leaf_m)`` and the same
        centroids up to float64 summation order; :meth:`DepthVoxels.pixel_voxel` maps pixels
        (not points) to voxels.
    """
    args = depth_kernel_args(depth, intrinsics, min_depth_m, max_depth_m)
    leaf = validate.positive("depth_voxel_grid", "leaf_m", leaf_m, 1e6, unit=" metres")
    bits, limit = voxel_table_size(args[0].shape[1])
    centroids, counts, keys, pixel_record, record_voxel, kept = _depth_voxel_kernel(
        *args, 1.0 / leaf, bits, limit)
    return DepthVoxels(points=centroids, counts=counts, keys=keys, leaf_m=leaf,
                       pixel_record=pixel_record, record_voxel=record_voxel, n_points=int(kept))
