"""How a scene is built (SceneParams) and its file's format name and version: what both the
scene model (robot_change.change.scene) and its file (robot_change.change.scene_file) need."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

from robot_change import validate
from robot_change.cloud.chain import CloudParams
from robot_change.errors import BadValue, InputError
from robot_change.mixture.model import CRITERIA

__all__ = ["FILE_FORMAT", "FILE_VERSION", "MIN_SCENE_POINTS", "SceneParams"]

FILE_FORMAT = "robot_change.scene"
#: 2: voxel keys pack z, y, x from the top (robot_change.cloud.voxels); version 1 packed x, y, z.
#: A version-1 file still loads: its cloud is rebuilt from its own depth image and parameters
#: (keys, point order and pixel maps as this version makes them); its mixture is kept.
FILE_VERSION = 2
#: Fewest clean points a scene may hold: fewer is no view of a room (and cannot be fitted:
#: fit_mixture's smallest component is 10 points).
MIN_SCENE_POINTS = 10


_number = functools.partial(validate.number, "SceneParams")
_whole = functools.partial(validate.whole, "SceneParams")


@dataclasses.dataclass(frozen=True)
class SceneParams:
    """How a scene is built, validated on construction (:class:`InputError` naming the field,
    its value and what is allowed).

    ``cloud``: the clean-cloud chain (its ``leaf_m`` also sets the mixture's covariance floor).
    ``criterion``, ``max_components``, ``tol``, ``max_iter``, ``seed``, ``search_points``: passed
    to :func:`robot_change.mixture.model.fit_mixture`.  ``min_valid_fraction``: in temporal fusion a
    pixel needs readings in at least ``ceil(fraction * N)`` of the N frames (0.5: flicker at
    object edges stays out).
    """

    cloud: CloudParams = dataclasses.field(default_factory=CloudParams)
    criterion: str = "mdl"
    # fit_mixture's default bound.  On 2 cm room clouds MDL keeps falling past K = 16
    # (ALGORITHM.md section 3), so the bound decides K; it keeps a fit near 0.1 s.
    max_components: int = 16
    tol: float = 1e-3
    max_iter: int = 100
    seed: int = 0
    search_points: int | None = 2000
    min_valid_fraction: float = 0.5

    def __post_init__(self) -> None:
        if not isinstance(self.cloud, CloudParams):
            raise BadValue("SceneParams", "cloud", self.cloud,
                           "a robot_change.cloud.chain.CloudParams", wrong_type=True)
        validate.choice("SceneParams", "criterion", self.criterion, CRITERIA)
        _whole("max_components", self.max_components, 1, 1000)
        _number("tol", self.tol, 0.0, math.inf, unit=" (change of mean log-likelihood per point)")
        _whole("max_iter", self.max_iter, 1, 100_000)
        _whole("seed", self.seed, 0, 2**63 - 1)
        if self.search_points is not None:  # None: search on every point
            _whole("search_points", self.search_points, 100, 10**9)
        _number("min_valid_fraction", self.min_valid_fraction, 0.0, 1.0, low_open=True,
                unit=" (0.5: a pixel needs a reading in half of the frames)")

    def min_valid(self, n_frames: int) -> int:
        """Readings a pixel needs among ``n_frames`` frames: ``ceil(fraction * N)``, >= 1."""
        # round first: 0.3 * 10 is 3.0000000000000004 in floating point
        return max(1, min(n_frames, math.ceil(round(self.min_valid_fraction * n_frames, 9))))

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (``cloud`` nested; ``plane_up`` a list or None)."""
        d = dataclasses.asdict(self)
        up = d["cloud"]["plane_up"]
        d["cloud"]["plane_up"] = None if up is None else list(up)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SceneParams:
        """Inverse of :meth:`to_dict`; missing fields take their defaults, unknown ones and
        invalid values raise :class:`InputError`."""
        if not isinstance(d, dict) or not isinstance(d.get("cloud", {}), dict):
            raise InputError(f"scene parameters must be a JSON object with a 'cloud' object, "
                             f"got {d!r}")
        known = {f.name for f in dataclasses.fields(cls)}
        cloud_known = {f.name for f in dataclasses.fields(CloudParams)}
        cloud = dict(d.get("cloud", {}))
        unknown = sorted(set(d) - known) + [f"cloud.{k}" for k in sorted(set(cloud) - cloud_known)]
        if unknown:
            raise InputError(f"unknown scene parameters {unknown}; known: {sorted(known)} and "
                             f"cloud.{{{', '.join(sorted(cloud_known))}}}")
        if cloud.get("plane_up") is not None:
            cloud["plane_up"] = tuple(cloud["plane_up"])
        rest = {k: v for k, v in d.items() if k != "cloud"}
        return cls(cloud=CloudParams(**cloud), **rest)
