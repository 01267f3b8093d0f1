"""A scene model: what the camera saw at one epoch, kept so that another epoch can be compared.

    frames (N x (H, W) uint16 mm)
      -> fused depth   :func:`robot_change.cloud.fusion.fuse_depth` (per-pixel median)
      -> clean cloud   :func:`robot_change.cloud.chain.clean_cloud` (voxels, outliers, plane)
      -> mixture       :func:`robot_change.mixture.model.fit_mixture` (split-EM, MDL / BIC / AIC)

A :class:`SceneModel` keeps all three, with the intrinsics (the free-space check of
ALGORITHM.md section 3 needs the fused depth image, not only the cloud and the mixture) and how
it was made.  :meth:`SceneModel.save` / :meth:`SceneModel.load` store it as one verified file;
:func:`check_compatible` refuses to compare scenes seen with other intrinsics or parameters.

No device is opened here: :func:`build_scene_from_source` is handed an open
:class:`hw.depth.DepthSource`.
"""

from __future__ import annotations

import dataclasses
import datetime
import time
from pathlib import Path

import numpy as np

import robot_change
from hw.depth import DepthFrame, DepthSource, Intrinsics
from robot_change import npzfile, validate
from robot_change.change import scene_file
from robot_change.change.mount import CameraMount
from robot_change.change.scene_params import (
    FILE_FORMAT,
    FILE_VERSION,
    MIN_SCENE_POINTS,
    SceneParams,
)
from robot_change.cloud.chain import CleanCloud, CloudParams, clean_cloud
from robot_change.cloud.fusion import fuse_depth
from robot_change.errors import (
    EmptySceneError,
    InputError,
    SceneMismatchError,
)
from robot_change.mixture.model import Mixture, fit_mixture
from robot_change.noise.estimate import FrameNoise, drift_limit, measure_frames
from robot_change.noise.profile import (
    DEFAULT_PROFILE,
    RAISE_TOLERANCE,
    NoiseProfile,
    builtin_profile,
)

__all__ = [
    "FILE_FORMAT",
    "FILE_VERSION",
    "INTRINSICS_TOLERANCE_PX",
    "intrinsics_differences",
    "MIN_SCENE_POINTS",
    "SceneModel",
    "SceneParams",
    "build_scene",
    "build_scene_from_source",
    "check_compatible",
    "measured_profile",
    "scene_differences",
]

#: Intrinsics closer than this (pixels) count as the same camera.
INTRINSICS_TOLERANCE_PX = 1e-3
#: CloudParams fields that change what a point or a voxel means; two scenes compared must
#: agree on them.  plane_iterations / plane_seed only set the RANSAC search effort.
COMPARED_CLOUD_FIELDS = (
    "leaf_m", "min_depth_m", "max_depth_m",
    "remove_outliers", "outlier_k", "outlier_alpha", "outlier_cap_leaves",
    "remove_plane", "plane_distance_m", "plane_min_inliers", "plane_up", "plane_max_tilt_deg",
)


# --------------------------------------------------------------------------- the model


@dataclasses.dataclass(frozen=True, eq=False)
class SceneModel:
    """What the camera saw at one epoch, and how the model was made.

    ``depth``: (H, W) uint16 mm, the fused image (0 = no reading), read-only.
    ``intrinsics``: of ``depth``.  ``cloud``: the :class:`robot_change.cloud.chain.CleanCloud` --
    ``cloud.points`` (M, 3) float32 metres (camera optical frame), ``cloud.pixel_voxel``
    (H, W) int32 (row of ``points`` each pixel went into, -1 none), ``cloud.pixel_stage``,
    ``cloud.keys``, ``cloud.counts``, ``cloud.plane``, ``cloud.stage_counts``.
    ``mixture``: fitted to ``cloud.points`` (``mixture.record``: the fit; kept in the file).
    Provenance: ``params``; ``n_frames`` fused; ``first_timestamp_us`` / ``last_timestamp_us``
    and ``first_index`` / ``last_index`` of those frames (None for bare arrays); ``seconds``
    per stage (``fusion``, ``points``, ``voxel``, ``outliers``, ``plane``, ``cloud`` (all four),
    ``fit``, ``total``; ``read`` when built from a source); ``created`` (UTC, ISO 8601);
    ``version`` (robot_change's); ``source`` (e.g. the depth URI); ``mount``: the camera's
    mounting on the base when the reference was captured (None: not recorded); ``noise``:
    the camera's noise profile (robot_change.noise), raised where the fused frames showed
    more noise, and what they showed (``noise.measured``, ``noise.flicker_*``); ``drift``: how
    far the last fused frame lies from the first against consecutive ones
    (robot_change.noise.estimate.FrameNoise.drift: about 1 for a still view, None for one
    frame), and :attr:`moved_while_captured` whether that says the view moved.
    """

    depth: np.ndarray
    intrinsics: Intrinsics
    cloud: CleanCloud
    mixture: Mixture
    params: SceneParams
    n_frames: int
    first_timestamp_us: int | None
    last_timestamp_us: int | None
    first_index: int | None
    last_index: int | None
    seconds: dict[str, float]
    created: str
    version: str
    source: str = ""
    mount: CameraMount | None = None
    noise: NoiseProfile = dataclasses.field(
        default_factory=lambda: builtin_profile(DEFAULT_PROFILE))
    drift: float | None = None

    @property
    def moved_while_captured(self) -> bool:
        """Whether the fused frames drift beyond a still view's
        (robot_change.noise.estimate.drift_limit): the camera or the scene moved while they
        were taken, so the reference is blurred and its noise profile raised by the motion."""
        return self.drift is not None and self.drift > drift_limit(self.n_frames)

    def __post_init__(self) -> None:
        d = self.depth
        if not isinstance(d, np.ndarray) or d.dtype != np.uint16 or d.ndim != 2:
            raise InputError("SceneModel.depth must be an (H, W) uint16 array in millimetres")
        if not isinstance(self.intrinsics, Intrinsics):
            raise InputError("SceneModel.intrinsics must be an hw.depth.Intrinsics")
        if d.shape != (self.intrinsics.height, self.intrinsics.width):
            raise InputError(f"SceneModel.depth is {d.shape[1]}x{d.shape[0]} but the intrinsics "
                             f"are for {self.intrinsics.width}x{self.intrinsics.height}")
        if not isinstance(self.cloud, CleanCloud):
            raise InputError("SceneModel.cloud must be a robot_change.cloud.chain.CleanCloud")
        if self.cloud.pixel_voxel.shape != d.shape:
            raise InputError(f"SceneModel.cloud.pixel_voxel has shape "
                             f"{self.cloud.pixel_voxel.shape}, the depth image {d.shape}")
        if not isinstance(self.mixture, Mixture) or not isinstance(self.params, SceneParams):
            raise InputError("SceneModel.mixture must be a Mixture and params a SceneParams")
        if self.mount is not None and not isinstance(self.mount, CameraMount):
            raise InputError("SceneModel.mount must be a robot_change.change.mount.CameraMount "
                             "or None")
        if not isinstance(self.noise, NoiseProfile):
            raise InputError("SceneModel.noise must be a NoiseProfile (robot_change.noise)")
        if d.flags.writeable:
            d = d.copy()
            d.setflags(write=False)
            object.__setattr__(self, "depth", d)
        object.__setattr__(self, "_derived", {})

    @property
    def derived(self) -> dict:
        """What checks against this model compute once and keep (the epochs' ``derived``,
        robot_change.change.epoch.Epoch): never saved, gone with the object."""
        return self._derived

    @property
    def points(self) -> np.ndarray:
        """(M, 3) float32 clean cloud, metres (``cloud.points``)."""
        return self.cloud.points

    @property
    def pixel_voxel(self) -> np.ndarray:
        """(H, W) int32 row of :attr:`points` per pixel, -1 none (``cloud.pixel_voxel``)."""
        return self.cloud.pixel_voxel

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the depth image."""
        return self.depth.shape  # type: ignore[return-value]

    def __len__(self) -> int:
        return len(self.cloud)

    def __repr__(self) -> str:
        return (f"SceneModel({self.shape[1]}x{self.shape[0]}, {len(self)} points, "
                f"K={self.mixture.n_components}, {self.n_frames} frames, source={self.source!r}, "
                f"created={self.created!r})")

    # ----------------------------------------------------------------------- files

    def save(self, path) -> None:
        """Write to ``path`` as one compressed .npz, atomically (temp file, fsync, rename).

        Arrays: ``depth``, ``points``, ``keys``, ``counts``, ``pixel_voxel``, ``pixel_stage``,
        ``plane_normal``, ``plane_inliers``, ``weights``, ``means``, ``covariances``; plus
        ``header``, a JSON string: format name and version, library version, intrinsics,
        params, provenance, the cloud's counts and timings, the fit record, the arrays' dtypes
        and shapes, and a SHA-256 over the header and the arrays (checked by :meth:`load`).
        """
        npzfile.write(path, FILE_FORMAT, FILE_VERSION, scene_file.arrays_of(self),
                      scene_file.header_of(self))

    @classmethod
    def load(cls, path) -> SceneModel:
        """Read a scene written by :meth:`save`, verifying everything (no pickled data is ever
        loaded).

        Raises
        ------
        SceneFileError
            Unreadable, truncated or not an .npz; another format; a newer format version;
            checksum mismatch; missing or malformed arrays; parameters that do not validate.
        FileNotFoundError
            ``path`` does not exist.
        """
        return scene_file.load_model(cls, Path(path))


# --------------------------------------------------------------------------- building


def _to_stack(frames, intrinsics: Intrinsics | None):
    """(N, H, W) uint16 stack, intrinsics, and (first/last timestamp, first/last index)."""
    if isinstance(frames, DepthFrame):
        frames = [frames]
    if isinstance(frames, np.ndarray):
        if frames.dtype != np.uint16 or frames.ndim not in (2, 3):
            raise InputError(f"frames must be (N, H, W) or (H, W) uint16 millimetres, got "
                             f"{frames.dtype} {frames.shape}; or a sequence of DepthFrames")
        stack = frames[None] if frames.ndim == 2 else frames
        stamps = (None, None, None, None)
        camera = None
    else:
        try:
            items = list(frames)
        except TypeError:
            raise InputError(f"frames must be a sequence of hw.depth.DepthFrame or a uint16 "
                             f"array, got {type(frames).__name__}") from None
        if not items:
            raise InputError("frames is empty: build a scene from at least one depth frame")
        if any(f is None for f in items):
            raise InputError(f"frame {[f is None for f in items].index(True)} is None (a source "
                             "that ended, or a read that timed out?); pass depth frames only")
        if all(isinstance(f, DepthFrame) for f in items):
            camera = items[0].intrinsics
            for i, f in enumerate(items[1:], 1):
                if f.shape != items[0].shape:
                    raise InputError(f"frame {i} (index {f.index}) is {f.shape[1]}x{f.shape[0]},"
                                     f" frame 0 is {items[0].shape[1]}x{items[0].shape[0]}: "
                                     "fuse frames of one camera mode only")
                diff = intrinsics_differences(camera, f.intrinsics)
                if diff:
                    raise InputError(f"frame {i} (index {f.index}) has other intrinsics than "
                                     f"frame 0 ({'; '.join(diff)}): fuse frames of one camera "
                                     "only")
            arrays = [f.depth for f in items]
            stamps = (int(items[0].timestamp_us), int(items[-1].timestamp_us),
                      int(items[0].index), int(items[-1].index))
        else:
            for i, f in enumerate(items):
                if isinstance(f, DepthFrame):
                    raise InputError(f"frames mixes DepthFrames and arrays (item {i}); pass one "
                                     "kind")
                if not isinstance(f, np.ndarray) or f.dtype != np.uint16 or f.ndim != 2:
                    got = (f"{f.dtype} {f.shape}" if isinstance(f, np.ndarray)
                           else type(f).__name__)
                    raise InputError(f"frame {i} must be an (H, W) uint16 array in millimetres "
                                     f"or a DepthFrame, got {got}")
                if f.shape != items[0].shape:
                    raise InputError(f"frame {i} is {f.shape[1]}x{f.shape[0]}, frame 0 is "
                                     f"{items[0].shape[1]}x{items[0].shape[0]}: all frames must "
                                     "have one size")
            arrays = items
            stamps = (None, None, None, None)
            camera = None
        stack = np.stack(arrays)
    if stack.shape[0] == 0:
        raise InputError("frames holds no frame: build a scene from at least one depth frame")
    height, width = stack.shape[1:]
    if intrinsics is not None:
        if not isinstance(intrinsics, Intrinsics):
            raise InputError(f"intrinsics must be an hw.depth.Intrinsics, got "
                             f"{type(intrinsics).__name__}")
        camera = intrinsics
    if camera is None:
        raise InputError(f"bare depth arrays need intrinsics=...: e.g. "
                         f"Intrinsics.openni_default({width}, {height}) for a Kinect-class "
                         "camera, or the camera's calibration")
    if (camera.width, camera.height) != (width, height):
        raise InputError(f"the frames are {width}x{height} but the intrinsics are for "
                         f"{camera.width}x{camera.height}; pass intrinsics for this resolution "
                         "(Intrinsics.scaled)")
    return stack, camera, stamps


def _empty_message(n: int, counts: dict[str, int], params: SceneParams, stack: np.ndarray,
                   fused: np.ndarray) -> str:
    cp = params.cloud
    n_frames = stack.shape[0]
    head = (f"the scene holds {n} points after filtering (at least {MIN_SCENE_POINTS} needed; "
            f"stage counts {counts}): ")
    if counts["pixels"] == 0 and n_frames > 1 and stack.any():
        why = (f"no pixel has a reading in {params.min_valid(n_frames)} of the {n_frames} "
               "frames, though single frames have some: did the camera move while the frames "
               "were taken? Keep it still, or lower min_valid_fraction")
    elif counts["pixels"] == 0:
        why = ("no pixel has a depth reading. Is the camera covered, or not streaming depth "
               "(IR projector off, wrong mode)? Check that it looks at something in range")
    elif counts["points"] < MIN_SCENE_POINTS:
        far = int(np.count_nonzero(fused > cp.max_depth_m * 1000.0))
        near = counts["pixels"] - far
        why = (f"of {counts['pixels']} readings, {far} are beyond max_depth_m = "
               f"{cp.max_depth_m} m and {near} nearer than min_depth_m = {cp.min_depth_m} m. "
               + ("Is everything beyond the maximum depth (an open space, a far wall)? "
                  if far >= near else
                  "Is the camera facing a surface right in front of it, or covered? ")
               + "Point the camera at the scene, or widen min_depth_m / max_depth_m")
    elif counts["after_outliers"] < MIN_SCENE_POINTS:
        why = ("outlier removal dropped almost every voxel: the readings are scattered noise. "
               "Check the camera and the view, or set remove_outliers=False")
    else:
        why = (f"the dominant plane took {counts['plane_inliers']} of {counts['after_outliers']} "
               "voxels: only the floor (or a table, or a wall) is in view. Point the camera at "
               "the objects to watch, or set remove_plane=False")
    return head + why


def build_scene(
    frames,
    params: SceneParams | None = None,
    *,
    intrinsics: Intrinsics | None = None,
    source: str = "",
    mount: CameraMount | None = None,
    noise: NoiseProfile | None = None,
) -> SceneModel:
    """Fuse frames, clean the cloud, fit the mixture, measure the noise: a :class:`SceneModel`.

    Parameters
    ----------
    frames : sequence of hw.depth.DepthFrame, or (N, H, W) / (H, W) uint16 array, or a
        sequence of (H, W) uint16 arrays
        Depth in millimetres, 0 = no reading, taken while the camera stood still.  DepthFrames
        must share shape and intrinsics (their timestamps and indices are recorded).
    params : SceneParams, optional
        Defaults to ``SceneParams()``.
    intrinsics : hw.depth.Intrinsics, optional
        Required for arrays; for DepthFrames it overrides theirs (``--intrinsics``).
    source : str
        Where the frames came from (recorded, e.g. the depth URI).
    mount : robot_change.change.mount.CameraMount, optional
        The camera's mounting on the base (recorded; ``detect`` uses it for base-frame
        results when not told otherwise).
    noise : robot_change.noise.profile.NoiseProfile, optional
        The camera's profile (default: the built-in ``DEFAULT_PROFILE``).  Two frames or more
        are measured (:func:`robot_change.noise.estimate.measure_frames`) and raise it where
        they are noisier by more than ``RAISE_TOLERANCE`` (never lower it).

    Raises
    ------
    InputError
        Bad frames (dtype, shape, frames of different sizes or intrinsics, no intrinsics).
    EmptySceneError
        Fewer than ``MIN_SCENE_POINTS`` points survive filtering; the message says what to
        check.
    """
    t0 = time.perf_counter()
    params = SceneParams() if params is None else params
    if not isinstance(params, SceneParams):
        raise InputError(f"params must be a SceneParams, got {type(params).__name__}")
    if not isinstance(source, str):
        raise InputError(f"source must be a string (e.g. the depth URI), got {source!r}")
    if noise is not None and not isinstance(noise, NoiseProfile):
        raise InputError(f"noise must be a robot_change.noise.profile.NoiseProfile, got "
                         f"{type(noise).__name__}")
    stack, camera, (ts0, ts1, i0, i1) = _to_stack(frames, intrinsics)
    n_frames = int(stack.shape[0])
    fused = fuse_depth(np.ascontiguousarray(stack), params.min_valid(n_frames))
    profile, measured = measured_profile(stack, noise or builtin_profile(DEFAULT_PROFILE),
                                         source)
    # the camera's near range where none is set, kept with the scene: its checks clean alike
    params = dataclasses.replace(params, cloud=params.cloud.for_camera(profile))
    t1 = time.perf_counter()
    cloud = clean_cloud(fused, camera, params.cloud)
    t2 = time.perf_counter()
    if len(cloud) < MIN_SCENE_POINTS:
        raise EmptySceneError(_empty_message(len(cloud), cloud.stage_counts, params, stack,
                                             fused))
    mixture = fit_mixture(cloud.points, params.criterion, leaf=params.cloud.leaf_m,
                          max_components=params.max_components, tol=params.tol,
                          max_iter=params.max_iter, seed=params.seed,
                          search_points=params.search_points)
    t3 = time.perf_counter()
    ms = cloud.timings_ms
    seconds = {
        "fusion": t1 - t0,  # includes checking and stacking the frames
        "voxel": ms["voxel_ms"] / 1e3,  # back-projection included
        "outliers": ms["outlier_ms"] / 1e3,
        "plane": ms["plane_ms"] / 1e3,
        "cloud": t2 - t1,
        "fit": t3 - t2,
        "total": t3 - t0,
    }
    for a in (cloud.points, cloud.keys, cloud.counts, cloud.pixel_voxel, cloud.pixel_stage):
        a.setflags(write=False)
    return SceneModel(
        depth=fused, intrinsics=camera, cloud=cloud, mixture=mixture, params=params,
        n_frames=n_frames, first_timestamp_us=ts0, last_timestamp_us=ts1, first_index=i0,
        last_index=i1, seconds=seconds,
        created=datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds"),
        version=robot_change.__version__, source=source, mount=mount, noise=profile,
        drift=None if measured is None else measured.drift,
    )


def measured_profile(stack: np.ndarray, noise: NoiseProfile, source: str = ""
                     ) -> tuple[NoiseProfile, FrameNoise | None]:
    """(``noise`` raised where the frames of ``stack`` ((N, H, W) uint16 mm) are noisier
    (:meth:`NoiseProfile.raised_by` with ``RAISE_TOLERANCE``), what they measured); (``noise``
    as it is, None) for one frame."""
    if stack.shape[0] < 2:
        return noise, None
    found = measure_frames(stack)
    if not found.bins:
        return noise, found
    said = f"the {stack.shape[0]} frames of {source or 'the reference'}"
    return noise.raised_by(found.bins, said, tolerance=RAISE_TOLERANCE,
                           flicker_valid=found.flicker_valid,
                           flicker_step=found.flicker_step), found


def build_scene_from_source(
    source: DepthSource,
    n_frames: int = 5,
    params: SceneParams | None = None,
    timeout: float | None = 2.0,
    *,
    intrinsics: Intrinsics | None = None,
) -> SceneModel:
    """Read ``n_frames`` frames from ``source`` and :func:`build_scene` them.

    ``source`` is opened if it is not yet (``open()`` on an open source does nothing); its owner
    closes it.  Each read waits at most ``timeout`` seconds (a camera raises
    :class:`hw.errors.FrameTimeout`); a recording that ends early gives fewer frames (the
    model's ``n_frames`` says how many).  ``intrinsics`` overrides the source's.  The model's
    ``source`` is the source's URI and ``seconds["read"]`` the time spent reading.

    Raises :class:`InputError` when ``n_frames`` < 1 or the source delivers no frame, and
    whatever :func:`build_scene` raises.
    """
    validate.whole("build_scene_from_source", "n_frames", n_frames, 1, 10**6)
    if not isinstance(source, DepthSource):
        raise InputError(f"source must be an hw.depth.DepthSource (from hw.depth.open_depth), "
                         f"got {type(source).__name__}")
    t0 = time.perf_counter()
    source.open()
    frames: list[DepthFrame] = []
    while len(frames) < n_frames:
        frame = source.read(timeout=timeout)
        if frame is None:
            break
        frames.append(frame)
    t_read = time.perf_counter() - t0
    uri = getattr(source, "uri", "") or ""
    if not frames:
        raise InputError(f"depth source {uri!r} delivered no frame (a recording that is "
                         "empty or already played to its end?)")
    model = build_scene(frames, params, intrinsics=intrinsics, source=uri)
    model.seconds["read"] = t_read
    return model


# --------------------------------------------------------------------------- compatibility


def intrinsics_differences(ref: Intrinsics, cur: Intrinsics,
                           tol: float = INTRINSICS_TOLERANCE_PX) -> list[str]:
    """What keeps two cameras apart: their image sizes, else each of fx, fy, cx, cy more than
    ``tol`` pixels apart (``"name ref vs cur px"`` strings; empty: one camera)."""
    if (ref.width, ref.height) != (cur.width, cur.height):
        return [f"image size {ref.width}x{ref.height} vs {cur.width}x{cur.height}"]
    return [f"{name} {getattr(ref, name):.6g} vs {getattr(cur, name):.6g} px"
            for name in ("fx", "fy", "cx", "cy")
            if not abs(float(getattr(ref, name)) - float(getattr(cur, name))) <= tol]


def scene_differences(reference: SceneModel, current) -> tuple[list[str], list[str]]:
    """What keeps ``current`` from being compared with ``reference``.

    ``current``: a SceneModel, or ``(intrinsics, params)`` with params a SceneParams or a
    CloudParams.  Returns (intrinsics differences, cloud parameter differences), each a list of
    ``"name reference vs current"`` strings; both empty when compatible.  Intrinsics agree
    within :data:`INTRINSICS_TOLERANCE_PX`; the cloud parameters compared are
    :data:`COMPARED_CLOUD_FIELDS` (mixture fit options are not: a current view may be fitted
    differently).
    """
    if not isinstance(reference, SceneModel):
        raise InputError(f"reference must be a SceneModel, got {type(reference).__name__}")
    if isinstance(current, SceneModel):
        cam, cloud = current.intrinsics, current.params.cloud.for_camera(current.noise)
    else:
        try:
            cam, params = current
        except (TypeError, ValueError):
            raise InputError("current must be a SceneModel or an (Intrinsics, SceneParams) "
                             "pair") from None
        cloud = params.cloud if isinstance(params, SceneParams) else params
        if not isinstance(cam, Intrinsics) or not isinstance(cloud, CloudParams):
            raise InputError(f"current must be a SceneModel or an (Intrinsics, SceneParams) "
                             f"pair, got ({type(cam).__name__}, {type(params).__name__})")
    ref_cloud = reference.params.cloud.for_camera(reference.noise)
    cloud = cloud.for_camera(reference.noise)  # a pair's unset near range: the reference's
    params_diff = [f"{name} {getattr(ref_cloud, name)!r} vs {getattr(cloud, name)!r}"
                   for name in COMPARED_CLOUD_FIELDS
                   if getattr(ref_cloud, name) != getattr(cloud, name)]
    return intrinsics_differences(reference.intrinsics, cam), params_diff


def check_compatible(reference: SceneModel, current) -> None:
    """Raise :class:`SceneMismatchError` unless ``current`` (a SceneModel or an
    ``(intrinsics, params)`` pair) can be compared with ``reference``: same image size,
    intrinsics within :data:`INTRINSICS_TOLERANCE_PX` pixels, same cloud parameters
    (:data:`COMPARED_CLOUD_FIELDS`).  The message lists every difference (reference vs
    current) and the fix."""
    cam_diff, params_diff = scene_differences(reference, current)
    parts = []
    r = reference.intrinsics
    if cam_diff and cam_diff[0].startswith("image size"):
        parts.append(f"the images differ ({cam_diff[0]}): another camera or mode; capture the "
                     "reference again with this one")
    elif cam_diff:
        # each the shortest text that reads back as the same float (570.342205, 525)
        exact = ",".join(repr(float(v)).removesuffix(".0") for v in (r.fx, r.fy, r.cx, r.cy))
        parts.append(
            f"intrinsics differ ({'; '.join(cam_diff)}): recapture the reference with this "
            f"camera and mode, or give the reference's intrinsics {exact} if it is the "
            f"reference's camera (--intrinsics on the command line, ?intrinsics= on a source "
            f"URI)")
    if params_diff:
        parts.append(
            f"cloud parameters differ ({'; '.join(params_diff)}): recapture the reference with "
            "the current parameters, or run with the reference's (reference.params.cloud)")
    if parts:
        where = f" ({reference.source})" if reference.source else ""
        raise SceneMismatchError(f"the reference{where} cannot be compared with the current "
                                 "view: " + "; ".join(parts))
