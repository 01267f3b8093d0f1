"""A check as Foxglove shows it: a :class:`~robot_change.change.results.ChangeSet`, the
reference it was compared with, the current depth image and the camera's mounting -> one
message per topic of :data:`TOPICS`, in foxglove-sdk's well-known schemas (protobuf) and one
JSON channel.  The MCAP writer (:mod:`robot_change.export.mcap`) and the live server
(:mod:`robot_change.export.live`) log the same messages on the same channels
(:class:`CheckChannels`).

Frames (REP 103 axes; every message is stamped with the check's time, the transforms too, so
Foxglove's 3-D panel draws everything in ``base_link`` with no set-up)::

    base_link                       the robot now: x forward, y left, z up
     +- camera_link                 the camera's body frame on the base (CameraMount)
         +- camera_optical          the current camera: x right, y down, z forward
             +- reference_camera_optical   where the camera stood for the reference:
                 |                         inverse of the registration's T_ref_from_cur
                 +- reference_base_link    the robot at its station pose (same mounting)

The change's own geometry (appeared and disappeared points, novelty components, region boxes)
is in ``camera_optical``, as in the ChangeSet; the reference's cloud, mixture and depth image
are in ``reference_camera_optical``, as they were captured, and the transform puts them in
place.  Each depth image has a CameraCalibration of the same frame on the sibling topic
``.../camera_info``.
"""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from robot_change import json_text
from robot_change.change.epoch import as_epoch
from robot_change.change.mount import BODY_FROM_OPTICAL, CameraMount
from robot_change.change.registration import invert, rpy_deg_to_rotation
from robot_change.change.results import ChangeSet
from robot_change.errors import InputError
from robot_change.export import APPEARED_RGB, DISAPPEARED_RGB
from robot_change.mixture.model import Mixture

__all__ = [
    "FRAMES",
    "POINT_DTYPE",
    "REPORT_SCHEMA_NAME",
    "SIGMAS",
    "TOPICS",
    "CheckChannels",
    "check_messages",
    "ellipsoid_axes",
    "region_label",
    "sdk",
]

#: The frame ids, parent first (module docstring).
FRAMES = ("base_link", "camera_link", "camera_optical", "reference_camera_optical",
          "reference_base_link")
#: topic -> schema: a foxglove-sdk message class name, or "json" (the report dict).
TOPICS = {
    "/tf": "FrameTransforms",
    "/current/depth/image": "RawImage",
    "/current/depth/camera_info": "CameraCalibration",
    "/reference/depth/image": "RawImage",
    "/reference/depth/camera_info": "CameraCalibration",
    "/current/cloud": "PointCloud",
    "/reference/cloud": "PointCloud",
    "/change/appeared": "PointCloud",
    "/change/disappeared": "PointCloud",
    "/reference/mixture": "SceneUpdate",
    "/change/novelty": "SceneUpdate",
    "/change/regions": "SceneUpdate",
    "/check/report": "json",
    "/check/log": "Log",
}
#: Schema name of the JSON report channel.
REPORT_SCHEMA_NAME = "robot_change.CheckReport"
#: Ellipsoids of the mixtures span this many standard deviations each way.
SIGMAS = 3.0

# colours (r, g, b) in 0..1
_CLOUD_CURRENT = (0.55, 0.75, 1.0)
_CLOUD_REFERENCE = (1.0, 0.75, 0.5)
_LOW_WEIGHT = np.array([0.15, 0.35, 1.0])  # the lightest component of a mixture ...
_HIGH_WEIGHT = np.array([1.0, 0.85, 0.1])  # ... and the heaviest


def sdk() -> Any:
    """The ``foxglove`` package (foxglove-sdk), with its messages and channels, or an
    InputError naming the extra that brings it."""
    try:
        import foxglove
        import foxglove.channels  # noqa: F401
        import foxglove.messages  # noqa: F401
    except ImportError as exc:
        raise InputError("Foxglove views of a check need foxglove-sdk: install the 'viz' extra "
                         "(./setup.sh viz, or pip install 'robot-change[viz]')") from exc
    return foxglove


# ---------------------------------------------------------------------------------------------
# geometry


def ellipsoid_axes(covariance: np.ndarray, sigmas: float = SIGMAS
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The ellipsoid ``sigmas`` standard deviations out of a (3, 3) covariance (m^2): its
    diameters (3,) metres along the columns of a proper rotation (3, 3) (the eigenvectors,
    det +1)."""
    values, vectors = np.linalg.eigh(np.asarray(covariance, dtype=np.float64))
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] = -vectors[:, 0]
    return 2.0 * sigmas * np.sqrt(np.clip(values, 0.0, None)), vectors


def _quaternion(m: Any, rotation: np.ndarray) -> Any:
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return m.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


def _vector(m: Any, v: Any) -> Any:
    return m.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _pose(m: Any, position: Any, rotation: np.ndarray | None = None) -> Any:
    return m.Pose(position=_vector(m, position),
                  orientation=_quaternion(m, np.eye(3) if rotation is None else rotation))


def _color(m: Any, rgb: Any, alpha: float) -> Any:
    return m.Color(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=float(alpha))


def _transforms(m: Any, stamp: Any, mount: CameraMount, T_ref_from_cur: np.ndarray) -> Any:
    """FrameTransforms of :data:`FRAMES`: each child's pose in its parent."""
    body = np.eye(4)
    body[:3, :3] = rpy_deg_to_rotation(*mount.rpy_deg)
    body[:3, 3] = mount.xyz_m
    optical = np.eye(4)
    optical[:3, :3] = BODY_FROM_OPTICAL
    chain = ((FRAMES[0], FRAMES[1], body), (FRAMES[1], FRAMES[2], optical),
             (FRAMES[2], FRAMES[3], invert(T_ref_from_cur)),
             (FRAMES[3], FRAMES[4], invert(mount.base_from_optical())))
    return m.FrameTransforms(transforms=[
        m.FrameTransform(timestamp=stamp, parent_frame_id=parent, child_frame_id=child,
                         translation=_vector(m, T[:3, 3]), rotation=_quaternion(m, T[:3, :3]))
        for parent, child, T in chain])


# ---------------------------------------------------------------------------------------------
# images and clouds


def _image(m: Any, stamp: Any, frame: str, depth: np.ndarray) -> Any:
    """RawImage 16UC1 (millimetres, 0 = no reading) of an (H, W) uint16 depth image."""
    h, w = depth.shape
    return m.RawImage(timestamp=stamp, frame_id=frame, width=w, height=h, encoding="16UC1",
                      step=2 * w, data=np.ascontiguousarray(depth, dtype="<u2").tobytes())


def _calibration(m: Any, stamp: Any, frame: str, camera: Any) -> Any:
    """CameraCalibration of the pinhole intrinsics (no distortion: the images are plumb)."""
    fx, fy, cx, cy = (float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    return m.CameraCalibration(
        timestamp=stamp, frame_id=frame, width=camera.width, height=camera.height,
        distortion_model="plumb_bob", D=[0.0] * 5, K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])


#: One point of a PointCloud: x, y, z float32 metres, then red, green, blue, alpha uint8.
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                        ("green", "u1"), ("blue", "u1"), ("alpha", "u1")])


def _cloud(m: Any, stamp: Any, frame: str, points: np.ndarray, rgb: tuple[float, ...]) -> Any:
    """PointCloud of (M, 3) points (metres) in one colour."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    packed = np.empty(len(pts), POINT_DTYPE)
    for axis, name in enumerate("xyz"):
        packed[name] = pts[:, axis]
    for value, name in zip(rgb, ("red", "green", "blue"), strict=True):
        packed[name] = round(255 * value)
    packed["alpha"] = 255
    kinds = m.PackedElementFieldNumericType
    fields = [m.PackedElementField(name=name, offset=POINT_DTYPE.fields[name][1],
                                   type=kinds.Float32 if name in "xyz" else kinds.Uint8)
              for name in POINT_DTYPE.names]
    return m.PointCloud(timestamp=stamp, frame_id=frame, pose=_pose(m, (0, 0, 0)),
                        point_stride=POINT_DTYPE.itemsize, fields=fields,
                        data=packed.tobytes())


# ---------------------------------------------------------------------------------------------
# scene entities


def _ellipsoids(m: Any, stamp: Any, frame: str, mixture: Mixture, rows: Any, prefix: str,
                colors: list[tuple[Any, float]]) -> list[Any]:
    """One SceneEntity (a SpherePrimitive scaled and turned by the covariance, SIGMAS out)
    per component ``rows`` of ``mixture``, each in its (rgb, alpha)."""
    out = []
    for k, (rgb, alpha) in zip(rows, colors, strict=False):
        size, rotation = ellipsoid_axes(mixture.covariances[k])
        sphere = m.SpherePrimitive(pose=_pose(m, mixture.means[k], rotation),
                                   size=_vector(m, size), color=_color(m, rgb, alpha))
        out.append(m.SceneEntity(
            timestamp=stamp, frame_id=frame, id=f"{prefix}{k}", spheres=[sphere],
            metadata=[m.KeyValuePair(key="component", value=str(int(k))),
                      m.KeyValuePair(key="weight", value=f"{float(mixture.weights[k]):.4f}")]))
    return out


def _scene(m: Any, stamp: Any, entities: list[Any]) -> Any:
    """A SceneUpdate that replaces everything the topic showed before."""
    clear = m.SceneEntityDeletion(timestamp=stamp, type=m.SceneEntityDeletionType.All)
    return m.SceneUpdate(deletions=[clear], entities=entities)


def region_label(number: int, region: Any) -> str:
    """``"appeared 1: 412 points, 0.31 x 0.25 x 0.40 m, 2.21 m away"`` (distance from the
    camera to the region's centroid)."""
    size = " x ".join(f"{v:.2f}" for v in region.extent)
    return (f"{region.kind} {number}: {region.n_points} points, {size} m, "
            f"{float(np.linalg.norm(region.centroid)):.2f} m away")


def _regions(m: Any, stamp: Any, changes: ChangeSet) -> list[Any]:
    """A translucent box (CubePrimitive) per region, with its label above it (optical frame:
    up is -y)."""
    out = []
    for number, region in enumerate(changes.regions, 1):
        rgb = APPEARED_RGB if region.kind == "appeared" else DISAPPEARED_RGB
        centre = (np.asarray(region.bbox_min) + np.asarray(region.bbox_max)) / 2.0
        top = (centre[0], float(region.bbox_min[1]) - 0.05, centre[2])
        out.append(m.SceneEntity(
            timestamp=stamp, frame_id=FRAMES[2], id=f"region_{number}",
            cubes=[m.CubePrimitive(pose=_pose(m, centre), size=_vector(m, region.extent),
                                   color=_color(m, rgb, 0.3))],
            texts=[m.TextPrimitive(pose=_pose(m, top), billboard=True, font_size=14.0,
                                   scale_invariant=True, color=_color(m, rgb, 1.0),
                                   text=region_label(number, region))],
            metadata=[m.KeyValuePair(key="kind", value=region.kind),
                      m.KeyValuePair(key="points", value=str(region.n_points))]))
    return out


def _novelty(m: Any, stamp: Any, changes: ChangeSet) -> list[Any]:
    """The components each direction's greedy EMD could remove (the novelty components), the
    accepted ones (the change) drawn stronger."""
    out = []
    for kind, mixture, trace, rgb in (
            ("appeared", changes.appeared_mixture, changes.greedy_appeared, APPEARED_RGB),
            ("disappeared", changes.disappeared_mixture, changes.greedy_disappeared,
             DISAPPEARED_RGB)):
        if mixture is None or trace is None:
            continue
        accepted = {int(k) for k in trace.change}
        rows = [int(k) for k in trace.candidates]
        colors = [(rgb, 0.5 if k in accepted else 0.15) for k in rows]
        out += _ellipsoids(m, stamp, FRAMES[2], mixture, rows, f"{kind}_novelty_", colors)
    return out


def _weight_colors(mixture: Mixture) -> list[tuple[Any, float]]:
    t = mixture.weights / max(float(mixture.weights.max()), 1e-12)
    return [(tuple(_LOW_WEIGHT + (_HIGH_WEIGHT - _LOW_WEIGHT) * float(v)), 0.35) for v in t]


def _log_text(changes: ChangeSet, report: dict) -> str:
    station = f"{report['station']}: " if report.get("station") else ""
    reg = changes.registration
    head = (f"{station}{changes.outcome}; registration "
            f"{1e3 * float(np.linalg.norm(reg.translation_m)):.0f} mm "
            f"{reg.rotation_deg:.1f} deg, fitness {reg.fitness:.2f}")
    if changes.not_at_station_reason:
        head += f" ({changes.not_at_station_reason})"
    return "; ".join([head] + [region_label(n, r) for n, r in enumerate(changes.regions, 1)])


# ---------------------------------------------------------------------------------------------
# the messages of a check


#: the default camera mount (frozen, built once)
_DEFAULT_MOUNT = CameraMount()


def check_messages(reference: Any, current_depth: np.ndarray, changes: ChangeSet,
                   mount: CameraMount = _DEFAULT_MOUNT, *, report: dict | None = None,
                   stamp_ns: int | None = None) -> list[tuple[str, Any]]:
    """The check as (topic, message) pairs, one per topic of :data:`TOPICS`, transforms first.

    ``reference``: the SceneModel (or Epoch) the check compared with; ``current_depth``: the
    (H, W) uint16 mm image it compared (the reference's intrinsics); ``changes``: its result;
    ``mount``: the camera on the base; ``report``: the JSON report (default
    ``changes.summary(mount)``, what report.json holds); ``stamp_ns``: the time of the check,
    ns since the epoch (default now), stamped on every message.  Raises InputError without
    foxglove-sdk, or when the current image does not fit the reference's intrinsics.
    """
    fox = sdk()
    m = fox.messages
    ref = as_epoch(reference, "reference")
    camera = ref.intrinsics
    depth = np.asarray(current_depth)
    if depth.dtype != np.uint16 or depth.shape != (camera.height, camera.width):
        raise InputError(f"current depth must be an ({camera.height}, {camera.width}) uint16 "
                         f"image like the reference's, got {depth.dtype} {depth.shape}")
    stamp_ns = time.time_ns() if stamp_ns is None else int(stamp_ns)
    stamp = m.Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)
    report = changes.summary(mount) if report is None else report
    current_points = (changes.current_points if changes.current_points is not None
                      else changes.appeared_points)
    current, reference_frame = FRAMES[2], FRAMES[3]
    mixture_entities = ([] if ref.mixture is None else _ellipsoids(
        m, stamp, reference_frame, ref.mixture, range(ref.mixture.n_components),
        "reference_component_", _weight_colors(ref.mixture)))
    level = m.LogLevel.Warning if changes.outcome != "no_change" else m.LogLevel.Info
    messages = {
        "/tf": _transforms(m, stamp, mount, changes.registration.T_ref_from_cur),
        "/current/depth/image": _image(m, stamp, current, depth),
        "/current/depth/camera_info": _calibration(m, stamp, current, camera),
        "/reference/depth/image": _image(m, stamp, reference_frame, ref.depth),
        "/reference/depth/camera_info": _calibration(m, stamp, reference_frame, camera),
        "/current/cloud": _cloud(m, stamp, current, current_points, _CLOUD_CURRENT),
        "/reference/cloud": _cloud(m, stamp, reference_frame, ref.points, _CLOUD_REFERENCE),
        "/change/appeared": _cloud(m, stamp, current, changes.appeared_points, APPEARED_RGB),
        "/change/disappeared": _cloud(m, stamp, current, changes.disappeared_points,
                                      DISAPPEARED_RGB),
        "/reference/mixture": _scene(m, stamp, mixture_entities),
        "/change/novelty": _scene(m, stamp, _novelty(m, stamp, changes)),
        "/change/regions": _scene(m, stamp, _regions(m, stamp, changes)),
        "/check/report": report,
        "/check/log": m.Log(timestamp=stamp, level=level, name="robot_change",
                            message=_log_text(changes, report)),
    }
    return list(messages.items())


class CheckChannels:
    """The channels of :data:`TOPICS` in a foxglove Context of their own: whatever sinks the
    context has (an MCAP file, a WebSocket server) get what :meth:`log` logs."""

    def __init__(self) -> None:
        fox = sdk()
        self.fox = fox
        self.context = fox.Context()
        self.channels: dict[str, Any] = {}
        for topic, schema in TOPICS.items():
            if schema == "json":
                report_schema = fox.Schema(name=REPORT_SCHEMA_NAME, encoding="jsonschema",
                                           data=json.dumps({"type": "object"}).encode())
                self.channels[topic] = fox.Channel(topic, schema=report_schema,
                                                   message_encoding="json",
                                                   context=self.context)
            else:
                channel_class = getattr(fox.channels, f"{schema}Channel")
                self.channels[topic] = channel_class(topic, context=self.context)

    def log(self, topic: str, message: Any, stamp_ns: int) -> None:
        """Log one message of :func:`check_messages` (log time ``stamp_ns``)."""
        if TOPICS[topic] == "json":
            message = json_text.dumps(message).encode()
        self.channels[topic].log(message, log_time=int(stamp_ns))

    def log_all(self, messages: list[tuple[str, Any]], stamp_ns: int) -> None:
        for topic, message in messages:
            self.log(topic, message, stamp_ns)
