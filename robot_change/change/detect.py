"""Change detection: what appeared and what disappeared between a reference scene and now.

ALGORITHM.md section 3, as we built and measured it (docs/algorithm.md, "Change detection";
numbers in docs/evaluation.md).  For what appeared (current points):

1. **Free-space check** against the reference depth image: a current point is a candidate only
   if the reference saw *through* it at the majority of its pixels -- its nearest reading
   within a few pixels (pose tolerance) is farther by a depth-dependent margin; where it has no
   reading, the farthest reading around a shadow or dropout stands in; with none at all,
   "no reading" counts as seen through.
2. **Novelty components.**  The reference mixture is held fixed (means, covariances and
   relative weights) as the background model of the current cloud; current points it explains
   poorly (log-density below a low quantile of the reference's own points) or that the
   reference saw through seed new free components, one per connected group on the voxel grid,
   and EM fits them (:func:`robot_change.mixture.model.fit_mixture` with ``fixed=`` and
   ``fix_weights=True``).
3. **Greedy EMD** (reference -> current) over the novelty components, with an explicit
   acceptance rule on its trajectory.  Computed and reported always; it decides only with
   ``greedy=True`` (off by default: measured to lose real changes, docs/evaluation.md).
4. **Segmentation**: a point is changed when the posterior mass of the change components at it
   exceeds ``posterior_threshold`` (0.5) and it passed the free-space check.
5. **Regions**: connected components on the voxel grid (26-neighbourhood of voxel keys),
   regions below ``min_region_points`` dropped.

The mirror (disappeared: reference points) runs the same steps with the roles swapped: the
reference cloud against the current's mixture held fixed, the free-space check against the
current depth image.

Each ingredient can be switched off (:class:`ChangeParams`) so it can be measured.  The
baselines (the plain method, the nearest-neighbour threshold, the geometric check) are
:func:`detect_plain`, :func:`detect_nn_threshold` and :func:`detect_geometric`.

Numeric module: arrays in, arrays out; no I/O, no logging, no global state.  Kernels are
``@njit(cache=True, nogil=True)`` with NumPy twins in ``tests/test_change.py``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any, TypeAlias

import numba
import numpy as np
from scipy.spatial import cKDTree

from hw.depth import Intrinsics
from robot_change import validate
from robot_change.change import transport as emd_mod
from robot_change.change.mount import CameraMount
from robot_change.change.registration import (
    Registration,
    RegistrationParams,
    identity_registration,
    register_depth,
    transform_points,
)
from robot_change.change.scene import (
    COMPARED_CLOUD_FIELDS,
    SceneModel,
    check_compatible,
)
from robot_change.cloud.chain import CloudParams, clean_cloud
from robot_change.cloud.filters import KEY_BITS
from robot_change.errors import EmptySceneError, InputError, SceneMismatchError
from robot_change.mixture.model import Mixture, component_of, fit_mixture

#: What a comparison takes as the reference, and as now (a depth array: (H, W) uint16 mm).
Reference: TypeAlias = "SceneModel | Epoch"
Current: TypeAlias = "SceneModel | Epoch | np.ndarray"

__all__ = [
    "ChangeParams",
    "ChangeSet",
    "Epoch",
    "GreedyTrace",
    "Region",
    "accept_trajectory",
    "detect_changes",
    "detect_geometric",
    "detect_nn_threshold",
    "detect_plain",
    "epoch_from_depth",
    "free_space_votes",
    "group_regions",
    "label_voxel_components",
]

METHODS = ("novelty", "plain", "geometric", "nn")
#: What a check found: something changed, nothing changed, or the camera is not where the
#: reference was taken (registration failed or the offset is beyond the station tolerance).
OUTCOMES = ("changed", "no_change", "not_at_station")
GROUND_DISTANCES = ("euclidean", "wasserstein2")
NOVELTY_SEEDS = ("density", "density+free_space")


# --------------------------------------------------------------------------- parameters

_num = functools.partial(validate.number, "ChangeParams")
_int = functools.partial(validate.whole, "ChangeParams")
_bool = functools.partial(validate.flag, "ChangeParams")
_choice = functools.partial(validate.choice, "ChangeParams")


@dataclasses.dataclass(frozen=True)
class ChangeParams:
    """Parameters of :func:`detect_changes`, validated on construction (:class:`InputError`
    naming the field, its value and what is allowed).

    Every ingredient can be switched so it can be measured (docs/evaluation.md has the
    numbers behind each default).
    """

    # --- the mixture part ------------------------------------------------------------------
    # True: novelty components over the other epoch's mixture held fixed (ours).  False: the
    # plain method, two independent fits and greedy EMD over all components.
    novelty: bool = True
    # Points below this quantile of the fixed mixture's log-density on its own cloud seed the
    # novelty components.
    novelty_quantile: float = 0.01
    # Which points seed the novelty components: "density" (log-density below the quantile) or
    # "density+free_space" (those, and the points the other epoch's depth image sees through).
    novelty_seed: str = "density+free_space"
    # Fixed components keep their relative weights in the novelty fit (only their total mass
    # is re-estimated), so the EMD of an unchanged view is ~0 instead of the reweighting noise.
    novelty_fix_weights: bool = True
    # True: MDL may split the seeded novelty components further (split-EM over the free
    # components); False: EM of the seeded components only (one component per connected
    # group of novel points).  Measured: F1 0.965 vs 0.964 (dev, single frame), 0.939 vs 0.932
    # (real), ~20 ms less per direction; so False.
    novelty_split: bool = False
    # EM tolerance of the novelty fit (change of mean log-likelihood per point; the seeds
    # start at their groups' moments, so EM has little to do).  1e-2 instead of
    # fit_mixture's 1e-3: the same F1 on the dev scenes and the real pairs, the two novelty
    # fits 48 -> 16 ms.
    novelty_tol: float = 1e-2
    # The current's own mixture for the mirror (reference cloud fitted with it held fixed),
    # when the current comes as a depth image without one: "fit" (split-EM from K = 1, as a
    # reference is built) or "from_reference" (EM from the reference mixture, all components
    # free, no splits: a removed object's component moves away or dies; ~5x faster: 15-25 ms
    # instead of 80-110 ms, same F1 to 0.001 on the dev scenes).
    current_mixture: str = "from_reference"
    # Most novelty components on top of the fixed ones (bounds K = K_ref + this).
    max_novelty_components: int = 8
    # Ground distance between components for the EMD: "euclidean" (between means) or
    # "wasserstein2" (closed-form 2-Wasserstein between the Gaussians: shape counts).
    ground_distance: str = "wasserstein2"
    # True: greedy EMD (the paper's selection) decides which novelty components are changes,
    # by the acceptance rule below.  False: every novelty component is a candidate and the
    # free-space check decides point by point; the greedy trajectory is still computed and
    # reported.  Measured (docs/evaluation.md): on the table-top pairs the greedy loop stops
    # before the novelty components of objects that moved a few cm (their removal does not
    # lower the EMD), F1 0.61 with it vs 0.94 without; on the simulated dev scenes no
    # difference.  So off by default.
    greedy: bool = False
    # Acceptance rule on the greedy trajectory: a removal is accepted while its EMD drop is at
    # least accept_min_drop_m (metres: drop ~ weight x distance) AND at least
    # accept_min_drop_rel x the starting EMD, and the component holds at least
    # min_region_points points (N w_k).  The first rejected step stops the loop.
    accept_min_drop_m: float = 0.0005
    accept_min_drop_rel: float = 0.02
    # Segmentation: posterior mass of the accepted components above this.
    posterior_threshold: float = 0.5
    # --- the geometric part -----------------------------------------------------------------
    # Free-space check against the other epoch's depth image.
    free_space: bool = True
    # Seen through = other depth > own depth + margin_m + margin_rel_per_m * z^2 (z in m; the
    # z^2 term follows the Kinect's axial noise), or no reading when no_reading_is_free.
    free_space_margin_m: float = 0.03
    free_space_margin_per_m2: float = 0.004
    free_space_no_reading_is_free: bool = True
    # The other image's nearest reading within this many pixels is compared (a camera back
    # at its station within a few pixels must not make static edges look seen through).
    free_space_pose_radius_px: int = 3
    # Where that window has no reading, the farthest reading within this many pixels stands
    # in (projector shadows and dropouts); 0 = the pixel alone.
    free_space_hole_radius_px: int = 5
    # A point passes when at least this fraction of its pixels are seen through.
    free_space_min_fraction: float = 0.5
    # Optional nearest-neighbour check: a changed point needs no point of the other epoch
    # within this distance (m); 0 = off.
    nn_check_m: float = 0.0
    # --- regions ----------------------------------------------------------------------------
    # Voxels are connected when their indices differ by at most this much per axis
    # (1 = the 26-neighbourhood).
    region_connectivity: int = 1
    # A region needs this many points (also the smallest group seeded as a novelty component)
    # and a box at least this long along its longest side (m); the daemon's wire parameters
    # min_region_points / min_region_extent_mm start from these.
    min_region_points: int = 12
    min_region_extent_m: float = 0.01
    # Run the mirror (what disappeared); False reports appearances only (the paper).
    disappeared: bool = True
    # Fewer points than this in either clean cloud raises EmptySceneError.
    min_cloud_points: int = 50
    # Seed of the mixture fits (subsets); same seed, same result.
    seed: int = 0
    # --- registration -----------------------------------------------------------------------
    # How the current view is registered to the reference before comparing (and the station
    # tolerance); RegistrationParams(enabled=False) compares in the shared pixel grid.
    registration: RegistrationParams = RegistrationParams()

    def __post_init__(self) -> None:
        if not isinstance(self.registration, RegistrationParams):
            raise InputError(f"ChangeParams.registration must be a RegistrationParams, got "
                             f"{type(self.registration).__name__}")
        _choice("novelty_seed", self.novelty_seed, NOVELTY_SEEDS)
        _choice("current_mixture", self.current_mixture, ("fit", "from_reference"))
        for name in ("novelty", "novelty_fix_weights", "novelty_split", "greedy", "free_space",
                     "free_space_no_reading_is_free", "disappeared"):
            _bool(name, getattr(self, name))
        _num("novelty_tol", self.novelty_tol, 0.0, 1.0, low_open=True)
        _num("novelty_quantile", self.novelty_quantile, 0.0, 0.5, low_open=True)
        _int("max_novelty_components", self.max_novelty_components, 1, 64)
        _choice("ground_distance", self.ground_distance, GROUND_DISTANCES)
        _num("accept_min_drop_m", self.accept_min_drop_m, 0.0, 100.0, unit=" metres")
        _num("accept_min_drop_rel", self.accept_min_drop_rel, 0.0, 1.0)
        _num("posterior_threshold", self.posterior_threshold, 0.0, 1.0, low_open=True)
        _num("free_space_margin_m", self.free_space_margin_m, 0.0, 10.0, unit=" metres")
        _num("free_space_margin_per_m2", self.free_space_margin_per_m2, 0.0, 1.0,
             unit=" per metre")
        _num("free_space_min_fraction", self.free_space_min_fraction, 0.0, 1.0, low_open=True)
        _num("nn_check_m", self.nn_check_m, 0.0, 10.0, unit=" metres")
        _int("free_space_pose_radius_px", self.free_space_pose_radius_px, 0, 50)
        _int("free_space_hole_radius_px", self.free_space_hole_radius_px, 0, 50)
        _int("region_connectivity", self.region_connectivity, 1, 3)
        _int("min_region_points", self.min_region_points, 1, 10**9)
        _num("min_region_extent_m", self.min_region_extent_m, 0.0, 10.0, unit=" metres")
        _int("min_cloud_points", self.min_cloud_points, 1, 10**9)
        _int("seed", self.seed, 0, 2**63 - 1)

    def replace(self, **changes: Any) -> ChangeParams:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)


# --------------------------------------------------------------------------- results


@dataclasses.dataclass(frozen=True)
class Region:
    """One connected changed region.

    ``kind``: ``"appeared"`` (points of the current cloud) or ``"disappeared"`` (points of the
    reference cloud).  ``centroid`` (3,) m, ``bbox_min``/``bbox_max`` (3,) m and ``extent``
    (3,) = max - min, camera optical frame.  ``n_points`` voxel points, ``n_pixels`` depth
    pixels behind them (in the current image for appeared, the reference image for
    disappeared).  ``components``: indices of the accepted change components (in
    :attr:`ChangeSet.appeared_mixture` / :attr:`ChangeSet.disappeared_mixture`) that carry the
    most posterior mass of the region's points, most first; empty for the methods without a
    mixture.  ``point_index``: rows of the region's points in that epoch's cloud.
    """

    kind: str
    centroid: np.ndarray
    extent: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    n_points: int
    n_pixels: int
    components: tuple[int, ...]
    point_index: np.ndarray = dataclasses.field(repr=False)

    def to_dict(self, mount: CameraMount | None = None) -> dict:
        """JSON-ready summary (no point indices); with ``mount``, ``"base"`` holds the
        centroid and the axis-aligned box in base_link (x forward, y left, z up, metres)."""
        out = {
            "kind": self.kind,
            "centroid_m": [round(float(v), 4) for v in self.centroid],
            "extent_m": [round(float(v), 4) for v in self.extent],
            "bbox_min_m": [round(float(v), 4) for v in self.bbox_min],
            "bbox_max_m": [round(float(v), 4) for v in self.bbox_max],
            "n_points": self.n_points,
            "n_pixels": self.n_pixels,
            "components": list(self.components),
        }
        if mount is not None:
            lo, hi = self.base_box(mount)
            out["base"] = {"centroid_m": [round(float(v), 4) for v in
                                          mount.to_base(self.centroid[None])[0]],
                           "extent_m": [round(float(v), 4) for v in hi - lo],
                           "bbox_min_m": [round(float(v), 4) for v in lo],
                           "bbox_max_m": [round(float(v), 4) for v in hi]}
        return out

    def base_box(self, mount: CameraMount) -> tuple[np.ndarray, np.ndarray]:
        """(min (3,), max (3,)) of the region's box in base_link, metres."""
        return mount.box_to_base(self.bbox_min, self.bbox_max)


@dataclasses.dataclass(frozen=True)
class GreedyTrace:
    """The greedy EMD trajectory of one direction and what the acceptance rule made of it.

    ``candidates``: indices (into the mixture searched) the greedy loop could remove;
    ``order``: the removal order it found; ``emd_after``: EMD before any removal, then after
    each (m + 1,); ``accepted``: how many leading removals were accepted; ``change``: the
    accepted component indices.
    """

    candidates: np.ndarray
    order: np.ndarray
    emd_after: np.ndarray
    accepted: int
    change: np.ndarray

    def to_dict(self) -> dict:
        return {"candidates": self.candidates.tolist(), "order": self.order.tolist(),
                "emd_after": [float(v) for v in self.emd_after], "accepted": self.accepted,
                "change": self.change.tolist()}


@dataclasses.dataclass(frozen=True, eq=False)
class ChangeSet:
    """The result of :func:`detect_changes` (and of the baselines).

    ``changed``: any region at all.  ``appeared``/``disappeared``: tuples of :class:`Region`.
    ``appeared_points`` (M, 3) float32 current-cloud points in appeared regions;
    ``disappeared_points`` (M', 3) float32 reference-cloud points in disappeared regions
    (camera optical frame, metres).  ``appeared_index``/``disappeared_index``: their rows in
    the current / reference cloud.  ``appeared_mask`` (H, W) bool over the current image and
    ``disappeared_mask`` over the reference image: the pixels of those points.
    ``appeared_mixture``: the mixture of the current cloud that was searched (reference
    components held fixed + novelty components; the current's own mixture for the plain
    method; None without a mixture); ``disappeared_mixture`` likewise for the reference cloud.
    ``k_reference``/``k_current``: K of the two epochs' own mixtures (0 when not fitted).
    ``greedy_appeared``/``greedy_disappeared``: :class:`GreedyTrace` or None.  ``method``:
    ``"novelty"``, ``"plain"``, ``"geometric"`` or ``"nn"``.  ``timings_ms``: per stage and
    ``detect_ms`` (the whole call).

    Frames: the current camera's optical frame (x right, y down, z forward, metres) for
    everything geometric: appeared points and regions are the current cloud's, disappeared
    points and regions are the reference cloud's mapped through the registration
    (``registration.inverse()``), so both say where things are relative to the camera now.
    ``outcome``: one of :data:`OUTCOMES`; with ``"not_at_station"`` nothing is reported
    (``changed`` False, no regions).  ``registration``: the :class:`Registration` used.
    ``unobserved_fraction``: of the two clouds' points, the fraction the other epoch's camera
    could not have seen (outside its image or range), neither appeared nor disappeared.
    ``not_at_station_reason``: why, for that outcome (else "").
    """

    changed: bool
    appeared: tuple[Region, ...]
    disappeared: tuple[Region, ...]
    appeared_points: np.ndarray
    disappeared_points: np.ndarray
    appeared_index: np.ndarray
    disappeared_index: np.ndarray
    appeared_mask: np.ndarray
    disappeared_mask: np.ndarray
    appeared_mixture: Mixture | None
    disappeared_mixture: Mixture | None
    k_reference: int
    k_current: int
    greedy_appeared: GreedyTrace | None
    greedy_disappeared: GreedyTrace | None
    method: str
    params: Any
    timings_ms: dict[str, float]
    outcome: str = "no_change"
    registration: Registration = dataclasses.field(default_factory=identity_registration)
    unobserved_fraction: float = 0.0
    not_at_station_reason: str = ""

    @property
    def regions(self) -> tuple[Region, ...]:
        """Appeared then disappeared regions."""
        return self.appeared + self.disappeared

    def summary(self, mount: CameraMount = CameraMount()) -> dict:
        """JSON-ready summary: outcome, registration (camera frames, and as the robot's offset
        from its station pose in base_link given the camera's ``mount``), regions (camera
        frame and base_link), K of both mixtures, greedy traces, timings."""
        return {
            "outcome": self.outcome,
            "changed": self.changed,
            "method": self.method,
            "registration": self.registration.to_dict(),
            "unobserved_fraction": round(self.unobserved_fraction, 4),
            "not_at_station_reason": self.not_at_station_reason,
            "mount": mount.to_dict(),
            "offset_base": mount.offset(self.registration).to_dict(),
            "regions": [r.to_dict(mount) for r in self.regions],
            "n_appeared_points": int(self.appeared_points.shape[0]),
            "n_disappeared_points": int(self.disappeared_points.shape[0]),
            "k_reference": self.k_reference,
            "k_current": self.k_current,
            "k_appeared_mixture": (self.appeared_mixture.n_components
                                   if self.appeared_mixture is not None else 0),
            "k_disappeared_mixture": (self.disappeared_mixture.n_components
                                      if self.disappeared_mixture is not None else 0),
            "greedy_appeared": (self.greedy_appeared.to_dict()
                                if self.greedy_appeared is not None else None),
            "greedy_disappeared": (self.greedy_disappeared.to_dict()
                                   if self.greedy_disappeared is not None else None),
            "timings_ms": {k: round(v, 3) for k, v in self.timings_ms.items()},
        }


# --------------------------------------------------------------------------- epochs


@dataclasses.dataclass(frozen=True, eq=False)
class Epoch:
    """What change detection needs of one epoch (a view of a SceneModel).

    ``depth`` (H, W) uint16 mm (fused for a reference), ``intrinsics``, the clean cloud
    ``points`` (M, 3) float32 with its voxel ``keys`` (M,) int64 and ``pixel_voxel`` (H, W)
    int32, ``leaf_m`` of its voxel grid, ``mixture`` (None until fitted), ``cloud_params``.
    """

    depth: np.ndarray
    intrinsics: Intrinsics
    points: np.ndarray
    keys: np.ndarray
    pixel_voxel: np.ndarray
    leaf_m: float
    mixture: Mixture | None
    cloud_params: CloudParams | None = None

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])


def epoch_from_depth(depth: np.ndarray, intrinsics: Intrinsics,
                     cloud_params: CloudParams = CloudParams(),
                     mixture: Mixture | None = None) -> Epoch:
    """Clean the depth image (:func:`robot_change.cloud.chain.clean_cloud`) into an :class:`Epoch`."""
    cloud = clean_cloud(depth, intrinsics, cloud_params)
    return Epoch(np.ascontiguousarray(depth), intrinsics, cloud.points, cloud.keys,
                 cloud.pixel_voxel, float(cloud_params.leaf_m), mixture, cloud_params)


def _as_epoch(obj: Any, name: str) -> Epoch:
    """An :class:`Epoch` from an Epoch or a SceneModel (duck-typed: ``depth``, ``intrinsics``,
    ``cloud`` or ``points``/``keys``/``pixel_voxel``, ``mixture``, ``params``)."""
    if isinstance(obj, Epoch):
        return obj
    try:
        depth = obj.depth
        intrinsics = obj.intrinsics
        cloud = getattr(obj, "cloud", None)
        src = cloud if cloud is not None else obj
        points, keys, pixel_voxel = src.points, src.keys, src.pixel_voxel
        params = getattr(obj, "params", None)
        cloud_params = getattr(params, "cloud", None) if params is not None else None
        if cloud_params is None:
            cloud_params = getattr(src, "params", None)
        leaf = float(cloud_params.leaf_m) if isinstance(cloud_params, CloudParams) else 0.02
        mixture = getattr(obj, "mixture", None)
    except AttributeError as exc:
        raise InputError(f"{name} must be a SceneModel (robot_change.change.scene) or an Epoch, got "
                         f"{type(obj).__name__} ({exc})") from None
    return Epoch(np.asarray(depth), intrinsics, np.asarray(points, dtype=np.float32),
                 np.asarray(keys, dtype=np.int64), np.asarray(pixel_voxel, dtype=np.int32),
                 leaf, mixture, cloud_params if isinstance(cloud_params, CloudParams) else None)


def _check_pair(ref: Epoch, cur: Epoch, params: ChangeParams) -> None:
    if ref.depth.shape != cur.depth.shape or ref.intrinsics != cur.intrinsics:
        _raise_mismatch(f"reference {ref.depth.shape[::-1]} {ref.intrinsics} and current "
                        f"{cur.depth.shape[::-1]} {cur.intrinsics} differ in image size or "
                        f"intrinsics; take both with the same camera mode, or rebuild the "
                        f"reference")
    if ref.cloud_params is not None and cur.cloud_params is not None:
        diff = [f"{n} {getattr(ref.cloud_params, n)!r} vs {getattr(cur.cloud_params, n)!r}"
                for n in COMPARED_CLOUD_FIELDS
                if getattr(ref.cloud_params, n) != getattr(cur.cloud_params, n)]
        if diff:
            _raise_mismatch(f"reference and current were cleaned with different CloudParams "
                            f"({'; '.join(diff)}); build the current with the reference's "
                            f"params (SceneModel.params.cloud)")
    for name, ep in (("reference", ref), ("current", cur)):
        if ep.n_points < params.min_cloud_points:
            raise EmptySceneError(
                f"the {name} cloud has {ep.n_points} points after cleaning (< min_cloud_points"
                f" = {params.min_cloud_points}) from {int(np.count_nonzero(ep.depth))} valid "
                f"depth pixels: the camera sees nothing to compare (covered, closer than its "
                f"minimum range, pointed at open space, or broken); treat it as a fault")


def _raise_mismatch(message: str) -> None:
    raise SceneMismatchError(message)


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True, nogil=True)
def _filter_pass(src, dst, radius, take_min, along_rows):
    """One 1-D pass of :func:`_window_filter` (min over readings > 0, or max)."""
    height, width = src.shape
    for r in range(height):
        for c in range(width):
            best = np.int64(65535) if take_min else np.int64(0)
            if along_rows:
                lo, hi = max(c - radius, 0), min(c + radius + 1, width)
            else:
                lo, hi = max(r - radius, 0), min(r + radius + 1, height)
            for t in range(lo, hi):
                d = np.int64(src[r, t]) if along_rows else np.int64(src[t, c])
                if take_min:
                    if d > 0 and d < best:
                        best = d
                elif d > best:
                    best = d
            if take_min and best == 65535:
                best = 0
            dst[r, c] = best


@numba.njit(cache=True, nogil=True)
def _window_filter(depth, radius, take_min):
    """Square-window min (``take_min``: readings > 0 only, 0 where the window has none) or
    max of a uint16 depth image, window (2 radius + 1)^2, separable."""
    tmp = np.zeros(depth.shape, dtype=np.uint16)
    out = np.zeros(depth.shape, dtype=np.uint16)
    _filter_pass(depth, tmp, radius, take_min, True)
    _filter_pass(tmp, out, radius, take_min, False)
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


@numba.njit(cache=True, nogil=True)
def _warp_kernel(own_depth, rot, trans, fx, fy, cx, cy, width, window, min_m, max_m):
    """Where each pixel of this epoch's depth image lands in the other epoch's image.

    ``own_depth`` (H, W) uint16 mm; (``rot`` (3, 3), ``trans`` (3,)) maps this camera's frame
    into the other's (same intrinsics, image ``width`` pixels wide).  Returns ``target`` (P,)
    int64, the flat index of the other image's pixel the reading projects to (-1 for no reading
    here; -2 when the other camera could not have seen it: behind it, outside its sensing
    ``window`` (row0, row1, col0, col1, inclusive), or outside its depth range
    ``min_m``..``max_m``) and ``z_other`` (P,) float64, its depth in the other frame (m).
    """
    h, w = own_depth.shape
    target = np.full(h * w, -1, dtype=np.int64)
    z_other = np.zeros(h * w)
    for r in range(h):
        for c in range(w):
            d = own_depth[r, c]
            if d == 0:
                continue
            p = r * w + c
            z = d * 0.001
            x = (c - cx) * z / fx
            y = (r - cy) * z / fy
            px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
            py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
            pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
            target[p] = -2
            if pz < min_m or pz > max_m:
                continue
            u = int(math.floor(fx * px / pz + cx + 0.5))
            v = int(math.floor(fy * py / pz + cy + 0.5))
            if v < window[0] or v > window[1] or u < window[2] or u > window[3]:
                continue
            target[p] = v * width + u
            z_other[p] = pz
    return target, z_other


@numba.njit(cache=True, nogil=True)
def _free_space_kernel(pixel_voxel, target, z_other, near_other, far_other, n_points, margin_m,
                       margin_per_m2, no_reading_is_free):
    """Per point: how many of its pixels the other image sees through, how many it has, and
    how many of them the other camera could not have seen.

    ``pixel_voxel`` (P,) int32 row of each pixel's point (-1 none); ``target`` (P,) and
    ``z_other`` (P,) from :func:`_warp_kernel`; ``near_other`` (P',) the other image's
    nearest reading in the pose window (0: none there), ``far_other`` (P',) its farthest
    reading in the hole window (0: none).  The other reading is ``near_other``, else
    ``far_other``; with neither, the pixel is seen through when ``no_reading_is_free``.  Seen
    through: reading > z + margin_m + margin_per_m2 * z^2 (metres, z = ``z_other``).
    """
    votes = np.zeros(n_points, dtype=np.int32)
    total = np.zeros(n_points, dtype=np.int32)
    unseen = np.zeros(n_points, dtype=np.int32)
    for p in range(pixel_voxel.shape[0]):
        v = pixel_voxel[p]
        if v < 0:
            continue
        total[v] += 1
        q = target[p]
        if q < 0:
            unseen[v] += 1
            continue
        d1 = near_other[q]
        if d1 == 0:
            d1 = far_other[q]
        if d1 == 0:
            if no_reading_is_free:
                votes[v] += 1
            continue
        z = z_other[p]
        if d1 * 0.001 > z + margin_m + margin_per_m2 * z * z:
            votes[v] += 1
    return votes, total, unseen


def free_space_votes(pixel_voxel: np.ndarray, own_depth: np.ndarray, other_depth: np.ndarray,
                     n_points: int, margin_m: float, margin_per_m2: float = 0.0,
                     pose_radius: int = 0, hole_radius: int = 0,
                     no_reading_is_free: bool = True, *,
                     intrinsics: Intrinsics | None = None,
                     other_from_own: np.ndarray | None = None,
                     depth_range_m: tuple[float, float] = (0.0, 65.535)
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Free-space evidence per point of one epoch against the other epoch's depth image.

    Each of the point's pixels (``pixel_voxel == v``) is back-projected with its own reading,
    moved into the other camera by ``other_from_own`` ((4, 4), the registration; identity when
    not given, and then the pixel is its own projection) and projected into the other image
    (same ``intrinsics``).  There the other epoch saw *through* the point when its reading is
    farther by more than ``margin_m + margin_per_m2 * z**2`` (z = the depth in the other
    frame, m).  The reading used is the *nearest* one of the other image within
    ``pose_radius`` pixels (a square window: a small residual pose error does not make static
    edges look seen through); where that window has no reading, the *farthest* reading within
    ``hole_radius`` pixels (projector shadows and dropouts border the surface behind them);
    with none there either, the pixel counts as seen through when ``no_reading_is_free``
    (open space beyond the sensor's range).  A pixel that lands behind the other camera,
    outside the part of its image it has readings in (:func:`sensing_window`) or outside
    ``depth_range_m`` was not observed by it.

    Returns
    -------
    votes, total, unseen : (n_points,) int32
        Pixels seen through, pixels, and pixels the other camera could not observe, per point.
    """
    if pixel_voxel.ndim != 2 or pixel_voxel.shape != own_depth.shape or \
            own_depth.shape != other_depth.shape:
        raise InputError(f"pixel_voxel {pixel_voxel.shape}, own depth {own_depth.shape} and "
                         f"other depth {other_depth.shape} must be the same (H, W)")
    for name, a in (("own_depth", own_depth), ("other_depth", other_depth)):
        if a.dtype != np.uint16:
            raise InputError(f"{name} must be uint16 millimetres, got {a.dtype}")
    height, width = own_depth.shape
    if intrinsics is None:
        intrinsics = Intrinsics(width, height, 525.0, 525.0, (width - 1) / 2, (height - 1) / 2)
    T = np.eye(4) if other_from_own is None else np.asarray(other_from_own, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError("other_from_own must be a finite (4, 4) rigid transform")
    own = np.ascontiguousarray(own_depth)
    if other_from_own is None:  # the pixel grid is shared: each pixel is its own projection
        target = np.where(own.ravel() > 0, np.arange(own.size), -1)
        z_other = own.ravel() * 0.001
    else:
        window = np.array(sensing_window(other_depth), dtype=np.int64)
        target, z_other = _warp_kernel(own, T[:3, :3].copy(), T[:3, 3].copy(), intrinsics.fx,
                                       intrinsics.fy, intrinsics.cx, intrinsics.cy, width,
                                       window, float(depth_range_m[0]),
                                       float(depth_range_m[1]))
    other = np.ascontiguousarray(other_depth)
    near = _window_filter(other, int(pose_radius), True) if pose_radius > 0 else other
    far = _window_filter(other, int(hole_radius), False) if hole_radius > 0 else other
    return _free_space_kernel(np.ascontiguousarray(pixel_voxel, dtype=np.int32).ravel(),
                              target, z_other, near.ravel(), far.ravel(), int(n_points),
                              float(margin_m), float(margin_per_m2), bool(no_reading_is_free))


_FIELD = (1 << KEY_BITS) - 1


@numba.njit(cache=True, nogil=True)
def _find(parent, i):
    root = i
    while parent[root] != root:
        root = parent[root]
    while parent[i] != root:  # path compression
        nxt = parent[i]
        parent[i] = root
        i = nxt
    return root


@numba.njit(cache=True, nogil=True)
def _components_kernel(keys, radius):
    """Connected components of voxels: ``keys`` (M,) int64 packed keys, sorted ascending and
    unique; voxels are neighbours when each index differs by at most ``radius``.  Returns
    (M,) int64 labels 0..C-1, numbered in order of each component's first voxel."""
    m = keys.shape[0]
    parent = np.arange(m)
    # the key's three fields (z, y, x from the top; the test treats them alike)
    shift_top = np.int64(1) << np.int64(2 * KEY_BITS)
    shift_mid = np.int64(1) << np.int64(KEY_BITS)
    for i in range(m):
        k = keys[i]
        it = (k >> np.int64(2 * KEY_BITS)) & _FIELD
        im = (k >> np.int64(KEY_BITS)) & _FIELD
        il = k & _FIELD
        for dt in range(-radius, radius + 1):
            for dm in range(-radius, radius + 1):
                for dl in range(-radius, radius + 1):
                    # each pair once: only neighbours with a larger key
                    if dt < 0 or (dt == 0 and (dm < 0 or (dm == 0 and dl <= 0))):
                        continue
                    jt = it + dt
                    jm = im + dm
                    jl = il + dl
                    if jt < 0 or jm < 0 or jl < 0 or jt > _FIELD or jm > _FIELD or \
                            jl > _FIELD:
                        continue
                    nk = jt * shift_top + jm * shift_mid + jl
                    j = np.searchsorted(keys, nk)
                    if j < m and keys[j] == nk:
                        a = _find(parent, i)
                        b = _find(parent, j)
                        if a != b:
                            if a < b:
                                parent[b] = a
                            else:
                                parent[a] = b
    labels = np.empty(m, dtype=np.int64)
    remap = np.full(m, -1, dtype=np.int64)
    count = 0
    for i in range(m):
        r = _find(parent, i)
        if remap[r] < 0:
            remap[r] = count
            count += 1
        labels[i] = remap[r]
    return labels


def label_voxel_components(keys: np.ndarray, radius: int = 1) -> np.ndarray:
    """Connected components of a set of voxels given by their packed keys.

    Parameters
    ----------
    keys : (M,) int64
        Packed voxel keys (:func:`robot_change.cloud.filters.pack_keys`), any order, no duplicates.
    radius : int
        Voxels whose indices differ by at most this on every axis are connected (1: the
        26-neighbourhood).

    Returns
    -------
    (M,) int64
        Component label of each key (same order as given), 0..C-1.
    """
    keys = np.asarray(keys, dtype=np.int64)
    if keys.ndim != 1:
        raise InputError(f"keys must be (M,) int64, got shape {keys.shape}")
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    if sk.size > 1 and (np.diff(sk) == 0).any():
        raise InputError("keys must be unique (one point per voxel)")
    labels_sorted = _components_kernel(np.ascontiguousarray(sk), int(radius))
    labels = np.empty_like(labels_sorted)
    labels[order] = labels_sorted
    return labels


# --------------------------------------------------------------------------- regions


def group_regions(kind: str, epoch: Epoch, changed: np.ndarray, params: ChangeParams,
                  posterior: np.ndarray | None = None,
                  change_components: np.ndarray | None = None) -> tuple[Region, ...]:
    """Group the changed points of ``epoch`` into :class:`Region` s (largest first).

    ``changed`` (M,) bool; ``posterior`` (M, K) responsibilities of the searched mixture and
    ``change_components`` the accepted components, to name each region's components.
    """
    idx = np.flatnonzero(changed)
    if idx.size == 0:
        return ()
    labels = label_voxel_components(epoch.keys[idx], params.region_connectivity)
    n_lab = int(labels.max()) + 1
    sizes = np.bincount(labels, minlength=n_lab)
    pix_count = np.bincount(epoch.pixel_voxel.ravel()[epoch.pixel_voxel.ravel() >= 0],
                            minlength=epoch.n_points)
    regions = []
    for lab in np.argsort(-sizes, kind="stable"):
        if sizes[lab] < params.min_region_points:
            break
        rows = idx[labels == lab]
        pts = epoch.points[rows].astype(np.float64)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        if float(np.max(hi - lo)) < params.min_region_extent_m:
            continue
        comps: tuple[int, ...] = ()
        if posterior is not None and change_components is not None and len(change_components):
            mass = posterior[rows][:, change_components].sum(axis=0)
            keep = np.argsort(-mass, kind="stable")
            comps = tuple(int(change_components[k]) for k in keep if mass[k] > 0.05 * len(rows))
        regions.append(Region(kind, pts.mean(axis=0), hi - lo, lo, hi, int(len(rows)),
                              int(pix_count[rows].sum()), comps, rows))
    return tuple(regions)


def _mask_of(epoch: Epoch, rows: np.ndarray) -> np.ndarray:
    sel = np.zeros(epoch.n_points + 1, dtype=bool)
    sel[rows] = True
    pv = epoch.pixel_voxel
    return sel[np.where(pv >= 0, pv, epoch.n_points)]


# --------------------------------------------------------------------------- EMD helpers


def _ground(ma: Mixture, mb: Mixture, kind: str) -> np.ndarray:
    if kind == "euclidean":
        return emd_mod.ground_distance(ma.means, mb.means, kind="euclidean")
    return emd_mod.ground_distance(ma.means, mb.means, ma.covariances, mb.covariances,
                                   kind="wasserstein2")


def accept_trajectory(order: np.ndarray, emd_after: np.ndarray, weights: np.ndarray,
                      n_points: int, params: ChangeParams) -> int:
    """How many leading removals of a greedy EMD trajectory the acceptance rule keeps.

    Step i (removing ``order[i]``) is accepted while ``emd_after[i] - emd_after[i + 1]`` is at
    least ``accept_min_drop_m`` and at least ``accept_min_drop_rel * emd_after[0]``, and the
    removed component holds at least ``min_region_points`` points (``n_points * w``); the
    first step that fails stops it.
    """
    d0 = float(emd_after[0]) if len(emd_after) else 0.0
    need = max(params.accept_min_drop_m, params.accept_min_drop_rel * d0)
    n_ok = 0
    for i, k in enumerate(order):
        drop = float(emd_after[i] - emd_after[i + 1])
        if drop < need or n_points * float(weights[k]) < params.min_region_points:
            break
        n_ok += 1
    return n_ok


def _greedy(fixed_mix: Mixture, var_mix: Mixture, candidates: np.ndarray, n_points: int,
            params: ChangeParams) -> GreedyTrace:
    cand_idx = np.flatnonzero(candidates)
    if cand_idx.size == 0:
        return GreedyTrace(cand_idx, np.zeros(0, np.int64),
                           np.array([np.nan]), 0, np.zeros(0, np.int64))
    cost = _ground(fixed_mix, var_mix, params.ground_distance)
    res = emd_mod.greedy_emd(fixed_mix.weights, var_mix.weights, cost, candidates,
                             int(cand_idx.size))
    order = np.asarray(res.order, dtype=np.int64)
    emd_after = np.asarray(res.emd_after, dtype=np.float64)
    if params.greedy:
        n_ok = accept_trajectory(order, emd_after, var_mix.weights, n_points, params)
        change = order[:n_ok]
    else:
        n_ok = int(order.size)
        change = cand_idx
    return GreedyTrace(cand_idx, order, emd_after, n_ok, np.sort(change))


# --------------------------------------------------------------------------- one direction


def _fit_own(ep: Epoch, params: ChangeParams) -> Mixture:
    return fit_mixture(ep.points, leaf=ep.leaf_m, seed=params.seed)


def _current_mixture(cur: Epoch, ref_mix: Mixture, params: ChangeParams) -> Mixture:
    """The current's mixture for the mirror when the current came without one."""
    if params.current_mixture == "fit":
        return _fit_own(cur, params)
    # EM from the reference mixture, every component free, no splits: the reference's
    # components follow the current cloud (a removed object's component moves or dies)
    return fit_mixture(cur.points, init=ref_mix, leaf=cur.leaf_m, seed=params.seed, split=False,
                       tol=params.novelty_tol)


def _seed_novelty(base_mix: Mixture, other: Epoch, novel: np.ndarray, params: ChangeParams):
    """``base_mix`` plus one free component per connected group (on the voxel grid) of novel
    points with at least ``min_region_points`` points, largest first, at most
    ``max_novelty_components``; returns (init Mixture, fixed mask (K_init,) bool: True for
    the components of ``base_mix``)."""
    k0 = base_mix.n_components
    idx = np.flatnonzero(novel)
    groups = []
    if idx.size:
        labels = label_voxel_components(other.keys[idx], params.region_connectivity)
        sizes = np.bincount(labels)
        for lab in np.argsort(-sizes, kind="stable")[:params.max_novelty_components]:
            if sizes[lab] < max(params.min_region_points, 4):
                break
            groups.append(idx[labels == lab])
    if not groups:
        return base_mix, np.ones(k0, dtype=bool)  # nothing to seed: every component fixed
    n = other.n_points
    reg = other.leaf_m ** 2 / 12.0
    w_new = np.array([len(g) / n for g in groups])
    means, covs = zip(*(component_of(other.points[g], reg) for g in groups))
    weights = np.concatenate([base_mix.weights * (1.0 - w_new.sum()), w_new])
    init = Mixture(weights / weights.sum(), np.vstack([base_mix.means, np.array(means)]),
                   np.concatenate([base_mix.covariances, np.array(covs)]))
    fixed = np.zeros(init.n_components, dtype=bool)
    fixed[:k0] = True
    return init, fixed


def _novelty_direction(kind, base: Epoch, other: Epoch, base_mix: Mixture, params: ChangeParams,
                       timings: dict, prefix: str, free: np.ndarray, observed: np.ndarray):
    """Changed points of ``other`` relative to ``base``: the mixture part.

    ``base_mix`` (fitted on ``base``) is held fixed as the background of ``other``'s cloud;
    novelty components for poorly explained points; greedy EMD base -> other over them.
    Returns (candidate mask (M,), searched mixture, posterior (M, K), trace).
    """
    t0 = time.perf_counter()
    # the quantile of the base's own log-densities, on a fixed stride subsample (<= 4000 pts)
    step = max(1, base.n_points // 4000)
    thr = np.quantile(base_mix.score_samples(base.points[::step]), params.novelty_quantile)
    log_dens = base_mix.score_samples(other.points)
    novel = log_dens < thr
    if params.novelty_seed == "density+free_space":
        novel |= free
    novel &= observed  # what the base's camera could not see is no evidence of novelty
    t1 = time.perf_counter()
    k0 = base_mix.n_components
    init, fixed = _seed_novelty(base_mix, other, novel, params)
    if isinstance(fixed, str) and params.novelty_fix_weights:
        # no group of novel points to seed: with the fixed components' weights held, EM has
        # nothing to estimate, so the searched mixture is the base mixture itself
        fitted = base_mix
    else:
        fitted = fit_mixture(other.points, init=init, fixed=fixed,
                             fix_weights=params.novelty_fix_weights, leaf=other.leaf_m,
                             seed=params.seed, split=params.novelty_split,
                             tol=params.novelty_tol,
                             max_components=k0 + params.max_novelty_components)
    t2 = time.perf_counter()
    candidates = np.zeros(fitted.n_components, dtype=bool)
    candidates[k0:] = True
    trace = _greedy(base_mix, fitted, candidates, other.n_points, params)
    t3 = time.perf_counter()
    # posteriors only where they can matter: with the free-space check on, a point it rejects
    # is never changed, so its posterior is not computed (left 0)
    rows = np.flatnonzero(free) if params.free_space else None
    post = _responsibilities(fitted, other.points, rows)
    if trace.change.size:
        mass = post[:, trace.change].sum(axis=1)
        cand = mass > params.posterior_threshold
    else:
        cand = np.zeros(other.n_points, dtype=bool)
    t4 = time.perf_counter()
    timings[f"{prefix}novelty_mask_ms"] = (t1 - t0) * 1e3
    timings[f"{prefix}novelty_fit_ms"] = (t2 - t1) * 1e3
    timings[f"{prefix}greedy_ms"] = (t3 - t2) * 1e3
    timings[f"{prefix}segment_ms"] = (t4 - t3) * 1e3
    return cand, fitted, post, trace


def _responsibilities(mix: Mixture, points: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """(M, K) posteriors; only ``rows`` filled when given (zeros elsewhere)."""
    if rows is None:
        return mix.responsibilities(points)
    post = np.zeros((points.shape[0], mix.n_components))
    if rows.size:
        post[rows] = mix.responsibilities(points[rows])
    return post


def _plain_direction(base_mix: Mixture, other: Epoch, other_mix: Mixture, params, timings,
                     prefix):
    t0 = time.perf_counter()
    candidates = np.ones(other_mix.n_components, dtype=bool)
    trace = _greedy(base_mix, other_mix, candidates, other.n_points, params)
    t1 = time.perf_counter()
    post = other_mix.responsibilities(other.points)
    if trace.change.size:
        cand = post[:, trace.change].sum(axis=1) > params.posterior_threshold
    else:
        cand = np.zeros(other.n_points, dtype=bool)
    timings[f"{prefix}greedy_ms"] = (t1 - t0) * 1e3
    timings[f"{prefix}segment_ms"] = (time.perf_counter() - t1) * 1e3
    return cand, other_mix, post, trace


def _free_mask(other: Epoch, base: Epoch, params: ChangeParams, base_from_other: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """(free, observed), (M,) bool each over ``other``'s points: the points ``base``'s depth
    image sees through, and those ``base``'s camera could see at all (the majority of their
    pixels land inside its image and depth range)."""
    cp = base.cloud_params or CloudParams()
    votes, total, unseen = free_space_votes(
        other.pixel_voxel, other.depth, base.depth, other.n_points, params.free_space_margin_m,
        params.free_space_margin_per_m2, params.free_space_pose_radius_px,
        params.free_space_hole_radius_px, params.free_space_no_reading_is_free,
        intrinsics=other.intrinsics, other_from_own=base_from_other,
        depth_range_m=(cp.min_depth_m, cp.max_depth_m))
    observed = (total > 0) & (2 * unseen < total)
    seen = total - unseen
    free = observed & (votes >= params.free_space_min_fraction * np.maximum(seen, 1))
    return free, observed


def _geometric_filters(other: Epoch, base: Epoch, cand: np.ndarray, params: ChangeParams,
                       timings: dict, prefix: str, free: np.ndarray, observed: np.ndarray
                       ) -> np.ndarray:
    """What the other camera could not see is never a change; then the free-space check
    (against ``base``'s depth image) and the optional NN check (``base.points`` are in
    ``other``'s frame)."""
    t0 = time.perf_counter()
    cand = cand & observed
    if params.free_space:
        cand = cand & free
    t1 = time.perf_counter()
    if params.nn_check_m > 0 and cand.any():
        rows = np.flatnonzero(cand)
        keep = np.zeros_like(cand)
        keep[rows[_nn_far(cKDTree(base.points), other.points[rows], params.nn_check_m)]] = True
        cand = keep
    timings[f"{prefix}free_space_ms"] = timings.get(f"{prefix}free_space_ms", 0.0) + \
        (t1 - t0) * 1e3
    timings[f"{prefix}nn_check_ms"] = (time.perf_counter() - t1) * 1e3
    return cand


# --------------------------------------------------------------------------- entry points


def _current_epoch(reference: Epoch, current: Any, intrinsics: Intrinsics | None,
                   timings: dict, reference_model: Any = None) -> Epoch:
    t0 = time.perf_counter()
    if isinstance(current, np.ndarray):
        if intrinsics is None:
            intrinsics = reference.intrinsics
        if not isinstance(intrinsics, Intrinsics):
            raise InputError(f"intrinsics must be a hw.depth.Intrinsics, got "
                             f"{type(intrinsics).__name__}")
        if current.ndim != 2 or current.dtype != np.uint16:
            raise InputError(f"current depth must be an (H, W) uint16 array of millimetres, got "
                             f"{current.dtype} of shape {current.shape}")
        if reference_model is not None:
            check_compatible(reference_model, (intrinsics, reference_model.params))
        if current.shape != (intrinsics.height, intrinsics.width):
            raise InputError(f"current depth is {current.shape[1]}x{current.shape[0]} but the "
                             f"intrinsics are for {intrinsics.width}x{intrinsics.height}")
        if current.shape != reference.depth.shape or intrinsics != reference.intrinsics:
            _raise_mismatch(f"current depth {current.shape[::-1]} with {intrinsics} does not "
                            f"match the reference's {reference.depth.shape[::-1]} "
                            f"{reference.intrinsics}; use the camera mode the reference was "
                            f"taken with, or rebuild the reference")
        cloud_params = reference.cloud_params or CloudParams(leaf_m=reference.leaf_m)
        ep = epoch_from_depth(current, intrinsics, cloud_params)
        timings["current_cloud_ms"] = (time.perf_counter() - t0) * 1e3
        return ep
    if intrinsics is not None:
        raise InputError("intrinsics= is only for a current depth array; a SceneModel "
                         "carries its own")
    return _as_epoch(current, "current")


def _scene_model(obj: Any) -> Any:
    return obj if isinstance(obj, SceneModel) else None


def _check_scene_models(reference: Any, current: Any) -> None:
    """scene.check_compatible for two SceneModels, when scene.py provides it."""
    if isinstance(reference, SceneModel) and isinstance(current, SceneModel):
        check_compatible(reference, current)


@dataclasses.dataclass(frozen=True, eq=False)
class _Direction:
    """One direction's result before regions: candidate mask (M,) bool, posteriors (M, K) of
    the searched mixture (or None), that mixture, its greedy trace, and the observed mask."""

    changed: np.ndarray
    posterior: np.ndarray | None
    mixture: Mixture | None
    trace: GreedyTrace | None
    observed: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class _Aligned:
    """The two epochs of a check in the current camera frame: ``ref`` with its points (and
    mixture) mapped through the registration, ``cur`` as it is; ``registration``; ``reason``
    why this is not the station ("" when it is); the free-space results (free, observed) of
    the current's points and, when the disappeared direction runs, of the reference's."""

    ref: Epoch
    cur: Epoch
    registration: Registration
    reason: str = ""
    free_cur: np.ndarray | None = None
    observed_cur: np.ndarray | None = None
    free_ref: np.ndarray | None = None
    observed_ref: np.ndarray | None = None

    @property
    def at_station(self) -> bool:
        return not self.reason


def _align(reference: Reference, current: Current, params: ChangeParams, intrinsics: Intrinsics | None,
           timings: dict, initial_pose: np.ndarray | None = None) -> _Aligned:
    """Checks, the current's clean cloud, registration and whether this is the station at all,
    the reference moved into the current camera frame, the free-space checks both ways."""
    _check_scene_models(reference, current)
    ref = _as_epoch(reference, "reference")
    cur = _current_epoch(ref, current, intrinsics, timings, _scene_model(reference))
    _check_pair(ref, cur, params)
    reg = register_depth(ref.depth, cur.depth, ref.intrinsics, params.registration,
                         initial=initial_pose)
    timings["registration_ms"] = reg.ms
    reason = reg.not_at_station(params.registration)
    if reason:
        return _Aligned(ref, cur, reg, reason)
    identity = reg.is_identity
    if not identity:
        T = reg.inverse()
        ref = dataclasses.replace(
            ref, points=transform_points(T, ref.points),
            mixture=ref.mixture.transformed(T) if ref.mixture is not None else None)
    free_cur, obs_cur = _timed_free(cur, ref, params, timings, "appeared_",
                                    None if identity else reg.T_ref_from_cur)
    if not params.disappeared:
        return _Aligned(ref, cur, reg, reason, free_cur, obs_cur)
    free_ref, obs_ref = _timed_free(ref, cur, params, timings, "disappeared_",
                                    None if identity else reg.inverse())
    return _Aligned(ref, cur, reg, reason, free_cur, obs_cur, free_ref, obs_ref)


def _finish(method: str, params: ChangeParams, aligned: _Aligned, app: _Direction | None,
            dis: _Direction | None, k_ref: int, k_cur: int, timings: dict, t_start: float
            ) -> ChangeSet:
    ref, cur = aligned.ref, aligned.cur
    t0 = time.perf_counter()
    regions_a = group_regions("appeared", cur, app.changed, params, app.posterior,
                              app.trace.change if app.trace is not None else None) \
        if app is not None else ()
    regions_d = group_regions("disappeared", ref, dis.changed, params, dis.posterior,
                              dis.trace.change if dis.trace is not None else None) \
        if dis is not None else ()
    rows_a = (np.sort(np.concatenate([r.point_index for r in regions_a]))
              if regions_a else np.zeros(0, np.int64))
    rows_d = (np.sort(np.concatenate([r.point_index for r in regions_d]))
              if regions_d else np.zeros(0, np.int64))
    unseen = sum(int((~d.observed).sum()) for d in (app, dis) if d is not None)
    seen_of = (cur.n_points if app is not None else 0) + (ref.n_points if dis is not None else 0)
    timings["regions_ms"] = (time.perf_counter() - t0) * 1e3
    timings["detect_ms"] = (time.perf_counter() - t_start) * 1e3
    changed = bool(regions_a or regions_d)
    return ChangeSet(
        changed=changed,
        appeared=regions_a, disappeared=regions_d,
        appeared_points=cur.points[rows_a].astype(np.float32),
        disappeared_points=ref.points[rows_d].astype(np.float32),
        appeared_index=rows_a, disappeared_index=rows_d,
        appeared_mask=_mask_of(cur, rows_a), disappeared_mask=_mask_of(ref, rows_d),
        appeared_mixture=app.mixture if app is not None else None,
        disappeared_mixture=dis.mixture if dis is not None else None,
        k_reference=k_ref, k_current=k_cur,
        greedy_appeared=app.trace if app is not None else None,
        greedy_disappeared=dis.trace if dis is not None else None,
        method=method, params=params, timings_ms=timings,
        outcome="changed" if changed else "no_change",
        registration=aligned.registration,
        unobserved_fraction=unseen / seen_of if seen_of else 0.0)


def _not_at_station(method: str, params: ChangeParams, aligned: _Aligned, timings: dict,
                    t_start: float) -> ChangeSet:
    """The camera is not where the reference was taken: nothing is compared, nothing
    reported."""
    ref, cur = aligned.ref, aligned.cur
    none = np.zeros(0, np.int64)
    timings["detect_ms"] = (time.perf_counter() - t_start) * 1e3
    return ChangeSet(
        changed=False, appeared=(), disappeared=(),
        appeared_points=np.zeros((0, 3), np.float32),
        disappeared_points=np.zeros((0, 3), np.float32),
        appeared_index=none, disappeared_index=none,
        appeared_mask=np.zeros(cur.depth.shape, bool),
        disappeared_mask=np.zeros(ref.depth.shape, bool),
        appeared_mixture=None, disappeared_mixture=None,
        k_reference=ref.mixture.n_components if ref.mixture is not None else 0, k_current=0,
        greedy_appeared=None, greedy_disappeared=None, method=method, params=params,
        timings_ms=timings, outcome="not_at_station", registration=aligned.registration,
        unobserved_fraction=1.0 - aligned.registration.fitness,
        not_at_station_reason=aligned.reason)


def detect_changes(reference: Reference, current: Current, params: ChangeParams = ChangeParams(), *,
                   intrinsics: Intrinsics | None = None,
                   initial_pose: np.ndarray | None = None) -> ChangeSet:
    """What appeared and what disappeared between the station's reference and now.

    The current view is first registered to the reference
    (:func:`robot_change.change.registration.register_depth`, ``params.registration``); when the
    registration fails or the offset is beyond the station tolerance, the outcome is
    ``"not_at_station"`` and nothing is compared.  Otherwise both directions are compared in
    the current camera frame.

    Parameters
    ----------
    reference : SceneModel or Epoch
        The station's reference (fused depth, intrinsics, clean cloud, mixture).
    current : SceneModel, Epoch, or (H, W) uint16 depth array
        A depth array is cleaned with the reference's CloudParams (``intrinsics``: the
        reference's when not given; they must match).
    params : ChangeParams
        ``novelty=False`` runs the plain method (:func:`detect_plain`).
    initial_pose : (4, 4), optional
        Where registration starts (``T_ref_from_cur``; the identity by default: the robot
        believes it is at its station).  WATCH passes the last check's estimate.

    Returns
    -------
    ChangeSet

    Raises
    ------
    SceneMismatchError (robot_change.change.scene)
        Other image size, intrinsics or cloud parameters than the reference.
    EmptySceneError (robot_change.errors)
        Either clean cloud has fewer than ``params.min_cloud_points`` points: the camera sees
        nothing to compare.  Deliberately an error, not a "no change" result: with no
        readings we cannot tell an unchanged room from something right in front of the lens
        (nearer than the sensor's minimum range), a covered lens or a dead camera.  The
        caller decides (watch mode: a fault, pause the base).
    """
    if not isinstance(params, ChangeParams):
        raise InputError(f"params must be a ChangeParams, got {type(params).__name__}")
    if not params.novelty:
        return detect_plain(reference, current, params, intrinsics=intrinsics)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    aligned = _align(reference, current, params, intrinsics, timings, initial_pose)
    if not aligned.at_station:
        return _not_at_station("novelty", params, aligned, timings, t_start)
    ref, cur = aligned.ref, aligned.cur
    ref_mix = ref.mixture
    if ref_mix is None:
        t0 = time.perf_counter()
        ref_mix = _fit_own(ref, params)
        timings["reference_fit_ms"] = (time.perf_counter() - t0) * 1e3
    free_a, obs_a = aligned.free_cur, aligned.observed_cur
    cand, mix, post, trace = _novelty_direction("appeared", ref, cur, ref_mix, params, timings,
                                                "appeared_", free_a, obs_a)
    cand = _geometric_filters(cur, ref, cand, params, timings, "appeared_", free_a, obs_a)
    app = _Direction(cand, post, mix, trace, obs_a)
    dis = None
    k_cur = 0
    if params.disappeared:
        cur_mix = cur.mixture
        if cur_mix is None:
            t0 = time.perf_counter()
            cur_mix = _current_mixture(cur, ref_mix, params)
            timings["current_fit_ms"] = (time.perf_counter() - t0) * 1e3
        k_cur = cur_mix.n_components
        free_d, obs_d = aligned.free_ref, aligned.observed_ref
        cand, mix, post, trace = _novelty_direction("disappeared", cur, ref, cur_mix, params,
                                                    timings, "disappeared_", free_d, obs_d)
        cand = _geometric_filters(ref, cur, cand, params, timings, "disappeared_", free_d,
                                  obs_d)
        dis = _Direction(cand, post, mix, trace, obs_d)
    return _finish("novelty", params, aligned, app, dis, ref_mix.n_components, k_cur, timings,
                   t_start)


def detect_plain(reference: Reference, current: Current, params: ChangeParams = ChangeParams(
        novelty=False, free_space=False), *, intrinsics: Intrinsics | None = None) -> ChangeSet:
    """The plain method (the paper's): independent fits of both clouds, greedy EMD over all
    components both ways deciding what changed (``params.greedy`` is forced on: without it
    every component would count as changed), posterior segmentation; the free-space / NN
    checks only if ``params`` switches them on (off by default here).  Registered first, as
    :func:`detect_changes` is."""
    params = params.replace(greedy=True)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    aligned = _align(reference, current, params, intrinsics, timings)
    if not aligned.at_station:
        return _not_at_station("plain", params, aligned, timings, t_start)
    ref, cur = aligned.ref, aligned.cur
    mixes = []
    for name, ep in (("reference", ref), ("current", cur)):
        m = ep.mixture
        if m is None:
            t0 = time.perf_counter()
            m = _fit_own(ep, params)
            timings[f"{name}_fit_ms"] = (time.perf_counter() - t0) * 1e3
        mixes.append(m)
    ref_mix, cur_mix = mixes
    free_a, obs_a = aligned.free_cur, aligned.observed_cur
    cand, mix, post, trace = _plain_direction(ref_mix, cur, cur_mix, params, timings,
                                              "appeared_")
    cand = _geometric_filters(cur, ref, cand, params, timings, "appeared_", free_a, obs_a)
    app = _Direction(cand, post, mix, trace, obs_a)
    dis = None
    if params.disappeared:
        free_d, obs_d = aligned.free_ref, aligned.observed_ref
        cand, mix, post, trace = _plain_direction(cur_mix, ref, ref_mix, params, timings,
                                                  "disappeared_")
        cand = _geometric_filters(ref, cur, cand, params, timings, "disappeared_", free_d,
                                  obs_d)
        dis = _Direction(cand, post, mix, trace, obs_d)
    return _finish("plain", params, aligned, app, dis, ref_mix.n_components,
                   cur_mix.n_components, timings, t_start)


def _timed_free(other: Epoch, base: Epoch, params: ChangeParams, timings: dict, prefix: str,
                base_from_other: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_free_mask`, timed."""
    t0 = time.perf_counter()
    out = _free_mask(other, base, params, base_from_other)
    timings[f"{prefix}free_space_ms"] = (time.perf_counter() - t0) * 1e3
    return out


def _nn_far(tree: cKDTree, points: np.ndarray, d: float) -> np.ndarray:
    dist, _ = tree.query(points, k=1, distance_upper_bound=d)
    return ~np.isfinite(dist)


def detect_nn_threshold(reference: Reference, current: Current, params: ChangeParams = ChangeParams(
        free_space=False, nn_check_m=0.05), *, intrinsics: Intrinsics | None = None,
        initial_pose: np.ndarray | None = None) -> ChangeSet:
    """Baseline: a current point is appeared when no reference point is within
    ``params.nn_check_m`` (a reference point disappeared likewise); no mixture, and the
    free-space check only when ``params.free_space``.  Same registration and region grouping
    as ours."""
    if params.nn_check_m <= 0 and not params.free_space:
        raise InputError("detect_nn_threshold needs params.nn_check_m > 0 (the threshold, m) "
                         "or the free-space check")
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    method = ("free_space" if params.nn_check_m <= 0 else "geometric") if params.free_space \
        else "nn"
    aligned = _align(reference, current, params, intrinsics, timings, initial_pose)
    if not aligned.at_station:
        return _not_at_station(method, params, aligned, timings, t_start)
    ref, cur = aligned.ref, aligned.cur
    t0 = time.perf_counter()
    if params.nn_check_m > 0:
        app = _nn_far(cKDTree(ref.points), cur.points, params.nn_check_m)
        dis = _nn_far(cKDTree(cur.points), ref.points, params.nn_check_m) \
            if params.disappeared else None
    else:  # free-space check alone
        app = np.ones(cur.n_points, dtype=bool)
        dis = np.ones(ref.n_points, dtype=bool) if params.disappeared else None
    timings["nn_ms"] = (time.perf_counter() - t0) * 1e3
    no_nn = params.replace(nn_check_m=0.0)
    free_a, obs_a = aligned.free_cur, aligned.observed_cur
    app_d = _Direction(_geometric_filters(cur, ref, app, no_nn, timings, "appeared_", free_a,
                                          obs_a), None, None, None, obs_a)
    dis_d = None
    if dis is not None:
        free_d, obs_d = aligned.free_ref, aligned.observed_ref
        dis_d = _Direction(_geometric_filters(ref, cur, dis, no_nn, timings, "disappeared_",
                                              free_d, obs_d), None, None, None, obs_d)
    return _finish(method, params, aligned, app_d, dis_d,
                   ref.mixture.n_components if ref.mixture is not None else 0,
                   cur.mixture.n_components if cur.mixture is not None else 0,
                   timings, t_start)


def detect_geometric(reference: Reference, current: Current, params: ChangeParams = ChangeParams(
        nn_check_m=0.05), *, intrinsics: Intrinsics | None = None) -> ChangeSet:
    """Baseline without a mixture: the 5 cm nearest-reference-point check plus the free-space
    check on every point (ALGORITHM.md section 3's bar for the mixture method)."""
    return detect_nn_threshold(reference, current, params.replace(free_space=True),
                               intrinsics=intrinsics)
