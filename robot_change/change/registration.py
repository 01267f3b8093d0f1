"""Registration of the current view to the station's reference: where the camera stands now.

ALGORITHM.md section 4, as built (docs/algorithm.md, "Registration"): projective point-to-plane
ICP of the current depth image against the reference's fused depth image, as KinectFusion tracks
a camera (Newcombe et al. 2011), coarse to fine on depth pyramids, with

* **vertex maps by block averaging of 3-D points** (not of depths): a cell of a level is the
  mean of the back-projected readings of its ``f x f`` block that lie within a depth band of the
  block's nearest reading (a depth edge does not blend fore- and background).  Averaging over a
  block also smooths out the Kinect's disparity quantisation terraces, the trap of
  ALGORITHM.md section 4 (two clouds' terraces line up better than their surfaces);
* **normals** from central differences of the vertex map, refused across depth edges;
* **projective association**: a current cell, moved by the estimate, is projected into the
  reference level and paired with the cell it lands on, if the two are within a distance that
  shrinks level by level and their normals agree;
* **weights**: residuals are divided by the depth noise at the point (Kinect axial noise plus
  quantisation, both growing with z^2, so near surfaces count more), then a Tukey kernel with
  a scale from the median absolute residual: the change is what does not fit;
* **degeneracy**: the 6x6 normal matrix, rotations scaled by the cloud's radius to metres, is
  decomposed; directions with little information (a bare wall leaves translations along it
  free) are not moved along and are reported (Zhang, Kaess & Singh 2016);
* **table-plane starts** (a table top only: a dominant plane of at most 2 m): top-down
  occupancy grids of the two views on their planes, cross-correlated by FFT over in-plane
  shifts for a few yaws, give starts for (x, y, yaw) in the plane that ICP from the main
  estimate cannot reach when moved objects drag it; they compete with the main estimate on a
  score taken both ways (docs/algorithm.md, step 6b);
* **trimming the change** (a table top only): the objects (cells above the table) that
  contradict the other view more than they fit it are left out and ICP is run again on the
  table and the objects that stayed put, twice (docs/algorithm.md, step 6c);
* **fitness**: the fraction of current cells with an inlier correspondence at the end, and the
  RMSE of those.  Low fitness, or an offset beyond the station tolerance, is "not at the
  station", a different answer from "changed" (decided in :mod:`robot_change.change.detect`).

The floor stays in: registration runs on the depth images, before plane removal.

Numeric module: arrays in, arrays out.  Kernels are ``@njit(cache=True, nogil=True)`` with NumPy
twins in ``tests/test_registration.py``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any

import numba
import numpy as np
from scipy import ndimage

from hw.depth import Intrinsics
from robot_change import validate
from robot_change.arrays import readonly_view
from robot_change.errors import InputError

__all__ = [
    "AXES",
    "Registration",
    "RegistrationParams",
    "depth_sigma",
    "identity_registration",
    "register_depth",
    "rotation_to_rpy_deg",
    "transform_points",
]

#: Names of the six directions of the estimate, in the order of the Gauss-Newton step
#: (rotation vector, then translation), camera optical frame: rotations about x (right),
#: y (down), z (forward), translations along them.
AXES = ("rot_x", "rot_y", "rot_z", "x", "y", "z")
#: A cell within this distance of a view's table plane is on it (metres).
_ON_PLANE_M = 0.01

_num = functools.partial(validate.number, "RegistrationParams")
_int = functools.partial(validate.whole, "RegistrationParams")
_bool = functools.partial(validate.flag, "RegistrationParams")


@dataclasses.dataclass(frozen=True)
class RegistrationParams:
    """Parameters of :func:`register_depth`, validated on construction.

    ``levels``: pyramid factors, coarse to fine (a level of factor f has (H/f) x (W/f) cells);
    ``iterations`` per level; ``max_distance_m`` per level: correspondences farther apart are
    not paired.  The defaults cover offsets of 15 cm and 6 degrees (docs/algorithm.md).
    """

    # Register at all (False: the identity, for cameras bolted in place, and to measure).
    enabled: bool = True
    levels: tuple[int, ...] = (16, 8, 4)
    iterations: tuple[int, ...] = (12, 10, 6)
    max_distance_m: tuple[float, ...] = (0.35, 0.15, 0.06)
    # After the level of index search_level (0 = coarsest), translations along the two least
    # constrained translation directions (this step, out to this reach) are scored by their
    # inlier count and ICP goes on from the best: rooms let ICP slide along the floor and
    # walls (ALGORITHM.md section 4), and a yaw error is first taken up by a sideways slide.
    search_level: int = 1
    search_step_m: float = 0.1
    search_reach_m: float = 0.4
    # ... and screw motions (rotation and translation together) along the two least
    # constrained directions of the whole 6-D system, rotations scaled by the cloud's radius,
    # search_screw_steps steps of search_step_m each way (0: none; 1 did as well as 2-4 on the
    # table tops): a table top leaves the turn about its normal coupled with a slide.
    search_screw_steps: int = 1
    # At the coarsest level ICP also runs with Tukey's cut at least wide_cut_m (metres; 0:
    # not), and goes on from the better-scoring of the two ends (inliers less seen-through
    # cells, as the search).  On a table top the plane aligns first, the residual scale
    # collapses to the noise and the objects' pairs, still centimetres off, are cut: the
    # estimate drifts about the table's normal.  A room's walls keep the narrow cut right.
    wide_cut_m: float = 0.2
    # Table-plane starts (0: none): when the dominant plane of the reference's coarsest level
    # holds at least table_plane_fraction of its cells (a table top: 0.63-0.91 of the cells;
    # the current's need only be that plane again), and both views' span at most
    # table_max_extent_m (a table top 0.8-1.2 m; room floors 0.40-0.81 but 2.7-3.5 m), the
    # two views are drawn top-down on that plane (table_cell_m cells: +1 above it by more than
    # table_object_m, -1 on it, 0 unseen) and cross-correlated over in-plane shifts (FFT) for
    # yaws about its normal out to table_yaw_deg in table_yaw_step_deg steps; the
    # table_starts best distinct peaks are run through ICP down to search_level and compete
    # there with the main estimate on the search's score.  A table top's moved objects drag
    # ICP into a compromise; its outline and the objects that stayed fix (x, y, yaw).
    table_starts: int = 3
    table_plane_fraction: float = 0.6
    table_max_extent_m: float = 2.0
    table_cell_m: float = 0.02
    table_object_m: float = 0.015
    table_yaw_deg: float = 10.0
    table_yaw_step_deg: float = 2.0
    # The starts compete with the main estimate on a score taken both ways: each view's
    # inlier cells, less the cells either view sees through, less table_hole_weight times the
    # cells of either view that land on no reading of the other (a table top's outline).
    table_hole_weight: float = 1.0
    # On a table top, after the finest level: trim_rounds rounds of ICP from search_level down
    # to the finest level without the objects that changed: the connected groups of cells
    # standing more than table_object_m above each view's plane in which the cells that
    # contradict the other view (seen through, or paired beyond inlier_sigmas) outnumber
    # trim_conflict_share of those that contradict or fit.  Moved objects drag ICP into a
    # compromise; the table and the objects that stayed put are the static part.  0: none.
    trim_rounds: int = 2
    trim_conflict_share: float = 0.5
    # On a table top, at the final estimate: when more than table_outline_holes of each view's
    # table cells (within 1 cm of its plane) that land in the other image land on no reading
    # there, the two views' tables do not overlap at that pose (a wrong pose, or outlines
    # that differ, as when nothing on the table stayed put and the crop changed): the
    # directions in the table's plane (two slides, the turn about its normal) are reported
    # weak.  The smaller of the two views' shares was 0.001-0.015 at right poses (dropouts
    # and the field of view's edge; one of 147 at 0.032) and 0.027-0.087 at 13 of 15 wrong
    # ones on the table-top tuning sample (docs/benchmarks.md).  0: not checked.
    table_outline_holes: float = 0.02
    # On a table top, at the final estimate: when fewer than table_static_share of the two
    # views' object cells (standing more than table_object_m above their plane) fit the
    # other view, no object stayed put; the pose in the table's plane then rests on the
    # table's outline alone, like a bare table, and those directions are reported weak.
    # At right poses the share was 0.000-0.017 on the tuning pairs where every object moved
    # or shifted and 0.065-0.72 where one stayed (docs/benchmarks.md).  0: not checked.
    table_static_share: float = 0.03
    # Normals of a pair must agree within this angle.
    max_normal_angle_deg: float = 30.0
    # A cell is the mean of the block's readings within this band of the reading at its
    # centre: band = band_m + band_slope * (f * z / fx) (so a slanted floor's block is kept).
    band_m: float = 0.03
    band_slope: float = 2.0
    # Tukey's constant, in units of the robust residual scale (4.685: 95 % efficiency).
    tukey_c: float = 4.685
    # A correspondence is an inlier (fitness, RMSE) within this many noise sigmas.
    inlier_sigmas: float = 3.0
    # Eigenvalues of the scaled normal matrix per unit weight below this are weak directions.
    weak_eigenvalue: float = 1e-4
    # Stop a level when the step is below this (metres; rotations times the cloud radius):
    # 0.1 mm, a tenth of the depth noise at 0.5 m; a smaller one buys no accuracy.
    tol_m: float = 1e-4
    # Station tolerance: fitness below min_fitness, a translation above max_translation_m, a
    # rotation above max_rotation_deg, or more than max_seen_through of either whole view seen
    # through by the other (the views contradict each other: another place, or a change too
    # large to register against) is "not at the station".  Seen through: a reading farther by
    # more than seen_through_margin_m + seen_through_margin_per_m2 * z^2.
    min_fitness: float = 0.5
    max_seen_through: float = 0.25
    seen_through_margin_m: float = 0.03
    seen_through_margin_per_m2: float = 0.004
    max_translation_m: float = 0.5
    max_rotation_deg: float = 20.0
    # Depth readings outside this range are not used (metres).
    min_depth_m: float = 0.4
    max_depth_m: float = 5.0

    def __post_init__(self) -> None:
        _bool("enabled", self.enabled)
        n = len(self.levels) if isinstance(self.levels, tuple) else -1
        for name in ("levels", "iterations", "max_distance_m"):
            value = getattr(self, name)
            if not isinstance(value, tuple) or len(value) != n or n < 1:
                raise InputError(f"RegistrationParams.{name} must be a tuple of the same length "
                                 f"as levels (>= 1), got {value!r}")
        for f in self.levels:
            _int("levels", f, 1, 64)
        if any(a != 2 * b for a, b in zip(self.levels, self.levels[1:])):
            raise InputError(f"RegistrationParams.levels={self.levels!r}: each factor must be "
                             f"twice the next (coarse to fine), e.g. (16, 8, 4)")
        for it in self.iterations:
            _int("iterations", it, 0, 100)
        for d in self.max_distance_m:
            _num("max_distance_m", d, 0.0, 5.0, low_open=True, unit=" metres")
        _int("search_level", self.search_level, 0, n - 1)
        _num("search_step_m", self.search_step_m, 0.0, 1.0, low_open=True, unit=" metres")
        _num("search_reach_m", self.search_reach_m, 0.0, 5.0, unit=" metres")
        _int("search_screw_steps", self.search_screw_steps, 0, 20)
        _num("wide_cut_m", self.wide_cut_m, 0.0, 5.0, unit=" metres")
        _int("table_starts", self.table_starts, 0, 20)
        _num("table_plane_fraction", self.table_plane_fraction, 0.0, 1.0)
        _num("table_max_extent_m", self.table_max_extent_m, 0.0, 100.0, unit=" metres")
        _num("table_cell_m", self.table_cell_m, 0.002, 0.2, unit=" metres")
        _num("table_object_m", self.table_object_m, 0.0, 1.0, unit=" metres")
        _num("table_yaw_deg", self.table_yaw_deg, 0.0, 45.0)
        _num("table_yaw_step_deg", self.table_yaw_step_deg, 0.0, 45.0, low_open=True)
        _num("table_hole_weight", self.table_hole_weight, 0.0, 100.0)
        _int("trim_rounds", self.trim_rounds, 0, 20)
        _num("trim_conflict_share", self.trim_conflict_share, 0.0, 1.0)
        _num("table_outline_holes", self.table_outline_holes, 0.0, 1.0)
        _num("table_static_share", self.table_static_share, 0.0, 1.0)
        _num("max_normal_angle_deg", self.max_normal_angle_deg, 0.0, 90.0, low_open=True)
        _num("band_m", self.band_m, 0.0, 1.0, unit=" metres")
        _num("band_slope", self.band_slope, 0.0, 100.0)
        _num("tukey_c", self.tukey_c, 0.0, 100.0, low_open=True)
        _num("inlier_sigmas", self.inlier_sigmas, 0.0, 100.0, low_open=True)
        _num("weak_eigenvalue", self.weak_eigenvalue, 0.0, 1.0)
        _num("tol_m", self.tol_m, 0.0, 1.0, low_open=True, unit=" metres")
        _num("min_fitness", self.min_fitness, 0.0, 1.0)
        _num("max_seen_through", self.max_seen_through, 0.0, 1.0, low_open=True)
        _num("seen_through_margin_m", self.seen_through_margin_m, 0.0, 10.0, unit=" metres")
        _num("seen_through_margin_per_m2", self.seen_through_margin_per_m2, 0.0, 1.0,
             unit=" per metre")
        _num("max_translation_m", self.max_translation_m, 0.0, 100.0, unit=" metres")
        _num("max_rotation_deg", self.max_rotation_deg, 0.0, 180.0)
        _num("min_depth_m", self.min_depth_m, 0.0, 100.0, unit=" metres")
        _num("max_depth_m", self.max_depth_m, self.min_depth_m, 100.0, low_open=True,
             unit=" metres")

    def replace(self, **changes: Any) -> RegistrationParams:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True, eq=False)
class Registration:
    """The estimated rigid transform between the two camera frames, and how far to trust it.

    ``T_ref_from_cur`` (4, 4) float64 maps current camera-frame points into the reference
    camera frame (metres).  ``fitness``: fraction of the current's cells with an inlier
    correspondence (0..1); ``rmse_m`` of those residuals (point-to-plane).
    ``seen_through``: the larger of the two whole views' fractions seen through by the other
    (finest level, floor and table included).  ``weak``: names
    (:data:`AXES`) of directions the views leave unconstrained (not moved along; the estimate
    there is the starting value), and on a table top the directions in the table's plane
    together, when one of them is weak, the two tables do not overlap at the estimate
    (``RegistrationParams.table_outline_holes``) or no object stayed put
    (``table_static_share``): not to be trusted.  ``eigenvalues`` (6,) of the scaled normal
    matrix per unit weight, ascending.  ``n_pairs`` inlier correspondences, ``n_cells``
    current cells at the finest level; ``iterations`` run; ``ms`` the time taken;
    ``converged``.
    """

    T_ref_from_cur: np.ndarray
    fitness: float
    rmse_m: float
    weak: tuple[str, ...]
    eigenvalues: np.ndarray
    n_pairs: int
    n_cells: int
    iterations: int
    converged: bool
    ms: float
    seen_through: float = 0.0

    @property
    def translation_m(self) -> np.ndarray:
        """(3,) translation of ``T_ref_from_cur``: where the current camera stands in the
        reference camera frame, metres."""
        return self.T_ref_from_cur[:3, 3].copy()

    @property
    def rotation_deg(self) -> float:
        """Angle of the rotation of ``T_ref_from_cur``, degrees."""
        return rotation_angle_deg(self.T_ref_from_cur[:3, :3])

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.T_ref_from_cur, np.eye(4)))

    def inverse(self) -> np.ndarray:
        """(4, 4) ``T_cur_from_ref``."""
        return invert(self.T_ref_from_cur)

    def not_at_station(self, params: RegistrationParams) -> str:
        """Why the camera is not at the station by the tolerance of ``params``; "" when it is."""
        moved = float(np.linalg.norm(self.translation_m))
        if self.fitness < params.min_fitness:
            return (f"registration fitness {self.fitness:.2f} < {params.min_fitness:.2f}: the "
                    f"views do not overlap enough")
        if moved > params.max_translation_m:
            return f"offset {moved:.2f} m > {params.max_translation_m:.2f} m"
        if self.rotation_deg > params.max_rotation_deg:
            return f"rotation {self.rotation_deg:.1f} deg > {params.max_rotation_deg:.1f} deg"
        if self.seen_through > params.max_seen_through:
            return (f"{self.seen_through:.0%} of one view is seen through by the other (more "
                    f"than {params.max_seen_through:.0%}): another place, or a change too large "
                    f"to register against")
        return ""

    def to_dict(self) -> dict:
        """JSON-ready: the transform, translation (m) and roll/pitch/yaw (deg) of
        ``T_ref_from_cur`` in the camera optical frame, fitness, RMSE, weak directions, ms."""
        return {
            "T_ref_from_cur": [[round(float(v), 9) for v in row] for row in self.T_ref_from_cur],
            "translation_m": [round(float(v), 5) for v in self.translation_m],
            "rotation_deg": [round(float(v), 4)
                             for v in rotation_to_rpy_deg(self.T_ref_from_cur[:3, :3])],
            "fitness": round(self.fitness, 4),
            "rmse_m": round(self.rmse_m, 5),
            "seen_through": round(self.seen_through, 4),
            "weak_directions": list(self.weak),
            "n_pairs": self.n_pairs,
            "iterations": self.iterations,
            "converged": self.converged,
            "ms": round(self.ms, 3),
        }


def identity_registration(transform: np.ndarray | None = None) -> Registration:
    """A registration taken as given (registration switched off): ``transform`` (4, 4), the
    identity by default, with fitness 1."""
    T = np.eye(4) if transform is None else np.array(transform, dtype=np.float64)
    return Registration(T, 1.0, 0.0, (), np.ones(6), 0, 0, 0, True, 0.0)


# --------------------------------------------------------------------------- small geometry


def invert(T: np.ndarray) -> np.ndarray:
    """(4, 4) inverse of a rigid transform."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M, 3) float32 ``points`` mapped by the (4, 4) rigid transform ``T``."""
    p = np.asarray(points, dtype=np.float64)
    return (p @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation matrix ``R`` (3, 3), degrees."""
    c = (float(np.trace(R)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def rotation_to_rpy_deg(R: np.ndarray) -> np.ndarray:
    """(3,) roll, pitch, yaw in degrees of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (angles about
    the frame's x, y and z axes, the REP 103 convention)."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    yaw = math.atan2(float(R[1, 0]), float(R[0, 0]))
    return np.degrees([roll, pitch, yaw])


def rpy_deg_to_rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """(3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)``, angles in degrees."""
    r, p, y = (math.radians(a) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), \
        math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues: (3, 3) rotation of the rotation vector ``w`` (radians)."""
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


@numba.njit(cache=True, nogil=True)
def depth_sigma(z):
    """Axial depth noise of a Kinect-class sensor at depth ``z`` (m), metres: the noise of
    Nguyen et al. 2012, 0.0012 + 0.0019 (z - 0.4)^2, with the disparity quantisation step
    2.85e-3 z^2 (Khoshelham & Oude Elberink 2012) added as a uniform error (step / sqrt 12)."""
    noise = 0.0012 + 0.0019 * (z - 0.4) ** 2
    quant = 2.85e-3 / math.sqrt(12.0) * z * z
    return np.sqrt(noise * noise + quant * quant)


# --------------------------------------------------------------------------- kernels


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


@numba.njit(cache=True, nogil=True)
def _associate(cur_v, cur_n, ref_v, ref_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos,
               res, jac, zs):
    """Projective data association and point-to-plane residuals of one ICP step.

    Each current cell with a normal (``cur_v``, ``cur_n`` (h, w, 3)) is moved by (``rot``
    (3, 3), ``trans`` (3,)), projected with the level's intrinsics into the reference level and
    paired with the cell it lands on when that has a normal, the two points are within
    ``max_dist`` and the normals' cosine is at least ``min_cos``.  Fills, per pair k, ``res[k]``
    = n_ref . (p - q) (metres), ``jac[k]`` = (p x n_ref, n_ref) (derivative of the residual
    under a left perturbation (rotation vector, translation)) and ``zs[k]`` the depth of p in
    the reference frame.  Returns the number of pairs.

    (The body is written out, not split into a per-cell helper: numba's call of a helper
    returning a tuple made this loop five times slower.)
    """
    k = 0
    md2 = max_dist * max_dist
    h = ref_v.shape[0]
    w = ref_v.shape[1]
    for i in range(cur_v.shape[0]):
        for j in range(cur_v.shape[1]):
            nx0 = cur_n[i, j, 0]
            ny0 = cur_n[i, j, 1]
            nz0 = cur_n[i, j, 2]
            if nx0 == 0.0 and ny0 == 0.0 and nz0 == 0.0:
                continue
            x = cur_v[i, j, 0]
            y = cur_v[i, j, 1]
            z = cur_v[i, j, 2]
            px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
            py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
            pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
            if pz <= 0.0:
                continue
            u = int(math.floor(fx * px / pz + cx + 0.5))
            v = int(math.floor(fy * py / pz + cy + 0.5))
            if u < 0 or v < 0 or u >= w or v >= h:
                continue
            mx = ref_n[v, u, 0]
            my = ref_n[v, u, 1]
            mz = ref_n[v, u, 2]
            if mx == 0.0 and my == 0.0 and mz == 0.0:
                continue
            dx = px - ref_v[v, u, 0]
            dy = py - ref_v[v, u, 1]
            dz = pz - ref_v[v, u, 2]
            if dx * dx + dy * dy + dz * dz > md2:
                continue
            nx = rot[0, 0] * nx0 + rot[0, 1] * ny0 + rot[0, 2] * nz0
            ny = rot[1, 0] * nx0 + rot[1, 1] * ny0 + rot[1, 2] * nz0
            nz = rot[2, 0] * nx0 + rot[2, 1] * ny0 + rot[2, 2] * nz0
            if nx * mx + ny * my + nz * mz < min_cos:
                continue
            res[k] = mx * dx + my * dy + mz * dz
            jac[k, 0] = py * mz - pz * my
            jac[k, 1] = pz * mx - px * mz
            jac[k, 2] = px * my - py * mx
            jac[k, 3] = mx
            jac[k, 4] = my
            jac[k, 5] = mz
            zs[k] = pz
            k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _count_inliers(cur_v, cur_n, ref_v, ref_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos,
                   sigmas, res, jac, zs):
    """The pairs of :func:`_associate` (filling its scratch arrays ``res``, ``jac``, ``zs``)
    whose residual is within ``sigmas`` depth noise sigmas (:func:`depth_sigma`), counted."""
    n = _associate(cur_v, cur_n, ref_v, ref_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos,
                   res, jac, zs)
    k = 0
    for m in range(n):
        if abs(res[m]) <= sigmas * depth_sigma(zs[m]):
            k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _seen_through(cur_v, ref_v, rot, trans, fx, fy, cx, cy, margin_m, margin_per_m2):
    """Of the current cells (``cur_v`` (h, w, 3)) that, moved by (rot, trans), land in the
    reference image, how many the reference sees *through* (its reading there is farther than
    the point by more than ``margin_m + margin_per_m2 * z^2``), how many land on a reading
    (compared), and how many land on no reading (a hole).  Returns (through, compared,
    holes)."""
    through = 0
    compared = 0
    holes = 0
    for i in range(cur_v.shape[0]):
        for j in range(cur_v.shape[1]):
            x = cur_v[i, j, 0]
            y = cur_v[i, j, 1]
            z = cur_v[i, j, 2]
            if z <= 0.0:
                continue
            px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
            py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
            pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
            if pz <= 0.0:
                continue
            u = int(math.floor(fx * px / pz + cx + 0.5))
            v = int(math.floor(fy * py / pz + cy + 0.5))
            if u < 0 or v < 0 or u >= ref_v.shape[1] or v >= ref_v.shape[0]:
                continue
            rz = ref_v[v, u, 2]
            if rz <= 0.0:
                holes += 1
                continue
            compared += 1
            if rz > pz + margin_m + margin_per_m2 * pz * pz:
                through += 1
    return through, compared, holes


@numba.njit(cache=True, nogil=True)
def _cell_states(cur_v, cur_n, ref_v, ref_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos,
                 sigmas, margin_m, margin_per_m2):
    """What the reference says of each current cell (``cur_v``, ``cur_n`` (h, w, 3)) moved by
    (rot, trans) and projected into it: 2 (contradicts) when it sees through the cell (its
    reading farther by more than ``margin_m + margin_per_m2 * z^2``) or pairs it as
    :func:`_associate` does with a residual beyond ``sigmas`` depth-noise sigmas; 1 (fits)
    when it pairs it within them; 0 otherwise (outside its image, on no reading, hidden
    behind a nearer reading, or not paired).  Returns (h, w) int8."""
    h, w = cur_v.shape[0], cur_v.shape[1]
    out = np.zeros((h, w), dtype=np.int8)
    md2 = max_dist * max_dist
    for i in range(h):
        for j in range(w):
            x = cur_v[i, j, 0]
            y = cur_v[i, j, 1]
            z = cur_v[i, j, 2]
            if z <= 0.0:
                continue
            px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
            py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
            pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
            if pz <= 0.0:
                continue
            u = int(math.floor(fx * px / pz + cx + 0.5))
            v = int(math.floor(fy * py / pz + cy + 0.5))
            if u < 0 or v < 0 or u >= ref_v.shape[1] or v >= ref_v.shape[0]:
                continue
            rz = ref_v[v, u, 2]
            if rz <= 0.0:
                continue
            margin = margin_m + margin_per_m2 * pz * pz
            if rz > pz + margin:
                out[i, j] = 2
                continue
            if rz < pz - margin:
                continue
            nx0 = cur_n[i, j, 0]
            ny0 = cur_n[i, j, 1]
            nz0 = cur_n[i, j, 2]
            mx = ref_n[v, u, 0]
            my = ref_n[v, u, 1]
            mz = ref_n[v, u, 2]
            if (nx0 == 0.0 and ny0 == 0.0 and nz0 == 0.0) or (mx == 0.0 and my == 0.0
                                                                and mz == 0.0):
                continue
            dx = px - ref_v[v, u, 0]
            dy = py - ref_v[v, u, 1]
            dz = pz - ref_v[v, u, 2]
            if dx * dx + dy * dy + dz * dz > md2:
                continue
            nx = rot[0, 0] * nx0 + rot[0, 1] * ny0 + rot[0, 2] * nz0
            ny = rot[1, 0] * nx0 + rot[1, 1] * ny0 + rot[1, 2] * nz0
            nz = rot[2, 0] * nx0 + rot[2, 1] * ny0 + rot[2, 2] * nz0
            if nx * mx + ny * my + nz * mz < min_cos:
                continue
            if abs(mx * dx + my * dy + mz * dz) <= sigmas * depth_sigma(pz):
                out[i, j] = 1
            else:
                out[i, j] = 2
    return out


@numba.njit(cache=True, nogil=True)
def _pose_scores(cur_v, cur_n, ref_v, ref_n, rots, transs, fx, fy, cx, cy, max_dist, min_cos,
                 sigmas, margin_m, margin_per_m2, both_ways, hole_weight, res, jac, zs):
    """Scores of candidate poses ``T_ref_from_cur`` (``rots`` (n, 3, 3), ``transs`` (n, 3)
    metres): per pose, the inlier pairs of :func:`_count_inliers` (with ``both_ways`` those of
    the reference's cells moved into the current view too) minus the cells of either view the
    other sees through, minus ``hole_weight`` times the cells of either view that land on no
    reading of the other inside its image (:func:`_seen_through`, both ways).  A wrong slide
    along a room fits floor and walls (inliers) but puts surfaces where the other camera saw
    free space; a wrong turn on a table top puts the table where the other saw none.
    ``res``, ``jac``, ``zs``: scratch arrays of :func:`_associate`, one row per cell (the two
    views' levels are the same size).  Returns (n,) float64."""
    out = np.empty(rots.shape[0])
    back = np.empty(3)
    for m in range(rots.shape[0]):
        rot = rots[m]
        t = transs[m]
        rot_t = np.ascontiguousarray(rot.T)
        for a in range(3):
            back[a] = -(rot_t[a, 0] * t[0] + rot_t[a, 1] * t[1] + rot_t[a, 2] * t[2])
        inliers = _count_inliers(cur_v, cur_n, ref_v, ref_n, rot, t, fx, fy, cx, cy, max_dist,
                                 min_cos, sigmas, res, jac, zs)
        if both_ways:
            inliers += _count_inliers(ref_v, ref_n, cur_v, cur_n, rot_t, back, fx, fy, cx, cy,
                                      max_dist, min_cos, sigmas, res, jac, zs)
        through_cur, _, holes_cur = _seen_through(cur_v, ref_v, rot, t, fx, fy, cx, cy,
                                                  margin_m, margin_per_m2)
        through_ref, _, holes_ref = _seen_through(ref_v, cur_v, rot_t, back, fx, fy, cx, cy,
                                                  margin_m, margin_per_m2)
        out[m] = inliers - through_cur - through_ref - hole_weight * (holes_cur + holes_ref)
    return out


# --------------------------------------------------------------------------- the pyramid


@dataclasses.dataclass(frozen=True, eq=False)
class _Level:
    factor: int
    vertex: np.ndarray
    normal: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def n_normals(self) -> int:
        """Cells with a normal (the cells that can be paired)."""
        n = self.normal
        return int(np.count_nonzero((n[:, :, 0] != 0) | (n[:, :, 1] != 0) | (n[:, :, 2] != 0)))


def _levels(depth: np.ndarray, intrinsics: Intrinsics, params: RegistrationParams
            ) -> list[_Level]:
    """The pyramid, coarse to fine: the finest level from the image, each coarser one by
    merging 2 x 2 cells of the one below (the factors must double)."""
    min_mm = int(math.ceil(params.min_depth_m * 1000.0))
    max_mm = int(math.floor(params.max_depth_m * 1000.0))
    finest = int(params.levels[-1])
    vertex, count = _vertex_level(readonly_view(depth), finest, intrinsics.fx, intrinsics.fy,
                                  intrinsics.cx, intrinsics.cy, min_mm, max_mm, params.band_m,
                                  params.band_slope)
    out = []
    for f in reversed(params.levels):
        if f != finest:
            vertex, count = _merge_level(vertex, count, params.band_m,
                                         params.band_slope * f / intrinsics.fx)
        # a difference of two cells spans 2 f pixels; allow surfaces up to ~76 deg
        normal = _normal_map(vertex, 8.0 * f / intrinsics.fx)
        out.append(_Level(int(f), vertex, normal, intrinsics.fx / f, intrinsics.fy / f,
                          (intrinsics.cx + 0.5) / f - 0.5, (intrinsics.cy + 0.5) / f - 0.5))
    return out[::-1]


def _check_depth(name: str, depth: Any, intrinsics: Intrinsics) -> np.ndarray:
    if not isinstance(depth, np.ndarray) or depth.ndim != 2 or depth.dtype != np.uint16:
        raise InputError(f"{name} depth must be an (H, W) uint16 array of millimetres")
    if depth.shape != (intrinsics.height, intrinsics.width):
        raise InputError(f"{name} depth is {depth.shape[1]}x{depth.shape[0]} but the intrinsics "
                         f"are for {intrinsics.width}x{intrinsics.height}")
    return np.ascontiguousarray(depth)


@numba.njit(cache=True, nogil=True)
def _weighted_system(res, jac, zs, n, tukey_c, min_cut_m):
    """The robustly weighted 6x6 normal equations of the first ``n`` pairs (``res`` (N,) m,
    ``jac`` (N, 6), ``zs`` (N,) m, from :func:`_associate`).

    Weight of a pair: 1 / sigma(z)^2 (:func:`depth_sigma`) times Tukey's biweight of its
    normalised residual e = res / sigma(z), with constant ``tukey_c`` times the scale
    max(1.4826 median |e|, 0.5), and no narrower than ``min_cut_m`` metres.  Returns (A (6, 6)
    = J^T W J, b (6,) = J^T W r, the sum of the weights, radius: the root of the median squared
    depth, m)."""
    e = np.empty(n)
    inv_var = np.empty(n)
    z2 = np.empty(n)
    for k in range(n):
        sig = depth_sigma(zs[k])
        e[k] = abs(res[k]) / sig
        inv_var[k] = 1.0 / (sig * sig)
        z2[k] = zs[k] * zs[k]
    scale = max(1.4826 * np.median(e), 0.5)
    radius = math.sqrt(np.median(z2))
    cut = tukey_c * scale
    A = np.zeros((6, 6))
    b = np.zeros(6)
    wsum = 0.0
    for k in range(n):
        u = e[k] / max(cut, min_cut_m * math.sqrt(inv_var[k]))
        if u >= 1.0:
            continue
        wt = (1.0 - u * u) ** 2 * inv_var[k]
        wsum += wt
        for a in range(6):
            ja = jac[k, a] * wt
            b[a] += ja * res[k]
            for c in range(a, 6):
                A[a, c] += ja * jac[k, c]
    for a in range(6):
        for c in range(a):
            A[a, c] = A[c, a]
    return A, b, wsum, radius


def _solve(A: np.ndarray, b: np.ndarray, radius: float, wsum: float, weak_eigenvalue: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton step of the 6x6 system, not moving along weak directions.

    Rotations are scaled by ``radius`` (m) so all six are metres; eigenvalues per unit weight
    below ``weak_eigenvalue`` are weak.  Returns (step (6,) rotation vector then translation,
    eigenvalues (6,) ascending, eigenvectors (6, 6) as columns, scaled)."""
    s = np.array([radius, radius, radius, 1.0, 1.0, 1.0])
    As = A / np.outer(s, s)
    bs = b / s
    lam, vec = np.linalg.eigh(As)
    lam_n = lam / max(wsum, 1e-300)
    step_s = np.zeros(6)
    for i in range(6):
        if lam_n[i] >= weak_eigenvalue:
            step_s -= (vec[:, i] @ bs) / lam[i] * vec[:, i]
    return step_s / s, lam_n, vec


def _weak_names(lam_n: np.ndarray, vec: np.ndarray, weak_eigenvalue: float) -> tuple[str, ...]:
    names = []
    for i in range(6):
        if lam_n[i] < weak_eigenvalue:
            axis = AXES[int(np.argmax(np.abs(vec[:, i])))]
            if axis not in names:
                names.append(axis)
    return tuple(names)


def register_depth(reference: np.ndarray, current: np.ndarray, intrinsics: Intrinsics,
                   params: RegistrationParams = RegistrationParams(), *,
                   initial: np.ndarray | None = None, keep: dict | None = None) -> Registration:
    """Estimate ``T_ref_from_cur``, the rigid transform that maps the current camera frame
    into the reference camera frame, from the two depth images.

    Parameters
    ----------
    reference, current : (H, W) uint16 mm
        The reference's (fused) depth image and the current one, same intrinsics.
    intrinsics : hw.depth.Intrinsics
    params : RegistrationParams
    initial : (4, 4) float64, optional
        Starting estimate (identity by default: the robot believes it is at its station).
    keep : dict, optional
        Where the reference's pyramid is kept between calls (a station's reference, checked
        against many frames, builds it once): an epoch's ``derived``
        (robot_change.change.epoch.Epoch), which belongs to ``reference`` alone.

    Returns
    -------
    Registration
        With ``enabled=False``, ``initial`` (the identity by default) taken as it is, with
        fitness 1: for a camera bolted in place, or a transform from elsewhere.
    """
    if not isinstance(params, RegistrationParams):
        raise InputError(f"params must be a RegistrationParams, got {type(params).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise InputError(f"intrinsics must be a hw.depth.Intrinsics, got "
                         f"{type(intrinsics).__name__}")
    ref = _check_depth("reference", reference, intrinsics)
    cur = _check_depth("current", current, intrinsics)
    T = np.eye(4) if initial is None else np.array(initial, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError("initial must be a finite (4, 4) rigid transform")
    if not params.enabled:
        return identity_registration(T)
    t0 = time.perf_counter()
    key = ("registration_levels", intrinsics, params.levels, params.min_depth_m,
           params.max_depth_m, params.band_m, params.band_slope)
    ref_levels = keep.get(key) if keep is not None else None
    if ref_levels is None:
        ref_levels = _levels(ref, intrinsics, params)
        if keep is not None:
            keep[key] = ref_levels
    cur_levels = _levels(cur, intrinsics, params)
    min_cos = math.cos(math.radians(params.max_normal_angle_deg))
    iterations = 0
    converged = False
    lam_n = np.zeros(6)
    vec = np.eye(6)
    tracks: list[np.ndarray] = []  # estimates from the table-plane starts, to search_level
    planes: tuple[_TablePlane, _TablePlane] | None = None  # a table top's, when it is one
    for li, (rl, cl) in enumerate(zip(ref_levels, cur_levels)):
        pairs = _Pairs(cl)
        start = T
        T, n_it, converged, lam_n, vec, A = _icp_level(rl, cl, start, params, li, min_cos, pairs)
        iterations += n_it
        if li == 0 and params.wide_cut_m > 0:
            wide = _icp_level(rl, cl, start, params, li, min_cos, pairs, params.wide_cut_m)
            iterations += wide[1]
            scores = _score_poses(rl, cl, [T, wide[0]], params, min_cos, pairs)
            if scores[1] > scores[0]:  # the narrow cut wins ties
                T, n_it, converged, lam_n, vec, A = wide
        if li == 0 and (params.table_starts > 0 or params.trim_rounds > 0):
            planes = _table_planes(ref_levels, cur_levels, params)
            if planes is not None and params.table_starts > 0:
                tracks = _table_starts(ref_levels, cur_levels, planes, params)
        if tracks and li <= params.search_level:
            ends = [_icp_level(rl, cl, st, params, li, min_cos, pairs) for st in tracks]
            iterations += sum(e[1] for e in ends)
            tracks = [e[0] for e in ends]
        if li == params.search_level and params.search_reach_m > 0 and A is not None:
            moved = _weak_search(rl, cl, T, A, params, min_cos, pairs)
            if moved is not None:
                T, n_it, converged, lam_n, vec, _ = _icp_level(rl, cl, moved, params, li,
                                                               min_cos, pairs)
                iterations += n_it
        if tracks and li == params.search_level:
            # the table-plane tracks against the main one, on the score taken both ways
            scores = _score_poses(rl, cl, [T] + [e[0] for e in ends], params, min_cos, pairs,
                                  True, params.table_hole_weight)
            best = int(np.argmax(scores))  # the first of equal scores: the main track
            if best > 0:
                T, n_it, converged, lam_n, vec, _ = ends[best - 1]
            tracks = []
    if planes is not None:
        for _round in range(params.trim_rounds):
            for li in range(params.search_level, len(ref_levels)):
                rl, cl = _without_changed_objects(ref_levels[li], cur_levels[li], planes, T,
                                                  params, li, min_cos)
                T, n_it, converged, lam_n, vec, _ = _icp_level(rl, cl, T, params, li, min_cos,
                                                               _Pairs(cl))
                iterations += n_it
    fitness, rmse, n_pairs, n_cells = _fitness(ref_levels[-1], cur_levels[-1], T, params,
                                               min_cos, pairs)
    through = _contradiction(ref_levels[-1], cur_levels[-1], T, params)
    weak = _weak_names(lam_n, vec, params.weak_eigenvalue)
    if planes is not None and _table_pose_weak(ref_levels[-1], cur_levels[-1], T, planes, weak,
                                               params, min_cos):
        weak = tuple(dict.fromkeys(weak + _in_plane_names(planes[1])))
    return Registration(T, fitness, rmse, weak,
                        lam_n, n_pairs, n_cells, iterations, converged,
                        (time.perf_counter() - t0) * 1e3, through)


def _contradiction(rl: _Level, cl: _Level, T: np.ndarray, params: RegistrationParams) -> float:
    """The larger of the fractions of each view that the other sees through (finest level)."""
    out = 0.0
    for own, other, M in ((cl, rl, T), (rl, cl, invert(T))):
        through, compared, _ = _seen_through(own.vertex, other.vertex, M[:3, :3].copy(),
                                             M[:3, 3].copy(), other.fx, other.fy, other.cx,
                                             other.cy, params.seen_through_margin_m,
                                             params.seen_through_margin_per_m2)
        out = max(out, through / compared if compared else 0.0)
    return out


class _Pairs:
    """Scratch arrays for the pairs of one level (one row per current cell)."""

    def __init__(self, level: _Level) -> None:
        size = level.vertex.shape[0] * level.vertex.shape[1]
        self.res = np.empty(size)
        self.jac = np.empty((size, 6))
        self.zs = np.empty(size)

    def associate(self, rl: _Level, cl: _Level, T: np.ndarray, max_dist: float, min_cos: float
                  ) -> int:
        return _associate(cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3].copy(),
                          T[:3, 3].copy(), rl.fx, rl.fy, rl.cx, rl.cy, max_dist, min_cos,
                          self.res, self.jac, self.zs)

    def count_inliers(self, rl: _Level, cl: _Level, T: np.ndarray, max_dist: float,
                      min_cos: float, sigmas: float) -> int:
        return _count_inliers(cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3].copy(),
                              T[:3, 3].copy(), rl.fx, rl.fy, rl.cx, rl.cy, max_dist, min_cos,
                              sigmas, self.res, self.jac, self.zs)

    def inliers(self, n: int, sigmas: float) -> np.ndarray:
        """(n,) bool: pairs whose residual is within ``sigmas`` depth-noise sigmas."""
        return np.abs(self.res[:n]) <= sigmas * depth_sigma(self.zs[:n])


def _icp_level(rl: _Level, cl: _Level, T: np.ndarray, params: RegistrationParams, li: int,
               min_cos: float, pairs: _Pairs, min_cut_m: float = 0.0):
    """Gauss-Newton iterations of one level from ``T`` (Tukey's cut at least ``min_cut_m``
    metres); returns (T, iterations, converged, eigenvalues, eigenvectors, last normal matrix
    or None)."""
    lam_n, vec, A = np.zeros(6), np.eye(6), None
    n_it = 0
    for _ in range(params.iterations[li]):
        n = pairs.associate(rl, cl, T, params.max_distance_m[li], min_cos)
        if n < 6:
            break
        A, b, wsum, radius = _weighted_system(pairs.res, pairs.jac, pairs.zs, n,
                                              params.tukey_c, min_cut_m)
        step, lam_n, vec = _solve(A, b, radius, wsum, params.weak_eigenvalue)
        # a trust region: no step moves a point by more than half the pairing distance (a
        # first step from many wrong pairs must not throw the estimate out of the basin)
        length = math.sqrt(float((step[:3] ** 2).sum()) * radius * radius
                           + float((step[3:] ** 2).sum()))
        cap = 0.5 * params.max_distance_m[li]
        if length > cap:
            step = step * (cap / length)
        n_it += 1
        inc = np.eye(4)
        inc[:3, :3] = _exp_so3(step[:3])
        inc[:3, 3] = step[3:]
        T = inc @ T
        if math.sqrt(float((step[:3] ** 2).sum()) * radius * radius
                     + float((step[3:] ** 2).sum())) < params.tol_m:
            return T, n_it, True, lam_n, vec, A
    return T, n_it, False, lam_n, vec, A


def _score_poses(rl: _Level, cl: _Level, poses: list[np.ndarray], params: RegistrationParams,
                 min_cos: float, pairs: _Pairs, both_ways: bool = False,
                 hole_weight: float = 0.0) -> np.ndarray:
    """(n,) :func:`_pose_scores` of the (4, 4) ``poses`` at one level: inliers within one
    search step (of the current's cells; ``both_ways``: of both views' cells), less the cells
    either view sees through and ``hole_weight`` times those landing on no reading."""
    rots = np.array([T[:3, :3] for T in poses])
    transs = np.array([T[:3, 3] for T in poses])
    return _pose_scores(cl.vertex, cl.normal, rl.vertex, rl.normal, rots, transs, rl.fx, rl.fy,
                        rl.cx, rl.cy, params.search_step_m, min_cos, params.inlier_sigmas,
                        params.seen_through_margin_m, params.seen_through_margin_per_m2,
                        bool(both_ways), float(hole_weight), pairs.res, pairs.jac, pairs.zs)


def _weak_search(rl: _Level, cl: _Level, T: np.ndarray, A: np.ndarray,
                 params: RegistrationParams, min_cos: float, pairs: _Pairs) -> np.ndarray | None:
    """The best-scoring (:func:`_score_poses`) of ``T`` moved along the least constrained
    directions of the normal matrix ``A`` (6, 6): translation offsets along the two weakest
    directions of its translation block, and screw motions along the two weakest directions
    of the whole, rotations scaled by the radius (root median squared depth) of the current
    level; None when ``T`` itself scores best."""
    _lam, vecs = np.linalg.eigh(A[3:, 3:])
    steps = np.arange(params.search_step_m, params.search_reach_m + 1e-9, params.search_step_m)
    steps = np.concatenate([-steps[::-1], steps])
    poses = [T]
    for d in (vecs[:, 0], vecs[:, 1]):
        for st in steps:
            c = T.copy()
            c[:3, 3] += st * d
            poses.append(c)
    if params.search_screw_steps:
        z = cl.vertex[:, :, 2]
        radius = math.sqrt(float(np.median(np.square(z[z > 0], dtype=np.float64))))
        s = np.array([radius, radius, radius, 1.0, 1.0, 1.0])
        _lam6, vecs6 = np.linalg.eigh(A / np.outer(s, s))
        screw = params.search_step_m * np.arange(1, params.search_screw_steps + 1)
        for d in (vecs6[:, 0] / s, vecs6[:, 1] / s):
            for st in np.concatenate([-screw[::-1], screw]):
                inc = np.eye(4)
                inc[:3, :3] = _exp_so3(st * d[:3])
                inc[:3, 3] = st * d[3:]
                poses.append(inc @ T)
    best = int(np.argmax(_score_poses(rl, cl, poses, params, min_cos, pairs)))
    return None if best == 0 else poses[best]  # the first of equal scores: T wins ties


# --------------------------------------------------------------------------- table-plane starts


def _dominant_plane(level: _Level, max_dist_m: float = _ON_PLANE_M, min_cos: float = 0.95,
                    n_seeds: int = 64) -> tuple[np.ndarray, float, float]:
    """The plane holding most cells of ``level``: each of ``n_seeds`` cells with a normal,
    evenly spaced in image order, proposes the plane through it along its normal; a cell
    supports a plane within ``max_dist_m`` metres of it with a normal within acos(min_cos).
    The winner is refitted to its supporters (least squares).  Returns (n (3,) unit normal,
    d m, fraction of the cells with a normal supporting it), n . p + d = 0 on the plane and
    d >= 0 (the camera on the positive side); fraction 0 when there are too few cells."""
    v = level.vertex.reshape(-1, 3)
    nm = level.normal.reshape(-1, 3)
    ok = (nm[:, 0] != 0) | (nm[:, 1] != 0) | (nm[:, 2] != 0)
    p, q = v[ok], nm[ok]
    if len(p) < 3 * n_seeds:
        return np.array([0.0, 0.0, 1.0]), 0.0, 0.0
    seeds = np.linspace(0, len(p) - 1, n_seeds).astype(np.int64)
    sn = q[seeds]                                          # (S, 3)
    sd = -np.einsum("ij,ij->i", sn, p[seeds])              # (S,)
    support = (np.abs(p @ sn.T + sd) < max_dist_m) & (np.abs(q @ sn.T) > min_cos)  # (N, S)
    counts = support.sum(axis=0)
    best = int(np.argmax(counts))
    inl = p[support[:, best]]
    c = inl.mean(axis=0)
    _u, _s, vt = np.linalg.svd(inl - c, full_matrices=False)
    n = vt[2]
    d = -float(n @ c)
    if d < 0:
        n, d = -n, -d
    return n, d, float(counts[best]) / len(p)


def _plane_frame(n: np.ndarray, d: float) -> np.ndarray:
    """(4, 4) camera-from-plane transform of the plane n . p + d = 0 (``n`` (3,) unit, ``d``
    m >= 0): origin the camera's foot on the plane, z along ``n`` (towards the camera), x the
    camera's x projected onto the plane (its y when ``n`` is along x)."""
    ex = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(ex) < 1e-6:  # a plane facing the camera's x: use its y instead
        ex = np.array([0.0, 1.0, 0.0]) - n[1] * n
    ex /= np.linalg.norm(ex)
    F = np.eye(4)
    F[:3, 0] = ex
    F[:3, 1] = np.cross(n, ex)
    F[:3, 2] = n
    F[:3, 3] = -d * n
    return F


@numba.njit(cache=True, nogil=True)
def _plane_grid(vertex, rot, trans, cell_m, lo_x, lo_y, rows, cols, object_m, below_m):
    """Top-down occupancy of a vertex map ``vertex`` (h, w, 3) m on a plane: each cell with a
    reading (z > 0) is moved to plane coordinates q = rot @ p + trans (``rot`` (3, 3),
    ``trans`` (3,): plane-from-camera, q_z the height above the plane, m) and binned by
    (q_x - lo_x, q_y - lo_y) / cell_m into a (rows, cols) grid.  A grid cell is +1 when a
    reading in it stands more than ``object_m`` above the plane, else -1 when one lies within
    (-below_m, object_m] of it, else 0 (nothing seen there).  Returns (rows, cols) float64."""
    out = np.zeros((rows, cols))
    h, w = vertex.shape[0], vertex.shape[1]
    for i in range(h):
        for j in range(w):
            z = vertex[i, j, 2]
            if z <= 0.0:
                continue
            x, y = vertex[i, j, 0], vertex[i, j, 1]
            qx = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
            qy = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
            qz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
            if qz <= -below_m:
                continue
            r = int(math.floor((qx - lo_x) / cell_m))
            c = int(math.floor((qy - lo_y) / cell_m))
            if r < 0 or c < 0 or r >= rows or c >= cols:
                continue
            if qz > object_m:
                out[r, c] = 1.0
            elif out[r, c] == 0.0:
                out[r, c] = -1.0
    return out


def _parabola_peak(before: float, after: float, at: float) -> float:
    """Offset (cells, within +-0.5 for a peak) of the vertex of the parabola through three
    equally spaced samples with ``at`` in the middle; 0 unless it opens downwards."""
    den = before - 2.0 * at + after
    return 0.5 * (before - after) / den if den < 0 else 0.0


@dataclasses.dataclass(frozen=True, eq=False)
class _TablePlane:
    """A view's table plane: ``frame`` (4, 4) camera-from-plane (:func:`_plane_frame`), ``lo``,
    ``hi`` (2,) the 2-98 % extent of the cells on it in the plane's x and y, metres."""

    frame: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def heights(self, vertex: np.ndarray) -> np.ndarray:
        """(h, w) height above the plane (towards the camera) of each point of ``vertex``
        (h, w, 3), metres."""
        n = self.frame[:3, 2]
        return vertex @ n - float(n @ self.frame[:3, 3])


def _table_planes(ref_levels: list[_Level], cur_levels: list[_Level],
                  params: RegistrationParams) -> tuple[_TablePlane, _TablePlane] | None:
    """The (reference, current) table planes when the views are of a table top, else None.
    Each view's dominant plane (:func:`_dominant_plane`, coarsest level) must have its
    supporters (2-98 %) span no more than ``table_max_extent_m`` in either plane direction (a
    room's floor is larger).  Whether the station is a table top is the reference's to say:
    its plane must hold ``table_plane_fraction`` of its cells.  The current's plane need only
    be that table seen again, its normal within ``max_rotation_deg`` of the reference's: a
    revisit displaced sideways sees less of the table and more of what lies beyond it."""
    planes = []
    for level in (ref_levels[0], cur_levels[0]):
        n, d, frac = _dominant_plane(level)
        if frac == 0.0 or (not planes and frac < params.table_plane_fraction):
            return None
        if planes and float(n @ planes[0].frame[:3, 2]) < math.cos(
                math.radians(params.max_rotation_deg)):
            return None  # not the reference's table
        F = _plane_frame(n, d)
        v = level.vertex.reshape(-1, 3)
        q = (v[v[:, 2] > 0] - F[:3, 3]) @ F[:3, :3]
        on = q[np.abs(q[:, 2]) < _ON_PLANE_M, :2]
        lo, hi = np.percentile(on, 2, axis=0), np.percentile(on, 98, axis=0)
        if float((hi - lo).max()) > params.table_max_extent_m:
            return None  # a floor, not a table top
        planes.append(_TablePlane(F, lo, hi))
    return planes[0], planes[1]


def _table_starts(ref_levels: list[_Level], cur_levels: list[_Level],
                  planes: tuple[_TablePlane, _TablePlane], params: RegistrationParams
                  ) -> list[np.ndarray]:
    """Up to ``params.table_starts`` (4, 4) starting estimates of ``T_ref_from_cur`` for a
    table top whose (reference, current) ``planes`` are :func:`_table_planes`'.  Each start
    puts the current plane on the reference's and moves it in the plane by a yaw about its
    normal and a shift: the peaks of the cross-correlation (FFT, cyclic, with a 0.25 m guard
    band round the reference's plane) of the two views' top-down grids (:func:`_plane_grid`,
    finest level, ``table_cell_m`` cells), one grid of the current per yaw, the best distinct
    (apart by > 2.5 table_yaw_step_deg or > 3 cells) of all yaws, best first."""
    Fr, lo, hi = planes[0].frame, planes[0].lo, planes[0].hi
    Fc = planes[1].frame
    rl, cl = ref_levels[-1], cur_levels[-1]
    cell = params.table_cell_m
    to_r = invert(Fr)
    margin = 0.25  # the cyclic correlation's guard band: more than any shift looked for
    lo = lo - margin
    rows, cols = (8 * int(math.ceil(e / cell / 8)) for e in hi + margin - lo)
    args = (cell, float(lo[0]), float(lo[1]), rows, cols, params.table_object_m, 0.03)
    G = np.fft.rfft2(_plane_grid(rl.vertex, to_r[:3, :3].copy(), to_r[:3, 3].copy(), *args))
    to_c = invert(Fc)
    n_yaw = int(math.floor(params.table_yaw_deg / params.table_yaw_step_deg + 1e-9))
    yaws = np.radians(params.table_yaw_step_deg * np.arange(-n_yaw, n_yaw + 1))
    k = params.table_starts
    peaks = []  # (score, yaw, shift_x, shift_y)
    for yaw in yaws:
        Rz = np.eye(4)
        Rz[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        M = Rz @ to_c
        cc = np.fft.irfft2(G * np.conj(np.fft.rfft2(_plane_grid(
            cl.vertex, M[:3, :3].copy(), M[:3, 3].copy(), *args))), s=(rows, cols))
        flat = cc.ravel()
        for f in np.argpartition(flat, -k)[-k:]:
            r, c = divmod(int(f), cols)
            # sub-cell peak: a parabola through the neighbours along each axis
            dr_ = _parabola_peak(cc[(r - 1) % rows, c], cc[(r + 1) % rows, c], cc[r, c])
            dc_ = _parabola_peak(cc[r, (c - 1) % cols], cc[r, (c + 1) % cols], cc[r, c])
            sr = r - rows if r > rows // 2 else r
            sc = c - cols if c > cols // 2 else c
            peaks.append((float(flat[f]), float(yaw), (sr + dr_) * cell, (sc + dc_) * cell))
    peaks.sort(key=lambda t: -t[0])
    chosen: list[tuple[float, float, float, float]] = []
    for pk in peaks:
        if all(abs(pk[1] - o[1]) > math.radians(2.5 * params.table_yaw_step_deg)
               or math.hypot(pk[2] - o[2], pk[3] - o[3]) > 3 * cell for o in chosen):
            chosen.append(pk)
            if len(chosen) == k:
                break
    out = []
    for _score, yaw, sx, sy in chosen:
        M = np.eye(4)
        M[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        M[0, 3], M[1, 3] = sx, sy
        out.append(Fr @ M @ to_c)
    return out


# --------------------------------------------------------------------------- trimming the change


def _object_states(own: _Level, other: _Level, M: np.ndarray, plane: _TablePlane,
                   params: RegistrationParams, max_dist: float, min_cos: float
                   ) -> tuple[np.ndarray, int, np.ndarray]:
    """The objects of ``own`` on its table ``plane`` and what ``other`` says of each cell,
    seen with ``M`` (4, 4) other-from-own: (labels (h, w) int, 0 off any object; the number
    of objects; :func:`_cell_states` (h, w) int8).  An object is a 4-connected group of cells
    standing more than ``table_object_m`` above ``plane``."""
    objects, n = ndimage.label((own.vertex[:, :, 2] > 0)
                               & (plane.heights(own.vertex) > params.table_object_m))
    states = _cell_states(own.vertex, own.normal, other.vertex, other.normal, M[:3, :3].copy(),
                          M[:3, 3].copy(), other.fx, other.fy, other.cx, other.cy, max_dist,
                          min_cos, params.inlier_sigmas, params.seen_through_margin_m,
                          params.seen_through_margin_per_m2)
    return objects, n, states


def _static_object_share(rl: _Level, cl: _Level, T: np.ndarray,
                         planes: tuple[_TablePlane, _TablePlane], params: RegistrationParams,
                         min_cos: float) -> float:
    """Of the object cells of both views (reference ``rl``, current ``cl``, one level; their
    table ``planes``), the share that fit the other view at ``T`` (T_ref_from_cur): near 0
    when no object stayed put, 1 on a table where nothing changed.  1 when there is no object
    (a bare table: its weak directions are the normal equations')."""
    fit = total = 0
    for own, other, M, plane in ((rl, cl, invert(T), planes[0]), (cl, rl, T, planes[1])):
        objects, _n, states = _object_states(own, other, M, plane, params,
                                             params.max_distance_m[-1], min_cos)
        on = objects > 0
        total += int(np.count_nonzero(on))
        fit += int(np.count_nonzero(on & (states == 1)))
    return fit / total if total else 1.0


def _changed_objects(own: _Level, other: _Level, M: np.ndarray, plane: _TablePlane,
                     params: RegistrationParams, max_dist: float, min_cos: float) -> np.ndarray:
    """(h, w) bool: the cells of ``own`` in objects that changed, as seen from ``other`` with
    ``M`` (4, 4) other-from-own (:func:`_object_states`).  An object changed when its cells
    that contradict ``other`` are more than ``trim_conflict_share`` of those that contradict
    or fit (and at least 2)."""
    objects, n, states = _object_states(own, other, M, plane, params, max_dist, min_cos)
    out = np.zeros(objects.shape, dtype=bool)
    if n == 0:
        return out
    counts = np.bincount((3 * objects + states).ravel(), minlength=3 * (n + 1)).reshape(-1, 3)
    fits, contradicts = counts[:, 1], counts[:, 2]
    changed = (contradicts > params.trim_conflict_share * (fits + contradicts)) & \
        (contradicts >= 2)
    changed[0] = False  # not an object: the table, and cells with no reading
    return changed[objects]


def _without_changed_objects(rl: _Level, cl: _Level, planes: tuple[_TablePlane, _TablePlane],
                             T: np.ndarray, params: RegistrationParams, li: int, min_cos: float
                             ) -> tuple[_Level, _Level]:
    """The two views of level ``li`` (reference, current) with the normals of their changed
    objects' cells (:func:`_changed_objects`, judged at ``T``) set to zero, so ICP pairs
    only the table and the objects that stayed put."""
    out = []
    for own, other, M, plane in ((rl, cl, invert(T), planes[0]), (cl, rl, T, planes[1])):
        drop = _changed_objects(own, other, M, plane, params, params.max_distance_m[li],
                                min_cos)
        normal = own.normal.copy()
        normal[drop] = 0.0
        out.append(dataclasses.replace(own, normal=normal))
    return out[0], out[1]


def _table_holes(own: _Level, other: _Level, M: np.ndarray, plane: _TablePlane,
                 params: RegistrationParams) -> float:
    """Of the cells of ``own`` on its table ``plane`` (within ``_ON_PLANE_M``) that land in the
    image of ``other`` when moved by ``M`` (4, 4) other-from-own, the share that land on no
    reading there (:func:`_seen_through`'s holes)."""
    on = (own.vertex[:, :, 2] > 0) & (np.abs(plane.heights(own.vertex)) < _ON_PLANE_M)
    table = np.where(on[:, :, None], own.vertex, 0.0)
    _through, compared, holes = _seen_through(table, other.vertex, M[:3, :3].copy(),
                                              M[:3, 3].copy(), other.fx, other.fy, other.cx,
                                              other.cy, params.seen_through_margin_m,
                                              params.seen_through_margin_per_m2)
    return holes / (holes + compared) if holes + compared else 0.0


def _table_pose_weak(rl: _Level, cl: _Level, T: np.ndarray,
                     planes: tuple[_TablePlane, _TablePlane], weak: tuple[str, ...],
                     params: RegistrationParams, min_cos: float) -> bool:
    """Whether the estimate ``T`` (T_ref_from_cur) of a table top (finest levels ``rl``,
    ``cl``; their table ``planes``) is not to be trusted in the table's plane: one of the
    directions there is already ``weak`` by the normal equations (the three are coupled: a
    slide along the table is nearly a turn about a far axis, and the weakest direction mixes
    them), the two tables do not overlap (``table_outline_holes``), or no object stayed put
    (``table_static_share``)."""
    if any(name in weak for name in _in_plane_names(planes[1])):
        return True
    if params.table_outline_holes > 0 and min(
            _table_holes(rl, cl, invert(T), planes[0], params),
            _table_holes(cl, rl, T, planes[1], params)) > params.table_outline_holes:
        return True
    return params.table_static_share > 0 and _static_object_share(
        rl, cl, T, planes, params, min_cos) < params.table_static_share


def _in_plane_names(plane: _TablePlane) -> tuple[str, ...]:
    """The :data:`AXES` names nearest to the motions that keep a view on its table ``plane``:
    the slides along the plane's two axes and the turn about its normal (camera frame)."""
    F = plane.frame
    names = [AXES[3 + int(np.argmax(np.abs(F[:3, k])))] for k in (0, 1)]
    names.append(AXES[int(np.argmax(np.abs(F[:3, 2])))])
    return tuple(dict.fromkeys(names))


def _fitness(rl: _Level, cl: _Level, T: np.ndarray, params: RegistrationParams, min_cos: float,
             pairs: _Pairs) -> tuple[float, float, int, int]:
    """(fitness, rmse_m, inlier pairs, current cells with a normal) at the finest level
    (``pairs``: that level's scratch arrays)."""
    n_cells = cl.n_normals
    if n_cells == 0:
        return 0.0, 0.0, 0, 0
    n = pairs.associate(rl, cl, T, params.max_distance_m[-1], min_cos)
    inl = pairs.inliers(n, params.inlier_sigmas)
    k = int(np.count_nonzero(inl))
    rmse = math.sqrt(float(np.square(pairs.res[:n][inl]).mean())) if k else 0.0
    return k / n_cells, rmse, k, n_cells
