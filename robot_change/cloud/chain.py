"""Depth image -> clean point cloud: the four stages of ALGORITHM.md section 1 in one call.

    depth (H, W) uint16 mm
      -> points and voxel grid, in one pass
                      :func:`robot_change.cloud.depth_voxels.depth_voxel_grid` (min/max depth, one
                      centroid per voxel; the same as geometry.depth_to_points followed by
                      voxels.voxel_grid)
      -> outliers     :func:`robot_change.cloud.outliers.statistical_outliers` (on the voxel cloud)
      -> plane        :func:`robot_change.cloud.plane.fit_plane_ransac` (dominant plane removed)

Temporal fusion (:func:`robot_change.cloud.fusion.fuse_depth`) happens before this, on the frames.
Numeric module: arrays in, arrays out; no I/O, no logging, no global state.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import numba
import numpy as np

from hw.depth import Intrinsics
from robot_change import validate
from robot_change.cloud.depth_voxels import depth_voxel_grid
from robot_change.cloud.geometry import MAX_DEPTH_M
from robot_change.cloud.outliers import statistical_outliers
from robot_change.cloud.plane import Plane, fit_plane_ransac
from robot_change.errors import BadValue, InputError
from robot_change.noise.profile import DEFAULT_NEAR_M, NoiseProfile

__all__ = [
    "PIXEL_KEPT",
    "PIXEL_NO_POINT",
    "PIXEL_OUTLIER",
    "PIXEL_PLANE",
    "CleanCloud",
    "CloudParams",
    "clean_cloud",
]

#: Values of ``CleanCloud.pixel_stage``: what happened to each depth pixel.
PIXEL_NO_POINT = 0  # no reading, or outside min/max depth (or a voxel key could not hold it)
PIXEL_OUTLIER = 1  # its voxel was dropped by statistical outlier removal
PIXEL_PLANE = 2  # its voxel was on the removed plane
PIXEL_KEPT = 3  # its voxel is in CleanCloud.points (row pixel_voxel)


_number = functools.partial(validate.number, "CloudParams")
_whole = functools.partial(validate.whole, "CloudParams")


@dataclasses.dataclass(frozen=True)
class CloudParams:
    """Parameters of :func:`clean_cloud`, validated on construction (:class:`InputError`
    naming the field, its value and the allowed range).

    The defaults are for a Kinect-class VGA camera (OpenNI: fx = 525) looking into a room.
    """

    # 3 cm: a room-sized VGA view (surfaces 1.5-5 m away) lands at 11k-30k points after all
    # stages (measured on single frames: TUM office 11.0k; our five synthetic rooms 19k-30k;
    # at 2 cm they give 22k-54k, at 2.5 cm 15k-40k): the 10k-30k the paper's clouds had, which
    # keeps the mixture fit and the change step within their budgets.  It is about the Kinect's
    # depth noise at 4 m (sigma_z ~ 3 cm), so voxels hide little the sensor resolves there; a
    # 10 cm object still covers ~3 x 3 voxels per face.  Table-top work wants ~1 cm.
    leaf_m: float = 0.03
    # None: the camera's (:meth:`near_m`: 0.4 m, where Kinect-class sensors read nothing useful
    # nearer, or the near range of a camera that reads nearer); beyond 5 m the depth
    # quantization step of the disparity (~7 cm at 5 m) exceeds three voxels.
    min_depth_m: float | None = None
    max_depth_m: float = 5.0
    # Outlier removal on the voxel cloud: see outliers.statistical_outliers for why k = 4,
    # alpha = 2 and a cap of 2 leaves (PCL's k = 50 assumes the raw cloud's density).
    remove_outliers: bool = True
    outlier_k: int = 4
    outlier_alpha: float = 2.0
    outlier_cap_leaves: float = 2.0
    # Dominant plane: inliers within 2 cm (centroids of a floor seen at 3-4 m scatter by about
    # that much).  Up to 1000 triples with the adaptive stop at 99.9 %
    # confidence: a plane holding 30 % of the points stops it after ~250 triples, one holding
    # 20 % after ~860; a smaller plane is rarely "the floor".  A plane needs 500 inliers, i.e.
    # 0.45 m^2 at a 3 cm leaf, so a wall fragment in a cluttered view does not count.
    # up/max_tilt (camera frame, y down) restrict which planes count when the camera's
    # mounting is known, e.g. up = (0, -1, 0) and 15 degrees for a level camera; off by default
    # (a table top seen from above is tilted by the camera's pitch, 34-44 degrees in the OSD
    # frames).
    remove_plane: bool = True
    plane_distance_m: float = 0.02
    plane_iterations: int = 1000
    plane_seed: int = 0
    plane_min_inliers: int = 500
    plane_up: tuple[float, float, float] | None = None
    plane_max_tilt_deg: float | None = None

    def __post_init__(self) -> None:
        _number("leaf_m", self.leaf_m, 0.001, 1.0, unit=" metres")
        if self.min_depth_m is not None:
            _number("min_depth_m", self.min_depth_m, 0.0, MAX_DEPTH_M, unit=" metres")
        _number("max_depth_m", self.max_depth_m, float(self.min_depth_m)
                if isinstance(self.min_depth_m, (int, float)) else 0.0, 1000.0, low_open=True,
                unit=" metres (and above min_depth_m)")
        for name in ("remove_outliers", "remove_plane"):
            validate.flag("CloudParams", name, getattr(self, name))
        _whole("outlier_k", self.outlier_k, 1, 26)
        _number("outlier_alpha", self.outlier_alpha, 0.0, 100.0, unit=" standard deviations")
        _number("outlier_cap_leaves", self.outlier_cap_leaves, 0.0, 100.0, low_open=True,
                unit=" leaf sizes")
        _number("plane_distance_m", self.plane_distance_m, 0.0, 1.0, low_open=True,
                unit=" metres")
        _whole("plane_iterations", self.plane_iterations, 1, 1_000_000)
        _whole("plane_seed", self.plane_seed, 0, 2**63 - 1)
        _whole("plane_min_inliers", self.plane_min_inliers, 3, 2**31 - 1)
        if (self.plane_up is None) != (self.plane_max_tilt_deg is None):
            raise InputError(
                f"CloudParams.plane_up={self.plane_up!r}, plane_max_tilt_deg="
                f"{self.plane_max_tilt_deg!r}: give both (camera-frame up vector, e.g. "
                "(0, -1, 0), and the largest tilt in degrees) or neither"
            )
        if self.plane_up is not None:
            try:
                up = np.asarray(self.plane_up, dtype=np.float64)
            except (TypeError, ValueError):
                up = np.zeros(0)
            if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.any(up):
                raise BadValue("CloudParams", "plane_up", self.plane_up, "a non-zero finite "
                               "3-vector (x right, y down, z forward)", wrong_type=True)
            object.__setattr__(self, "plane_up", tuple(float(v) for v in up))
            _number("plane_max_tilt_deg", self.plane_max_tilt_deg, 0.0, 90.0, unit=" degrees")

    def near_m(self, noise: NoiseProfile | None = None) -> float:
        """The nearest depth used, metres: ``min_depth_m``, or where that is None the camera's
        (``noise.near_m``; :data:`~robot_change.noise.profile.DEFAULT_NEAR_M` for a camera not
        named)."""
        if self.min_depth_m is not None:
            return float(self.min_depth_m)
        return DEFAULT_NEAR_M if noise is None else noise.near_m

    def for_camera(self, noise: NoiseProfile) -> CloudParams:
        """These parameters with ``min_depth_m`` set to :meth:`near_m` of ``noise``: what a
        scene of that camera is made with, and records."""
        if self.min_depth_m is not None:
            return self
        return dataclasses.replace(self, min_depth_m=noise.near_m)


@dataclasses.dataclass(frozen=True, eq=False)
class CleanCloud:
    """The result of :func:`clean_cloud`.

    ``points``: (M, 3) float32 voxel centroids in metres (camera optical frame) that survived
    all four stages, sorted by voxel key.  ``keys``: (M,) int64 their packed voxel keys
    (:func:`robot_change.cloud.voxels.unpack_keys`).  ``counts``: (M,) int32 depth pixels per point.
    ``pixel_voxel``: (H, W) int32, for each depth pixel the row in ``points`` it was merged
    into, -1 for pixels that were invalid, out of range, or whose voxel was dropped as an
    outlier or as part of the plane.  ``pixel_stage``: (H, W) uint8, which of those happened
    (``PIXEL_NO_POINT``, ``PIXEL_OUTLIER``, ``PIXEL_PLANE``, ``PIXEL_KEPT``).  ``plane``: the
    removed plane; its ``inliers`` run over the voxels that survived outlier removal
    (``stage_counts["after_outliers"]`` of them). ``stage_counts``: ``pixels`` (valid depth
    readings), ``points`` (in the depth range), ``voxels``, ``after_outliers``,
    ``plane_inliers``, ``kept``.  ``timings_ms``: ``voxel_ms`` (depth to voxel grid, back-projection
    included), ``outlier_ms``, ``plane_ms`` and ``preprocess_ms`` (the whole call, pixel maps
    included).
    """

    points: np.ndarray
    keys: np.ndarray
    counts: np.ndarray
    pixel_voxel: np.ndarray
    pixel_stage: np.ndarray
    plane: Plane
    stage_counts: dict[str, int]
    timings_ms: dict[str, float]
    params: CloudParams

    def __len__(self) -> int:
        return int(self.points.shape[0])


@numba.njit(cache=True, nogil=True)
def _take_rows(points, rows):
    """(V, 3) float32, (R,) int64 -> (R, 3) float32 ``points[rows]`` (twice as fast as
    ``np.take`` on a room's 30k rows)."""
    out = np.empty((rows.shape[0], 3), dtype=points.dtype)
    for j in range(rows.shape[0]):
        r = rows[j]
        out[j, 0] = points[r, 0]
        out[j, 1] = points[r, 1]
        out[j, 2] = points[r, 2]
    return out


@numba.njit(cache=True, nogil=True)
def _finish(points, keys, counts, kept_rows, on_plane, pixel_record, record_voxel):
    """The clean cloud and the pixel maps, in two passes.

    ``points`` (V, 3), ``keys`` (V,), ``counts`` (V,): the voxel grid; ``kept_rows`` (K,)
    int64 ascending: the voxels outlier removal kept; ``on_plane`` (K,) bool: which of those
    the plane took; ``pixel_record`` (P,) int32 and ``record_voxel`` (Q,) int32: each pixel's
    voxel in two steps (:class:`robot_change.cloud.depth_voxels.DepthVoxels`).  Returns
    (points (M, 3), keys (M,), counts (M,), pixel rows (P,) int32 with -1 for none, pixel
    stages (P,) uint8).
    """
    v = points.shape[0]
    voxel_to_final = np.full(v, -1, dtype=np.int32)
    voxel_stage = np.full(v, PIXEL_OUTLIER, dtype=np.uint8)
    m = 0
    for j in range(kept_rows.shape[0]):
        m += not on_plane[j]
    out_points = np.empty((m, 3), dtype=points.dtype)
    out_keys = np.empty(m, dtype=keys.dtype)
    out_counts = np.empty(m, dtype=counts.dtype)
    f = 0
    for j in range(kept_rows.shape[0]):
        r = kept_rows[j]
        if on_plane[j]:
            voxel_stage[r] = PIXEL_PLANE
        else:
            voxel_stage[r] = PIXEL_KEPT
            voxel_to_final[r] = f
            out_points[f, 0] = points[r, 0]
            out_points[f, 1] = points[r, 1]
            out_points[f, 2] = points[r, 2]
            out_keys[f] = keys[r]
            out_counts[f] = counts[r]
            f += 1
    # per record, the pixel's row and stage packed as row * 4 + stage (row -1: -4 + stage),
    # with one more entry for pixels without a point: one gather per pixel below
    n_rec = record_voxel.shape[0]
    packed = np.empty(n_rec + 1, dtype=np.int32)
    for r in range(n_rec):
        vr = record_voxel[r]
        packed[r] = voxel_to_final[vr] * 4 + voxel_stage[vr]
    packed[n_rec] = -4 + PIXEL_NO_POINT
    n = pixel_record.shape[0]
    rows = np.empty(n, dtype=np.int32)
    stages = np.empty(n, dtype=np.uint8)
    sentinel = np.uint32(n_rec)
    for i in range(n):
        # -1 (no point) wraps to 2**32 - 1 and becomes the sentinel; an unsigned index also
        # spares numba's negative-index fix-up (1.5x faster)
        x = packed[min(np.uint32(pixel_record[i]), sentinel)]
        rows[i] = x >> 2
        stages[i] = np.uint8(x & 3)
    return out_points, out_keys, out_counts, rows, stages


def clean_cloud(
    depth: np.ndarray, intrinsics: Intrinsics, params: CloudParams = CloudParams()
) -> CleanCloud:
    """Depth image -> points -> voxel grid -> outlier removal -> dominant plane removed.

    Parameters
    ----------
    depth : (H, W) uint16
        Millimetres, 0 = no reading (a single frame or the output of ``fuse_depth``).
    intrinsics : hw.depth.Intrinsics
        For a W x H image.
    params : CloudParams

    Returns
    -------
    CleanCloud
        Empty (0 points, no plane) for a frame without valid pixels; never raises for that.
    """
    if not isinstance(params, CloudParams):
        raise InputError(f"params must be a CloudParams, got {type(params).__name__}")
    start = time.perf_counter()
    voxels = depth_voxel_grid(depth, intrinsics, params.leaf_m, min_depth_m=params.near_m(),
                              max_depth_m=params.max_depth_m)
    t_voxel = time.perf_counter()

    if params.remove_outliers:
        inlier = statistical_outliers(voxels.points, voxels.keys, voxels.leaf_m, params.outlier_k,
                                      params.outlier_alpha, params.outlier_cap_leaves)
        kept_rows = np.flatnonzero(inlier)
    else:
        kept_rows = np.arange(len(voxels), dtype=np.int64)
    t_outlier = time.perf_counter()

    survivors = _take_rows(voxels.points, kept_rows)
    if params.remove_plane:
        plane = fit_plane_ransac(
            survivors, params.plane_distance_m, params.plane_iterations, params.plane_seed,
            up=params.plane_up, max_tilt_deg=params.plane_max_tilt_deg,
            min_inliers=params.plane_min_inliers,
        )
    else:
        plane = Plane.none(len(kept_rows))
    t_plane = time.perf_counter()

    points, keys, counts, pixel_voxel, pixel_stage = _finish(
        voxels.points, voxels.keys, voxels.counts, kept_rows, plane.inliers, voxels.pixel_record,
        voxels.record_voxel)
    height, width = depth.shape
    end = time.perf_counter()

    return CleanCloud(
        points=points,
        keys=keys,
        counts=counts,
        pixel_voxel=pixel_voxel.reshape(height, width),
        pixel_stage=pixel_stage.reshape(height, width),
        plane=plane,
        stage_counts={
            "pixels": int(np.count_nonzero(depth)),
            "points": voxels.n_points,
            "voxels": len(voxels),
            "after_outliers": int(len(kept_rows)),
            "plane_inliers": int(plane.n_inliers),
            "kept": len(points),
        },
        timings_ms={
            "voxel_ms": (t_voxel - start) * 1e3,
            "outlier_ms": (t_outlier - t_voxel) * 1e3,
            "plane_ms": (t_plane - t_outlier) * 1e3,
            "preprocess_ms": (end - start) * 1e3,
        },
        params=params,
    )
