"""Point files: clouds written as PCD (PCL's format, through ``pypcd4``), PLY (through
``plyfile``) or ``.npy``, and PCD files read, through one module.

    write_points("appeared.pcd", points, frame="base_link", pose=mount_matrix)
    cloud = read_pcd("scene.pcd")        # PcdCloud: (N, 3) points, width x height, viewpoint

Points are (M, 3) metres.  The frame they are in is said in the file: a PCD's ``VIEWPOINT``
(the camera's pose in that frame: ``tx ty tz qw qx qy qz``) and a ``# frame`` comment line, a
PLY's ``comment frame ...`` and ``comment viewpoint ...`` lines; an ``.npy`` holds the bare
(M, 3) float32 array.  PCD is written binary (``DATA binary``), PLY binary little-endian; both
as float32 ``x y z`` and, with a ``color``, 8-bit ``rgb`` (PCD: PCL's packed ``rgb`` float; PLY:
``red green blue`` uchar).  Every file is written atomically (:mod:`hw.atomic`).

``plyfile`` is GPL-3.0 licensed, so it is an optional extra (``robot-change[ply]``), not a
requirement of this BSD-licensed package: writing ``.ply`` without it raises
:class:`BackendUnavailable` naming what to install.  ``pypcd4`` (BSD) is a dependency.
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
from pathlib import Path

import numpy as np

from hw.atomic import write_atomically
from hw.errors import BackendUnavailable, DepthFileError, FrameError

__all__ = ["FRAMES", "POINT_FORMATS", "PcdCloud", "pose_of_viewpoint", "read_pcd", "viewpoint_of",
           "write_points"]

#: The frames points are written in, and how the files describe them.
FRAMES = {
    "camera_optical": "the camera's optical frame, x right, y down, z forward, metres",
    "base_link": "the robot's base frame, REP 103: x forward, y left, z up, metres",
}
#: File formats :func:`write_points` writes, by file ending.
POINT_FORMATS = ("npy", "pcd", "ply")
#: PCD VIEWPOINT of a camera at the origin of its own frame.
IDENTITY_VIEWPOINT = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


def write_points(path: str | os.PathLike, points: np.ndarray, *, frame: str = "camera_optical",
                 pose: np.ndarray | None = None,
                 color: tuple[int, int, int] | None = None) -> Path:
    """Write (M, 3) points (metres, in ``frame``, one of :data:`FRAMES`) to ``path``, whose
    ending (``.npy``, ``.pcd``, ``.ply``) picks the format.  ``pose``: (4, 4) the camera's pose
    in ``frame`` (camera optical -> frame; default identity), written as the PCD VIEWPOINT and
    a PLY comment; ``color``: (r, g, b) 0..255 given to every point (PCD and PLY).  Returns
    the path.  Raises :class:`FrameError` for bad arguments, :class:`DepthFileError` when the
    file cannot be written, :class:`BackendUnavailable` for ``.ply`` without plyfile.
    """
    target = Path(path)
    kind = target.suffix.lower().lstrip(".")
    if kind not in POINT_FORMATS:
        raise FrameError(f"{target}: a point file ends in " + ", ".join(
            f".{name}" for name in POINT_FORMATS))
    if frame not in FRAMES:
        raise FrameError(f"frame {frame!r}: one of {', '.join(FRAMES)}")
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3 or not np.issubdtype(array.dtype, np.number):
        raise FrameError(f"{target}: points must be an (M, 3) array of numbers, got "
                         f"{array.dtype} {array.shape}")
    array = np.ascontiguousarray(array, dtype=np.float32)
    viewpoint = viewpoint_of(np.eye(4) if pose is None else pose)
    if color is not None and (len(color) != 3 or not all(
            isinstance(c, (int, np.integer)) and 0 <= c <= 255 for c in color)):
        raise FrameError(f"color={color!r}: three whole numbers 0..255 (r, g, b)")
    if kind == "npy":
        buffer = io.BytesIO()
        np.save(buffer, array)
        data = buffer.getvalue()
    elif kind == "pcd":
        data = _pcd_bytes(array, frame, viewpoint, color)
    else:
        data = _ply_bytes(array, frame, viewpoint, color)
    try:
        write_atomically(target, data)
    except OSError as exc:
        raise DepthFileError(f"{target}: cannot write it ({exc.strerror or exc})") from None
    return target


def viewpoint_of(pose: np.ndarray) -> tuple[float, ...]:
    """(4, 4) rigid transform -> PCD VIEWPOINT ``(tx, ty, tz, qw, qx, qy, qz)`` (unit quaternion,
    qw >= 0)."""
    T = np.asarray(pose, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise FrameError(f"pose must be a finite (4, 4) transform, got {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise FrameError("pose: its (3, 3) block is not a rotation")
    # Shepperd's method: the largest of the four squared components first, for accuracy
    trace = np.trace(R)
    squares = [1.0 + trace, 1.0 + 2 * R[0, 0] - trace, 1.0 + 2 * R[1, 1] - trace,
               1.0 + 2 * R[2, 2] - trace]
    k = int(np.argmax(squares))
    s = 2.0 * math.sqrt(squares[k])
    if k == 0:
        q = (s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s)
    elif k == 1:
        q = ((R[2, 1] - R[1, 2]) / s, s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s)
    elif k == 2:
        q = ((R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s)
    else:
        q = ((R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4)
    if q[0] < 0:
        q = tuple(-v for v in q)
    return tuple(round(float(v), 9) + 0.0 for v in (*T[:3, 3], *q))


def pose_of_viewpoint(viewpoint: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """PCD VIEWPOINT -> (4, 4) transform (camera -> the points' frame)."""
    tx, ty, tz, w, x, y, z = (float(v) for v in viewpoint)
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if not norm:
        raise FrameError(f"VIEWPOINT {tuple(viewpoint)}: its quaternion is zero")
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = (tx, ty, tz)
    return T


def _header_comments(frame: str, viewpoint: tuple[float, ...]) -> list[str]:
    return [f"frame {frame}: {FRAMES[frame]}",
            "viewpoint " + " ".join(f"{v:g}" for v in viewpoint)
            + " (the camera's pose in this frame: tx ty tz qw qx qy qz)",
            "written by robot_change"]


def _pcd_bytes(points: np.ndarray, frame: str, viewpoint: tuple[float, ...],
               color: tuple[int, int, int] | None) -> bytes:
    from pypcd4 import Encoding, PointCloud

    columns = [points[:, 0], points[:, 1], points[:, 2]]
    fields, types = ["x", "y", "z"], [np.float32] * 3
    if color is not None:
        rgb = np.tile(np.array(color, np.uint8), (len(points), 1))
        columns.append(PointCloud.encode_rgb(rgb).astype(np.float32))
        fields.append("rgb")
        types.append(np.float32)
    cloud = PointCloud.from_points(columns, tuple(fields), tuple(types))
    cloud.metadata = cloud.metadata.derive(viewpoint=viewpoint)
    buffer = io.BytesIO()
    cloud.save(buffer, encoding=Encoding.BINARY)
    comments = "".join(f"# {line}\n" for line in
                       [".PCD v0.7 - Point Cloud Data file format",
                        *_header_comments(frame, viewpoint)])
    return comments.encode("ascii") + buffer.getvalue()


def _ply_bytes(points: np.ndarray, frame: str, viewpoint: tuple[float, ...],
               color: tuple[int, int, int] | None) -> bytes:
    try:
        from plyfile import PlyData, PlyElement
    except ImportError as exc:
        raise BackendUnavailable(
            f"writing .ply needs plyfile (pip install plyfile, or robot-change[ply]; it is "
            f"GPL-3.0 licensed, hence optional); .pcd and .npy need nothing more: {exc}"
        ) from exc
    names = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if color is not None:
        names += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertices = np.zeros(len(points), dtype=names)
    for axis, name in enumerate("xyz"):
        vertices[name] = points[:, axis]
    if color is not None:
        for channel, name in zip(color, ("red", "green", "blue"), strict=True):
            vertices[name] = channel
    data = PlyData([PlyElement.describe(vertices, "vertex")], text=False, byte_order="<",
                   comments=_header_comments(frame, viewpoint))
    buffer = io.BytesIO()
    data.write(buffer)
    return buffer.getvalue()


# --- reading ----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class PcdCloud:
    """A PCD file's points: ``points`` (width * height, 3) float32 in the file's frame (NaN
    where there is none), row by row; ``width``, ``height`` (> 1: organized, one point per
    pixel of an image); ``viewpoint`` (7,) the sensor's pose in that frame."""

    points: np.ndarray
    width: int
    height: int
    viewpoint: tuple[float, ...]

    @property
    def organized(self) -> bool:
        return self.height > 1


def read_pcd(path: str | os.PathLike) -> PcdCloud:
    """Read a PCD file (ascii, binary or binary_compressed; any fields, of which ``x y z`` are
    taken).  Raises :class:`DepthFileError` naming the file for a missing, foreign or broken
    one."""
    from pypcd4 import PointCloud

    where = Path(path)
    if not where.is_file():
        raise DepthFileError(f"{where}: no such file" if not where.exists() else
                             f"{where}: is a folder, expected a .pcd file")
    with open(where, "rb") as handle:
        start = handle.read(4096)
    if b"FIELDS" not in start and b"VERSION" not in start:
        raise DepthFileError(f"{where}: not a PCD file (no PCD header at its start)")
    try:
        cloud = PointCloud.from_path(where)
        fields = cloud.fields
        if not {"x", "y", "z"} <= set(fields):
            raise DepthFileError(f"{where}: the PCD has fields {' '.join(fields)}, not x y z")
        points = np.ascontiguousarray(cloud.numpy(("x", "y", "z")), dtype=np.float32)
        meta = cloud.metadata
    except DepthFileError:
        raise
    except Exception as exc:  # noqa: BLE001 - pypcd4's errors on a broken file are of any kind
        raise DepthFileError(f"{where}: truncated or broken PCD ({type(exc).__name__}: "
                             f"{exc})") from None
    width, height = int(meta.width), int(meta.height)
    if len(points) != width * height:
        raise DepthFileError(f"{where}: the header says {width} x {height} points, the data "
                             f"holds {len(points)}")
    return PcdCloud(points.reshape(-1, 3), width, height, tuple(float(v) for v in meta.viewpoint))
