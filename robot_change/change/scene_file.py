"""The scene file: a :class:`robot_change.change.scene.SceneModel` as one checksummed,
versioned .npz (robot_change.npzfile): its arrays, its header (provenance, parameters, the
camera's noise profile, the fit record), and reading it back with every check.

A reference comes from disk, where anything can happen to it: every way a file can be bad
(damaged, crafted, of another version) ends as :class:`SceneFileError`, and the arrays' sizes
are checked against the header's camera before any is read, so checking a file never takes
more than :data:`robot_change.npzfile.MAX_BYTES` (~128 MiB) however large it claims to be.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hw.depth import Intrinsics
from hw.errors import FrameError
from robot_change import npzfile
from robot_change.change.mount import CameraMount
from robot_change.change.scene_params import (
    FILE_FORMAT,
    FILE_VERSION,
    MIN_SCENE_POINTS,
    SceneParams,
)
from robot_change.cloud.chain import PIXEL_KEPT, CleanCloud, clean_cloud
from robot_change.cloud.plane import Plane
from robot_change.errors import SceneFileError
from robot_change.mixture.model import FitRecord, FitStep, Mixture
from robot_change.noise.profile import DEFAULT_PROFILE, NoiseProfile, builtin_profile

if TYPE_CHECKING:
    from robot_change.change.scene import SceneModel

__all__ = ["arrays_of", "header_of", "load_model"]

#: name -> (dtype, number of dimensions) of every array in a scene file.
_ARRAYS = {
    "depth": ("<u2", 2),
    "points": ("<f4", 2),
    "keys": ("<i8", 1),
    "counts": ("<i4", 1),
    "pixel_voxel": ("<i4", 2),
    "pixel_stage": ("|u1", 2),
    "plane_normal": ("<f8", 1),
    "plane_inliers": ("|b1", 1),
    "weights": ("<f8", 1),
    "means": ("<f8", 2),
    "covariances": ("<f8", 3),
}
#: The largest reference image (pixels): above every depth camera's (Azure Kinect WFOV
#: 1024 x 1024, stereo 1280 x 720, structured light 2064 x 1544), far below what would not
#: fit the service's memory.
MAX_PIXELS = 2048 * 2048
#: The most mixture components a reference may hold (a fit stops at tens).
MAX_COMPONENTS = 4096
#: The largest whole number a header field may hold (int64, what numpy takes).
_MAX_WHOLE = 2**63 - 1


def arrays_of(model: SceneModel) -> dict[str, np.ndarray]:
    c, m = model.cloud, model.mixture
    raw = {
        "depth": model.depth, "points": c.points, "keys": c.keys, "counts": c.counts,
        "pixel_voxel": c.pixel_voxel, "pixel_stage": c.pixel_stage,
        "plane_normal": c.plane.normal, "plane_inliers": c.plane.inliers,
        "weights": m.weights, "means": m.means, "covariances": m.covariances,
    }
    return {k: np.ascontiguousarray(raw[k], dtype=np.dtype(dt)) for k, (dt, _) in _ARRAYS.items()}


#: How far (metres) a mixture's means may lie outside its cloud's box (:func:`_check_fitted_to`).
_FIT_SLACK_M = 0.5


def _record_to_dict(record: FitRecord | None) -> dict | None:
    if record is None:
        return None
    d = dataclasses.asdict(record)
    d["steps"] = [dataclasses.asdict(s) for s in record.steps]
    return d


def _record_from_dict(d: dict | None) -> FitRecord | None:
    if d is None:
        return None
    d = dict(d)
    d["steps"] = tuple(FitStep(**s) for s in d["steps"])
    return FitRecord(**d)


def header_of(model: SceneModel) -> dict[str, Any]:
    """The header fields of a scene (robot_change.npzfile adds format, version, saved_by, the
    arrays' dtypes and shapes and the checksum)."""
    c = model.cloud
    return {
        "library_version": model.version,
        "created": model.created,
        "source": model.source,
        "mount": None if model.mount is None else model.mount.to_dict(),
        "n_frames": model.n_frames,
        "first_timestamp_us": model.first_timestamp_us,
        "last_timestamp_us": model.last_timestamp_us,
        "first_index": model.first_index,
        "last_index": model.last_index,
        "seconds": dict(model.seconds),
        "intrinsics": dataclasses.asdict(model.intrinsics),
        "params": model.params.to_dict(),
        "cloud": {
            "stage_counts": dict(c.stage_counts),
            "timings_ms": dict(c.timings_ms),
            "plane_offset": c.plane.offset,
            "plane_n_inliers": c.plane.n_inliers,
            "plane_iterations": c.plane.iterations,
        },
        "fit": _record_to_dict(model.mixture.record),
        "noise": model.noise.to_dict(),
        "drift": model.drift,
    }


def load_model(cls, path: Path) -> SceneModel:
    """The scene saved at ``path``, every part checked: :class:`SceneFileError` for any way
    the file can be bad (``FileNotFoundError`` when there is none, ``OSError`` when it cannot
    be read)."""
    redo = "build and save the reference again"
    header, arrays = npzfile.read(path, FILE_FORMAT, FILE_VERSION, _ARRAYS, SceneFileError, redo,
                                  limits=_check_declared)
    try:
        return _model_from(cls, header, arrays)
    except SceneFileError as exc:
        raise SceneFileError(f"{path}: {exc}; {redo}") from exc
    except Exception as exc:  # anything a crafted header or array can raise deeper in
        raise SceneFileError(f"{path}: the file does not hold a valid scene "
                             f"({type(exc).__name__}: {exc}); {redo}") from exc


def _check_declared(header: dict[str, Any], declared: npzfile.Declared) -> None:
    """Every array's dtype and shape against the header's camera and the limits, before any
    is read (``declared``: name -> (dtype, shape) from the members' own headers)."""
    try:
        camera = Intrinsics(**header["intrinsics"])
    except (KeyError, TypeError, FrameError) as exc:
        raise SceneFileError(f"the header's intrinsics are not valid ({exc})") from None
    if camera.width * camera.height > MAX_PIXELS:
        raise SceneFileError(f"the camera is {camera.width}x{camera.height}, more than the "
                             f"{MAX_PIXELS} pixels a reference may have")
    for name, (dtype, ndim) in _ARRAYS.items():
        got, shape = declared[name]
        if got != np.dtype(dtype) or len(shape) != ndim:
            raise SceneFileError(f"array {name!r} is {got} with {len(shape)} dimensions, "
                                 f"expected {np.dtype(dtype)} with {ndim}")
    image = (camera.height, camera.width)
    m, k = declared["points"][1][0], declared["weights"][1][0]
    expected = {"depth": image, "pixel_voxel": image, "pixel_stage": image, "points": (m, 3),
                "keys": (m,), "counts": (m,), "plane_normal": (3,), "weights": (k,),
                "means": (k, 3), "covariances": (k, 3, 3)}
    for name, shape in expected.items():
        if declared[name][1] != shape:
            raise SceneFileError(f"array {name!r} is {declared[name][1]}, expected {shape} for "
                                 f"a {camera.width}x{camera.height} camera with {m} points and "
                                 f"{k} components")
    pixels = camera.width * camera.height
    if m > pixels or declared["plane_inliers"][1][0] > pixels:
        raise SceneFileError(f"{m} points for {pixels} pixels")
    if not 1 <= k <= MAX_COMPONENTS:
        raise SceneFileError(f"{k} mixture components (1..{MAX_COMPONENTS})")


def _whole(value: Any, what: str, lo: int = 0, hi: int = _MAX_WHOLE) -> int:
    """``value`` if it is a whole number in lo..hi (JSON can hold Infinity, 1e999, 2.5, true)."""
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise SceneFileError(f"{what} = {value!r} is not a whole number in {lo}..{hi}")
    return value


def _finite(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneFileError(f"{what} = {value!r} is not a finite number")
    return float(value)


def _model_from(cls, header: dict[str, Any], arrays: dict[str, np.ndarray]) -> SceneModel:
    """The scene of a file whose arrays passed :func:`_check_declared`: their contents and
    the header's numbers checked here."""
    params = SceneParams.from_dict(header["params"])
    camera = Intrinsics(**header["intrinsics"])
    m = arrays["points"].shape[0]
    shape = arrays["depth"].shape
    checks = [
        (arrays["points"].shape == (m, 3), "points is not (M, 3)"),
        (arrays["keys"].shape == (m,) and arrays["counts"].shape == (m,),
         "keys / counts do not match points"),
        (arrays["pixel_voxel"].shape == shape and arrays["pixel_stage"].shape == shape,
         "pixel_voxel / pixel_stage do not match the depth image"),
        (m == 0 or (arrays["pixel_voxel"].min() >= -1 and arrays["pixel_voxel"].max() < m),
         "pixel_voxel points outside the cloud"),
        (arrays["pixel_stage"].max(initial=0) <= PIXEL_KEPT, "pixel_stage has unknown codes"),
        (arrays["plane_normal"].shape == (3,), "plane_normal is not a 3-vector"),
        (m >= MIN_SCENE_POINTS or header["version"] == 1,
         f"the scene holds {m} points (at least {MIN_SCENE_POINTS})"),
        (bool(np.isfinite(arrays["points"]).all()), "points holds NaN or infinite coordinates"),
        (m == 0 or arrays["counts"].min() >= 1, "counts holds voxels of no point"),
    ]
    for ok, what in checks:
        if not ok:
            raise SceneFileError(what)
    for a in arrays.values():
        a.setflags(write=False)
    ch = header["cloud"]
    n_inliers = _whole(ch["plane_n_inliers"], "cloud.plane_n_inliers", 0,
                       arrays["plane_inliers"].size)
    offset = ch["plane_offset"]
    if n_inliers or offset is not None and not (isinstance(offset, float) and math.isnan(offset)):
        offset = _finite(offset, "cloud.plane_offset")  # NaN only when no plane was found
    plane = Plane(normal=arrays["plane_normal"], offset=float("nan") if offset is None
                  else float(offset), inliers=arrays["plane_inliers"], n_inliers=n_inliers,
                  iterations=_whole(ch["plane_iterations"], "cloud.plane_iterations"))
    if header["version"] == 1:
        # keys in the old layout: rebuild the cloud as this version makes it
        cloud = clean_cloud(arrays["depth"], camera, params.cloud)
    else:
        cloud = CleanCloud(
            points=arrays["points"], keys=arrays["keys"], counts=arrays["counts"],
            pixel_voxel=arrays["pixel_voxel"], pixel_stage=arrays["pixel_stage"], plane=plane,
            stage_counts={k: _whole(v, f"cloud.stage_counts.{k}")
                          for k, v in ch["stage_counts"].items()},
            timings_ms={k: _finite(v, f"cloud.timings_ms.{k}")
                        for k, v in ch["timings_ms"].items()}, params=params.cloud,
        )
    mixture = Mixture(arrays["weights"], arrays["means"], arrays["covariances"],
                      _record_from_dict(header["fit"]))
    _check_fitted_to(mixture, cloud.points)

    def opt_int(key, lo=0):
        v = header[key]
        return None if v is None else _whole(v, key, lo)

    return cls(
        depth=arrays["depth"], intrinsics=camera, cloud=cloud, mixture=mixture, params=params,
        n_frames=_whole(header["n_frames"], "n_frames", 1),
        first_timestamp_us=opt_int("first_timestamp_us", -_MAX_WHOLE),
        last_timestamp_us=opt_int("last_timestamp_us", -_MAX_WHOLE),
        first_index=opt_int("first_index"), last_index=opt_int("last_index"),
        seconds={k: _finite(v, f"seconds.{k}") for k, v in header["seconds"].items()},
        created=str(header["created"]), version=str(header["library_version"]),
        source=str(header["source"]), mount=_mount_from(header.get("mount")),
        noise=_noise_from(header.get("noise")),
        drift=None if header.get("drift") is None else _finite(header["drift"], "drift"),
    )


def _check_fitted_to(mixture: Mixture, points: np.ndarray) -> None:
    """A SceneFileError unless ``mixture`` could have been fitted to ``points`` (M, 3) m: its
    means within their box and no component wider than it (an EM component is a weighted mean
    and covariance of the points, plus a regularisation of millimetres); ``_FIT_SLACK_M``
    spares a version-1 file, whose cloud is made again.  A crafted mean of 1e300 m passed
    every other check and made the distances infinite deep in a check."""
    if not len(points):
        return
    lo = points.min(axis=0) - _FIT_SLACK_M
    hi = points.max(axis=0) + _FIT_SLACK_M
    if not ((mixture.means >= lo) & (mixture.means <= hi)).all():
        raise SceneFileError("the mixture's means lie outside the cloud it was fitted to")
    widest = float(((hi - lo) ** 2).max())
    if float(np.diagonal(mixture.covariances, axis1=1, axis2=2).max()) > widest:
        raise SceneFileError("a mixture component is wider than the cloud it was fitted to")


def _mount_from(d: Any) -> CameraMount | None:
    """The header's ``mount`` (absent in files from before it was recorded: None)."""
    if d is None:
        return None
    if not isinstance(d, dict) or "xyz_m" not in d or "rpy_deg" not in d:
        raise SceneFileError(f"mount {d!r} is not an object with xyz_m and rpy_deg")
    return CameraMount(tuple(d["xyz_m"]), tuple(d["rpy_deg"]))


def _noise_from(d: Any) -> NoiseProfile:
    """The header's ``noise`` (absent in files from before profiles: the default built-in,
    the profile every check used then)."""
    if d is None:
        return builtin_profile(DEFAULT_PROFILE)
    return NoiseProfile.from_dict(d, "noise")
