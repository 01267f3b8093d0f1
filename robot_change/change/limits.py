"""What a station can see: the smallest change a check against its reference can report, in
each part of the view (:func:`detection_limit`), from the camera's noise and the check's rules.

A box of edge ``s`` (metres) that appears at depth ``z`` in front of a surface is reported when

* it stands out of that surface by more than the free-space margin there (``s`` >= the margin,
  ``free_space_sigmas`` sigmas of the two readings' noise and ``free_space_pose_m``);
* its face keeps a core seen through clear of the flying pixels at its edges: ``s`` less the
  ``2 edge_px + 1`` pixels the edges take is at least ``evidence_min_points`` points wide and
  high (voxels of ``leaf_m``; what the registration's error may turn, ``free_space_pose_deg``,
  moves where the face lands on the surface behind it, not what it sees through);
* it holds ``min_region_points`` points (its face, ``(s / leaf)^2``).

An object that moved by less than its size is another matter (its two places overlap): it is
told where the strip it left or took is as wide as such a core, and as far as the registration
is sure of it (docs/algorithm.md).

Beyond the camera's reliable range (``noise.max_range_m``) and where the reference has no
reading, nothing can be told (infinity).  tests/test_limits.py renders boxes just above and
well below the limit and checks that the first are found and the second are not.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from robot_change.change.params import ChangeParams
from robot_change.noise.profile import NoiseProfile

__all__ = ["DetectionLimit", "GRID", "detection_limit", "smallest_change_m"]

#: The view is told in GRID[0] x GRID[1] parts (rows, columns).
GRID = (6, 8)


def smallest_change_m(z, noise: NoiseProfile, params: ChangeParams, leaf_m: float,
                      fx: float) -> np.ndarray:
    """The edge (m) of the smallest box reported at depth ``z`` (m, any shape): module
    docstring; infinity outside the camera's range."""
    z = np.asarray(z, dtype=np.float64)
    stands_out = noise.margin(z, params.free_space_sigmas, params.free_space_pose_m)
    core = z * (2 * noise.edge_px + 1) / fx + leaf_m * math.sqrt(params.evidence_min_points)
    points = leaf_m * math.sqrt(params.min_region_points)
    edge = np.maximum(np.maximum(stands_out, core), points)
    return np.where((z >= noise.min_range_m) & (z <= noise.max_range_m), edge, np.inf)


@dataclasses.dataclass(frozen=True)
class DetectionLimit:
    """The smallest change reported in each part of a view: ``edge_m`` (GRID) the edge of the
    smallest box (m; infinity where nothing can be told: no reading, beyond the range),
    ``depth_m`` (GRID) the median depth of each part (NaN: no reading), and ``median_m``, the
    limit at the view's median depth: the one figure the base logs."""

    edge_m: np.ndarray
    depth_m: np.ndarray
    median_m: float

    def to_dict(self) -> dict:
        def mm(a):
            return [[None if not np.isfinite(v) else round(float(v) * 1000) for v in row]
                    for row in a]
        return {"median_mm": round(self.median_m * 1000) if math.isfinite(self.median_m)
                else None,
                "grid_mm": mm(self.edge_m),
                "depth_mm": mm(self.depth_m),
                "grid": list(GRID),
                "rule": "the edge of the smallest box that appears before a surface and is "
                        "reported, per part of the view (rows top to bottom)"}


def detection_limit(depth: np.ndarray, noise: NoiseProfile, params: ChangeParams,
                    leaf_m: float, fx: float) -> DetectionLimit:
    """:class:`DetectionLimit` of a reference's (H, W) uint16 mm ``depth`` image with the
    camera's ``noise``, the check's ``params``, the cloud's ``leaf_m`` and focal ``fx``."""
    h, w = depth.shape
    rows, cols = GRID
    depth_m = np.full(GRID, np.nan)
    for i in range(rows):
        for j in range(cols):
            part = depth[i * h // rows:(i + 1) * h // rows, j * w // cols:(j + 1) * w // cols]
            read = part[part > 0]
            if read.size:
                depth_m[i, j] = float(np.median(read)) * 1e-3
    edge = np.full(GRID, np.inf)
    seen = np.isfinite(depth_m)
    edge[seen] = smallest_change_m(depth_m[seen], noise, params, leaf_m, fx)
    read = depth[depth > 0]
    median = (float(smallest_change_m(float(np.median(read)) * 1e-3, noise, params, leaf_m,
                                      fx)) if read.size else math.inf)
    return DetectionLimit(edge, depth_m, median)
