"""What a RealSense recording looks like as a bag: librealsense's layout, for the bag backend
(:mod:`hw.rosbag`, no librealsense needed) and the RealSense backend's file check.

librealsense's recorder writes a ROS bag with one namespace per stream:
``/device_<d>/sensor_<s>/<Stream>_<i>/...``.  Since 2.59 a ROS 2 ``.db3``: depth as
``image/data/compressedDepth`` (``16UC1; compressedDepth png``), a CameraInfo at
``image/camera_info``, the sensor's options (``option/Depth_Units/value``) and the stream's info
(``info``: ``encoding=Z16;fps=30``) as strings.  Before, a ROS 1 ``.bag``: depth as a raw
``sensor_msgs/Image`` in ``mono16`` at ``image/data``, one CameraInfo at ``info/camera_info``,
the options as ``std_msgs/Float32``; its writer leaves 4 bytes after each Image (rosbags refuses
the size, so those images are read leniently).  Depth samples are in the sensor's depth units
(D400: 1 mm by default, D405 0.1 mm).
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from hw.errors import DepthFileError

__all__ = ["DEPTH_TOPIC", "camera_info_topics", "depth_units_m", "device_info",
           "float32_decimal", "frame_numbers", "is_realsense_depth", "lenient_ros1",
           "stream_fps", "to_millimetres"]

#: A librealsense recording's depth image topic (raw, or compressedDepth since 2.59).
DEPTH_TOPIC = re.compile(r"^(/device_\d+/sensor_\d+)/Depth_\d+/image/data(/compressedDepth)?$")
#: Trailing bytes a librealsense ROS 1 Image may carry beyond its fields.
_ROS1_SLACK = 8


def is_realsense_depth(topic: str | None) -> bool:
    """Whether ``topic`` is the depth of a librealsense recording (its ``mono16`` is depth)."""
    return bool(topic and DEPTH_TOPIC.match(topic))


def camera_info_topics(topic: str) -> list[str]:
    """Where a librealsense recording keeps the CameraInfo of the depth ``topic``: beside the
    image (2.59+), then the stream's ``info/camera_info`` (ROS 1 recordings)."""
    stream = topic.split("/image/")[0]
    return [stream + "/image/camera_info", stream + "/info/camera_info"]


def depth_units_m(reader: Any, topic: str, where: str) -> float:
    """Metres per depth sample of a librealsense recording's depth ``topic`` (its sensor's
    Depth_Units option, a string since 2.59, a Float32 before) as librealsense holds it, a
    float32 (0.0001 is 9.9999997e-05: samples convert as its playback converts them); 0.001
    when it has none."""
    match = DEPTH_TOPIC.match(topic)
    option = match and reader.topics.get(match.group(1) + "/option/Depth_Units/value")
    if not option:
        return 0.001
    first = next(reader.messages(connections=option.connections), None)
    text = ""
    if first is not None:
        try:
            text = str(reader.deserialize(first[2], option.msgtype).data)
        except Exception:  # noqa: BLE001 - the library's own errors: said below
            text = "(unreadable)"
    try:
        units = float(text)
    except ValueError:
        units = math.nan
    if not (math.isfinite(units) and 1e-6 <= units <= 0.1):
        raise DepthFileError(f"{where}: the RealSense depth units {text!r} on "
                             f"{match.group(1)}/option/Depth_Units/value make no sense")
    return float(np.float32(units))


#: A 2.59+ recording's per-frame metadata string: ``Frame number=101;...;timestamp=1033.33;``.
_FRAME_FIELDS = re.compile(r"(?:^|;)Frame number=(\d+);(?:.*;)?timestamp=([0-9.eE+-]+)(?:;|$)")


def frame_numbers(reader: Any, topic: str) -> dict[int, tuple[int, int]]:
    """What a 2.59+ recording says of each frame of the depth ``topic`` beside it
    (``<stream>/image/metadata``, a string per frame written with the image's log time): log
    time (ns) -> (the camera's frame number, its timestamp in µs), as librealsense's playback
    gives them; the image's header stamp there is only when it was written.  ``{}`` for a
    recording without them (ROS 1 recordings keep both in the image's header)."""
    meta = reader.topics.get(topic.split("/image/")[0] + "/image/metadata")
    if meta is None or meta.msgtype != "std_msgs/msg/String":
        return {}
    out = {}
    for connection, log_time, raw in reader.messages(connections=meta.connections):
        try:
            found = _FRAME_FIELDS.search(str(reader.deserialize(raw, connection.msgtype).data))
        except Exception:  # noqa: BLE001 - a damaged metadata message: that frame has none
            continue
        if found:
            out[log_time] = (int(found.group(1)), round(float(found.group(2)) * 1000))
    return out


def stream_fps(reader: Any, topic: str) -> float:
    """The fps a 2.59+ recording gives the stream of ``topic`` (``<stream>/info``,
    ``encoding=Z16;fps=30``); 30 when that is not there or not readable."""
    info = reader.topics.get(topic.split("/image/")[0] + "/info")
    if info is None or info.msgtype != "std_msgs/msg/String":
        return 30.0
    first = next(reader.messages(connections=info.connections), None)
    try:
        text = "" if first is None else str(reader.deserialize(first[2], info.msgtype).data)
    except Exception:  # noqa: BLE001 - a damaged info message: the default
        return 30.0
    found = re.search(r"(?:^|;)fps=(\d+(?:\.\d+)?)", text)
    return float(found.group(1)) if found and float(found.group(1)) > 0 else 30.0


def device_info(reader: Any, topic: str) -> dict[str, str]:
    """The camera a recording names for the depth ``topic``'s device (``/device_<d>/info``):
    ``{"name": "Intel RealSense D435", "serial": "..."}`` as librealsense's playback reports
    them (the ``auto`` noise profile's key), from a 2.59+ recording's string
    (``Name=...;Serial Number=...``) or an older one's KeyValue messages; ``{}`` when it names
    none or cannot be read."""
    match = DEPTH_TOPIC.match(topic)
    info = reader.topics.get(match.group(1).rsplit("/", 1)[0] + "/info") if match else None
    if info is None:
        return {}
    pairs: dict[str, str] = {}
    try:
        for connection, _, raw in reader.messages(connections=info.connections):
            message = reader.deserialize(raw, connection.msgtype)
            if info.msgtype == "std_msgs/msg/String":
                for part in str(message.data).split(";"):
                    key, _, value = part.partition("=")
                    pairs.setdefault(key.strip(), value.strip())
            elif info.msgtype == "diagnostic_msgs/msg/KeyValue":
                pairs.setdefault(str(message.key).strip(), str(message.value).strip())
    except Exception:  # noqa: BLE001 - a damaged info message names no camera
        return {}
    return {field: pairs[key] for field, key in (("name", "Name"), ("serial", "Serial Number"))
            if pairs.get(key)}


def to_millimetres(samples: np.ndarray, mm_per_sample: float) -> np.ndarray:
    """(H, W) depth samples in another unit -> (H, W) uint16 mm, rounded; beyond 65.535 m is 0
    (no reading)."""
    millimetres = np.floor(samples * mm_per_sample + 0.5)
    return np.where(millimetres <= 65535, millimetres, 0).astype(np.uint16)


def float32_decimal(value: float) -> float:
    """librealsense's float32 intrinsics as the shortest decimal that is that float32 (612.4,
    not 612.4000244140625), so a recording gives the same camera through both backends."""
    return float(np.format_float_positional(np.float32(value), unique=True, trim="-"))


def lenient_ros1(typestore: Any, raw: bytes, msgtype: str) -> Any:
    """A ROS 1 message with up to a few trailing bytes after its fields (librealsense's ROS 1
    Images), deserialized with the bag's own type; ``ValueError`` when it is not that."""
    msgdef = typestore.get_msgdef(msgtype)
    message, used = msgdef.deserialize_ros1(raw, 0, msgdef.cls, typestore)
    if not 0 <= len(raw) - used <= _ROS1_SLACK:
        raise ValueError(f"{len(raw) - used} bytes beyond the message")
    return message
