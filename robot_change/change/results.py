"""What a check returns: :class:`ChangeSet` (outcome, regions, masks, mixtures, registration,
timings), its :class:`Region` s and the greedy EMD :class:`GreedyTrace` of each direction.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from robot_change.change.limits import DetectionLimit
from robot_change.change.mount import CameraMount
from robot_change.change.registration import (
    Registration,
    identity_registration,
)
from robot_change.mixture.model import Mixture
from robot_change.noise.profile import NoiseProfile

__all__ = [
    "ChangeSet",
    "GreedyTrace",
    "Region",
]


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
    mixture.  ``point_index``: rows of the region's points in that epoch's cloud; ``points``
    (M, 3) float32 those points (camera optical frame, m).
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
    points: np.ndarray = dataclasses.field(repr=False)

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
        """(min (3,), max (3,)) of the region's points in base_link, metres: the tight box
        (the box round the camera-frame box turned into base_link was up to 12 cm taller)."""
        moved = mount.to_base(self.points)
        return moved.min(axis=0), moved.max(axis=0)


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


#: the default camera mount of ChangeSet.summary (frozen, built once)
_DEFAULT_MOUNT = CameraMount()


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
    ``not_at_station_reason``: why, for that outcome (else "").  ``current_points`` (N, 3)
    float32: the current's whole clean cloud (the rows ``appeared_index`` refer to; None when
    not kept).  ``noise``: the camera's noise profile the check was scaled by (the
    reference's; robot_change.noise); ``limit``: the smallest change the check could report in
    each part of the view (robot_change.change.limits).
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
    current_points: np.ndarray | None = dataclasses.field(default=None, repr=False)
    noise: NoiseProfile | None = dataclasses.field(default=None, repr=False)
    limit: DetectionLimit | None = dataclasses.field(default=None, repr=False)

    @property
    def regions(self) -> tuple[Region, ...]:
        """Appeared then disappeared regions."""
        return self.appeared + self.disappeared

    def summary(self, mount: CameraMount | None = None) -> dict:
        """JSON-ready summary: outcome, registration (camera frames, and as the robot's offset
        from its station pose in base_link given the camera's ``mount``), regions (camera
        frame and base_link), K of both mixtures, greedy traces, timings.  Without a ``mount``
        the offset and the regions' ``base`` are in the camera's body frame (``base_frame``
        says which: ``base_link`` or ``camera_link``, REP 103)."""
        frame = "camera_link" if mount is None else "base_link"
        mount = _DEFAULT_MOUNT if mount is None else mount
        return {
            "outcome": self.outcome,
            "changed": self.changed,
            "method": self.method,
            "registration": self.registration.to_dict(),
            "unobserved_fraction": round(self.unobserved_fraction, 4),
            "not_at_station_reason": self.not_at_station_reason,
            "mount": mount.to_dict() if frame == "base_link" else None,
            "base_frame": frame,
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
            "noise": self.noise_summary(),
            "detection_limit": self.limit.to_dict() if self.limit is not None else None,
        }

    def noise_summary(self) -> dict | None:
        """The camera's noise the check was scaled by: the profile's summary and the margin a
        surface had to lie beyond the other epoch's to be seen through, at 1-4 m (mm)."""
        if self.noise is None:
            return None
        out = self.noise.summary()
        sigmas = getattr(self.params, "free_space_sigmas", None)
        pose = getattr(self.params, "free_space_pose_m", None)
        if sigmas is not None and pose is not None:
            out["margin_mm"] = {f"{z:g}m": round(float(self.noise.margin(z, sigmas, pose))
                                                 * 1000, 1) for z in (1.0, 2.0, 3.0, 4.0)}
        return out
