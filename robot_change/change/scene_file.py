"""The scene file: a :class:`robot_change.change.scene.SceneModel` as one checksummed,
versioned .npz (robot_change.npzfile): its arrays, its header (provenance, parameters, the
camera's noise profile, the fit record), and reading it back with every check.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hw.depth import Intrinsics
from hw.errors import FrameError
from robot_change import npzfile
from robot_change.change.mount import CameraMount
from robot_change.change.scene import FILE_FORMAT, FILE_VERSION, SceneParams
from robot_change.cloud.chain import PIXEL_KEPT, CleanCloud, clean_cloud
from robot_change.cloud.plane import Plane
from robot_change.errors import InputError, SceneFileError
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


def arrays_of(model: SceneModel) -> dict[str, np.ndarray]:
    c, m = model.cloud, model.mixture
    raw = {
        "depth": model.depth, "points": c.points, "keys": c.keys, "counts": c.counts,
        "pixel_voxel": c.pixel_voxel, "pixel_stage": c.pixel_stage,
        "plane_normal": c.plane.normal, "plane_inliers": c.plane.inliers,
        "weights": m.weights, "means": m.means, "covariances": m.covariances,
    }
    return {k: np.ascontiguousarray(raw[k], dtype=np.dtype(dt)) for k, (dt, _) in _ARRAYS.items()}


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
    }


def load_model(cls, path: Path) -> SceneModel:
    redo = "build and save the reference again"
    header, arrays = npzfile.read(path, FILE_FORMAT, FILE_VERSION, _ARRAYS, SceneFileError, redo)
    try:
        return _model_from(cls, header, arrays)
    except SceneFileError:
        raise
    except (InputError, FrameError, KeyError, TypeError, ValueError) as exc:
        raise SceneFileError(f"{path}: the file does not hold a valid scene "
                             f"({type(exc).__name__}: {exc}); {redo}") from exc


def _model_from(cls, header: dict[str, Any], arrays: dict[str, np.ndarray]) -> SceneModel:
    for name, (dtype, ndim) in _ARRAYS.items():
        a = arrays[name]
        if a.dtype != np.dtype(dtype) or a.ndim != ndim:
            raise SceneFileError(f"array {name!r} is {a.dtype} with {a.ndim} dimensions, "
                                 f"expected {np.dtype(dtype)} with {ndim}")
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
    ]
    for ok, what in checks:
        if not ok:
            raise SceneFileError(what)
    for a in arrays.values():
        a.setflags(write=False)
    ch = header["cloud"]
    plane = Plane(normal=arrays["plane_normal"], offset=float(ch["plane_offset"]),
                  inliers=arrays["plane_inliers"], n_inliers=int(ch["plane_n_inliers"]),
                  iterations=int(ch["plane_iterations"]))
    if header["version"] == 1:
        # keys in the old layout: rebuild the cloud as this version makes it
        cloud = clean_cloud(arrays["depth"], camera, params.cloud)
    else:
        cloud = CleanCloud(
            points=arrays["points"], keys=arrays["keys"], counts=arrays["counts"],
            pixel_voxel=arrays["pixel_voxel"], pixel_stage=arrays["pixel_stage"], plane=plane,
            stage_counts={k: int(v) for k, v in ch["stage_counts"].items()},
            timings_ms={k: float(v) for k, v in ch["timings_ms"].items()}, params=params.cloud,
        )
    mixture = Mixture(arrays["weights"], arrays["means"], arrays["covariances"],
                      _record_from_dict(header["fit"]))

    def opt_int(key):
        v = header[key]
        return None if v is None else int(v)

    return cls(
        depth=arrays["depth"], intrinsics=camera, cloud=cloud, mixture=mixture, params=params,
        n_frames=int(header["n_frames"]), first_timestamp_us=opt_int("first_timestamp_us"),
        last_timestamp_us=opt_int("last_timestamp_us"), first_index=opt_int("first_index"),
        last_index=opt_int("last_index"),
        seconds={k: float(v) for k, v in header["seconds"].items()},
        created=str(header["created"]), version=str(header["library_version"]),
        source=str(header["source"]), mount=_mount_from(header.get("mount")),
        noise=_noise_from(header.get("noise")),
    )


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
