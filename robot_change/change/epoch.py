"""One epoch of a comparison (:class:`Epoch`: depth image, intrinsics, clean cloud, mixture),
made from a SceneModel or a depth image, and the checks that two epochs can be compared.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hw.depth import DepthFrame, Intrinsics
from robot_change.change.params import ChangeParams
from robot_change.change.registration import RegistrationParams
from robot_change.change.scene import (
    COMPARED_CLOUD_FIELDS,
    SceneModel,
    check_compatible,
    intrinsics_differences,
)
from robot_change.cloud.chain import CloudParams, clean_cloud
from robot_change.cloud.geometry import FROM_METRES
from robot_change.errors import EmptySceneError, InputError, SceneMismatchError
from robot_change.mixture.model import Mixture
from robot_change.noise.profile import (
    DEFAULT_PROFILE,
    NoiseProfile,
    builtin_profile,
    sigma_table,
)

__all__ = [
    "Epoch",
    "as_epoch",
    "check_current_depth",
    "check_pair",
    "check_scene_models",
    "clean_current",
    "current_epoch",
    "epoch_from_depth",
    "kept",
    "pair_sigma_table",
]

#: Results of one kind (a ``derived`` key's first item) an epoch keeps for different
#: parameters: a caller that varies them (a node's tunable parameter) keeps this many, not one
#: per value it ever tried (2.3 MB each for the objects' segments).
KEPT_PER_KIND = 4


def kept(derived: dict, key: tuple, make: Callable[[], Any]) -> Any:
    """``derived[key]``, made by ``make()`` the first time; of one kind (``key[0]``) at most
    :data:`KEPT_PER_KIND` are kept, the earliest made dropped first."""
    value = derived.get(key)
    if value is None:
        value = make()
        same = [k for k in list(derived) if isinstance(k, tuple) and k[:1] == key[:1]]
        for old in same[:max(0, len(same) + 1 - KEPT_PER_KIND)]:
            derived.pop(old, None)
        derived[key] = value
    return value


@dataclasses.dataclass(frozen=True, eq=False)
class Epoch:
    """What change detection needs of one epoch (a view of a SceneModel).

    ``depth`` (H, W) uint16 mm (fused for a reference), ``intrinsics``, the clean cloud
    ``points`` (M, 3) float32 with its voxel ``keys`` (M,) int64 and ``pixel_voxel`` (H, W)
    int32, ``leaf_m`` of its voxel grid, ``mixture`` (None until fitted), ``cloud_params``,
    ``noise``: the camera's profile (robot_change.noise; a current image has its reference's).

    ``derived``: results computed from this epoch that a rigid move of it does not change
    (functions of its depth image, or of its mixture on its own points), kept so that a
    station's reference pays for them once: an epoch of a SceneModel shares the model's dict,
    and a moved copy (``dataclasses.replace``) shares it too.  Keys are tuples naming the
    result and its parameters.
    """

    depth: np.ndarray
    intrinsics: Intrinsics
    points: np.ndarray
    keys: np.ndarray
    pixel_voxel: np.ndarray
    leaf_m: float
    mixture: Mixture | None
    cloud_params: CloudParams | None = None
    derived: dict = dataclasses.field(default_factory=dict, repr=False)
    noise: NoiseProfile = dataclasses.field(
        default_factory=lambda: builtin_profile(DEFAULT_PROFILE), repr=False)

    def registration_params(self, params: RegistrationParams) -> RegistrationParams:
        """``params`` with this epoch's camera: its noise profile and, where ``params`` sets no
        ``min_depth_m``, its cloud's near range (registration reads what the cloud reads).
        Kept in ``derived``: the pyramids registration keeps are found under these."""
        def make() -> RegistrationParams:
            near = (self.cloud_params or CloudParams()).near_m(self.noise)
            return params.replace(noise=self.noise, min_depth_m=near if params.min_depth_m is None
                                  else params.min_depth_m)

        return kept(self.derived, ("registration_params", params), make)

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])


def pair_sigma_table(a: Epoch, b: Epoch) -> np.ndarray:
    """(n,) float64 sigma table (robot_change.noise.kernels.sigma_at) of one reading when a
    reading of ``a`` is compared with one of ``b``: sqrt((sigma_a^2 + sigma_b^2) / 2), so that
    the margin of the two, k sqrt(2 sigma^2 + pose^2), holds both.  Kept in ``a.derived``."""
    def make() -> np.ndarray:
        ta, tb = sigma_table(a.noise), sigma_table(b.noise)
        table = np.sqrt(0.5 * (ta * ta + tb * tb))
        table.setflags(write=False)
        return table

    return kept(a.derived, ("pair_sigma_table", a.noise, b.noise), make)


#: the default cloud parameters (frozen, built once)
_DEFAULT_CLOUD_PARAMS = CloudParams()


def epoch_from_depth(depth: np.ndarray, intrinsics: Intrinsics,
                     cloud_params: CloudParams = _DEFAULT_CLOUD_PARAMS,
                     mixture: Mixture | None = None, noise: NoiseProfile | None = None
                     ) -> Epoch:
    """Clean the depth image (:func:`robot_change.cloud.chain.clean_cloud`) into an
    :class:`Epoch` (``noise``: the camera's profile, the default built-in when not given;
    its near range where ``cloud_params`` sets none)."""
    noise = noise or builtin_profile(DEFAULT_PROFILE)
    if isinstance(cloud_params, CloudParams):
        cloud_params = cloud_params.for_camera(noise)
    cloud = clean_cloud(depth, intrinsics, cloud_params)
    return Epoch(np.ascontiguousarray(depth), intrinsics, cloud.points, cloud.keys,
                 cloud.pixel_voxel, float(cloud_params.leaf_m), mixture, cloud_params,
                 noise=noise)


def as_epoch(obj: Any, name: str) -> Epoch:
    """An :class:`Epoch` from an Epoch or a SceneModel (duck-typed: ``depth``, ``intrinsics``,
    ``cloud`` or ``points``/``keys``/``pixel_voxel``, ``mixture``, ``params``)."""
    if isinstance(obj, Epoch):
        return obj
    if isinstance(obj, DepthFrame):
        raise InputError(f"{name} is a DepthFrame: pass its .depth (the intrinsics are the "
                         "reference's), or build_scene([frame]) to compare two scenes")
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
        derived = obj.derived if isinstance(obj, SceneModel) else {}
        noise = getattr(obj, "noise", None)
    except AttributeError as exc:
        raise InputError(f"{name} must be a SceneModel (robot_change.change.scene) or an Epoch, "
                         f"got {type(obj).__name__} ({exc})") from None
    return Epoch(np.asarray(depth), intrinsics, np.asarray(points, dtype=np.float32),
                 np.asarray(keys, dtype=np.int64), np.asarray(pixel_voxel, dtype=np.int32),
                 leaf, mixture, cloud_params if isinstance(cloud_params, CloudParams) else None,
                 derived, noise if isinstance(noise, NoiseProfile)
                 else builtin_profile(DEFAULT_PROFILE))


def check_pair(ref: Epoch, cur: Epoch, params: ChangeParams) -> None:
    if ref.depth.shape != cur.depth.shape or intrinsics_differences(ref.intrinsics,
                                                                    cur.intrinsics):
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


def check_current_depth(reference: Epoch, current: np.ndarray, intrinsics: Intrinsics | None,
                        reference_model: Any = None) -> Intrinsics:
    """The checks of a current depth array against the reference (dtype, shape, camera, the
    reference model's parameters); returns the reference's intrinsics (the current's are
    those, within :data:`~robot_change.change.scene.INTRINSICS_TOLERANCE_PX`)."""
    given = intrinsics is not None
    if intrinsics is None:
        intrinsics = reference.intrinsics
    if not isinstance(intrinsics, Intrinsics):
        raise InputError(f"intrinsics must be a hw.depth.Intrinsics, got "
                         f"{type(intrinsics).__name__}")
    if current.ndim != 2 or current.dtype != np.uint16:
        raise InputError(f"current depth must be an (H, W) uint16 array of millimetres, got "
                         f"{current.dtype} of shape {current.shape}; {FROM_METRES}")
    if reference_model is not None:
        check_compatible(reference_model, (intrinsics, reference_model.params))
    if given and current.shape != (intrinsics.height, intrinsics.width):
        raise InputError(f"current depth is {current.shape[1]}x{current.shape[0]} but the "
                         f"intrinsics are for {intrinsics.width}x{intrinsics.height}")
    if current.shape != reference.depth.shape or intrinsics_differences(reference.intrinsics,
                                                                        intrinsics):
        _raise_mismatch(f"current depth {current.shape[::-1]} with {intrinsics} does not "
                        f"match the reference's {reference.depth.shape[::-1]} "
                        f"{reference.intrinsics}; use the camera mode the reference was "
                        f"taken with, or rebuild the reference")
    return reference.intrinsics


def clean_current(reference: Epoch, current: np.ndarray, intrinsics: Intrinsics,
                  timings: dict) -> Epoch:
    """The current's :class:`Epoch` from a depth array already checked
    (:func:`check_current_depth`), cleaned with the reference's CloudParams, with the
    reference's camera profile (timed as ``current_cloud_ms``)."""
    t0 = time.perf_counter()
    cloud_params = reference.cloud_params or CloudParams(leaf_m=reference.leaf_m)
    ep = epoch_from_depth(current, intrinsics, cloud_params, noise=reference.noise)
    timings["current_cloud_ms"] = (time.perf_counter() - t0) * 1e3
    return ep


def current_epoch(reference: Epoch, current: Any, intrinsics: Intrinsics | None,
                   timings: dict, reference_model: Any = None) -> Epoch:
    """The current's :class:`Epoch`: a depth array checked and cleaned, or an Epoch /
    SceneModel as it is."""
    if isinstance(current, np.ndarray):
        intrinsics = check_current_depth(reference, current, intrinsics, reference_model)
        return clean_current(reference, current, intrinsics, timings)
    if intrinsics is not None:
        raise InputError("intrinsics= is only for a current depth array; a SceneModel "
                         "carries its own")
    return as_epoch(current, "current")


def check_scene_models(reference: Any, current: Any) -> None:
    """scene.check_compatible for two SceneModels, when scene.py provides it."""
    if isinstance(reference, SceneModel) and isinstance(current, SceneModel):
        check_compatible(reference, current)
