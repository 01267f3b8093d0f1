"""ROS bags as a depth source, and depth written to a ROS 2 bag, through ``rosbags`` (pure Python:
no ROS installation needed).

    open_depth("rosbag:run1?topic=/camera/depth/image_raw")   # a ROS 2 bag folder
    open_depth("rosbag:tum.bag")                               # ROS 1; the only depth topic
    write_rosbag2("run2", frames)                              # run2/run2.mcap + metadata.yaml

What a bag may be: a ROS 1 ``.bag`` file; a ROS 2 bag folder (``metadata.yaml`` beside ``.db3``
or ``.mcap`` storage); a single ROS 2 ``.db3`` or ``.mcap`` file.  Depth is a
``sensor_msgs/Image`` topic in ``16UC1`` (millimetres) or ``32FC1`` (metres; NaN, infinities,
readings <= 0 and beyond 65.535 m become 0, "no reading"), as REP 118 defines them, or a
``sensor_msgs/CompressedImage`` topic of depth as image_transport records it by default
(``.../compressedDepth``: PNG or RVL after its 12-byte header, 16UC1 or quantised 32FC1; or the
``compressed`` transport's 16-bit PNG), decoded by :mod:`hw.compressed_depth`; a payload that
cannot be decoded is a :class:`FrameError` naming the bag, the topic and the message's index.
RealSense recordings read as they are (:mod:`hw.realsense_bag`: a ROS 2 ``.db3`` of
librealsense 2.59 and later, a ROS 1 ``.bag`` before, its ``mono16`` depth and its CameraInfo
where librealsense keeps it), the samples scaled from the sensor's ``Depth_Units`` to
millimetres.

Intrinsics come from the ``sensor_msgs/CameraInfo`` beside the image topic (the same namespace's
``camera_info``: ``/camera/depth/image_raw`` -> ``/camera/depth/camera_info``, and the same for
``/camera/depth/image_raw/compressedDepth``), or the topic
given as ``?info=``, or ``?intrinsics=fx,fy,cx,cy`` (then no CameraInfo is needed).  A raw image
must be undistorted: distortion model ``plumb_bob``, ``rational_polynomial`` or ``none`` with
all coefficients zero (``K`` is used).  A rectified image (a topic whose last name starts with
``image_rect``, as image_proc and the RealSense driver name them, or ``?rectified=1``) is read
with the rectified camera matrix ``P`` and its distortion is not looked at.  Anything else is
refused with the fix: read the rectified topic.  Every later CameraInfo must match the first.

Frame timestamps (µs) are the image headers' stamps (the bag's receive time when a stamp is 0);
frame indices count delivered frames; ``stats.dropped`` counts gaps in ROS 1 header sequence
numbers.  ``rate=`` paces delivery, ``loop=1`` starts again after the last frame (timestamps
keep increasing), as the other file sources do (:mod:`hw.options`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hw.atomic import commit_folder
from hw.compressed_depth import COMPRESSED_TYPE, decode_compressed_depth, depth_format
from hw.depth import DepthFrame, DepthSource, Intrinsics
from hw.errors import DepthFileError, DeviceError, FrameError, UriError
from hw.options import LapClock, Pacer, flag, intrinsics_option, positive
from hw.realsense_bag import (
    camera_info_topics,
    depth_units_m,
    device_info,
    float32_decimal,
    frame_numbers,
    is_realsense_depth,
    lenient_ros1,
    to_millimetres,
)

try:  # the backend's library: hw.depth.open_depth reports it missing with what to install
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
except ImportError as exc:  # pragma: no cover - exercised without rosbags installed
    raise ImportError(f"rosbags is not installed ({exc})") from exc

__all__ = ["DEPTH_ENCODINGS", "RosbagSource", "open_bag", "open_rosbag", "write_rosbag2"]

log = logging.getLogger(__name__)

IMAGE_TYPE = "sensor_msgs/msg/Image"
INFO_TYPE = "sensor_msgs/msg/CameraInfo"
#: Depth encodings read (REP 118): unit of a sample.
DEPTH_ENCODINGS = {"16UC1": "mm", "32FC1": "m"}
#: Distortion models that are a plain pinhole when all their coefficients are zero.
PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "none", "",
                  # librealsense's names (its recordings' CameraInfo)
                  "Brown Conrady", "Modified Brown Conrady", "Inverse Brown Conrady")
#: What :func:`write_rosbag2` names things, as the openni2_camera / realsense ROS drivers do.
DEFAULT_TOPIC = "/camera/depth/image_raw"
DEFAULT_FRAME_ID = "camera_depth_optical_frame"
#: The camera a bag :func:`write_rosbag2` wrote names, in its metadata's ``custom_data``: the
#: source's ``info`` field -> the key.
CAMERA_KEYS = {"name": "camera_name", "serial": "camera_serial"}
#: Message types for ROS 2 bags without type definitions (db3 bags of Humble and before).
_TYPESTORE = Stores.ROS2_HUMBLE
_OPTIONS = ("topic", "info", "intrinsics", "rectified", "rate", "loop")
_MAX_LISTED = 12


# --- reading ----------------------------------------------------------------------------------
class RosbagSource(DepthSource):
    """The depth images of one topic of a ROS bag, delivered as frames (see the module
    docstring).  Made by :func:`open_rosbag`; opening reads the bag's index, picks the topic and
    the intrinsics, and checks the first image, so a wrong bag, topic, encoding or camera model
    fails at :meth:`open` with a :class:`DepthFileError` saying what to change.
    """

    def __init__(self, path: Path, *, topic: str | None, info: str | None,
                 intrinsics: Intrinsics | str | None, rectified: bool | None,
                 rate: float | None, loop: bool) -> None:
        super().__init__()
        self.path = path
        self.topic = topic
        self.info_topic = info
        self._given_intrinsics = intrinsics
        self._rectified = rectified
        self.rate = rate
        self.loop = loop
        self._pacer = Pacer(rate)
        self._reader: Any = None
        self._connections: list[Any] = []
        self._info_connections: list[Any] = []
        self._intrinsics: Intrinsics | None = None
        self._info_key: tuple | None = None
        self._messages: Iterator[tuple[Any, int, bytes]] | None = None
        self._pending: tuple[Any, int] | None = None  # the next image message and its log time
        self._position = 0
        self._clock = LapClock()
        self._last_seq: int | None = None
        self._taken = 0  # image messages of this lap taken by read()
        self._compressed = False
        self._realsense = False
        self._scale = 1.0  # millimetres per sample
        #: a RealSense recording's log time -> (frame number, timestamp µs) (frame_numbers)
        self._frame_numbers: dict[int, tuple[int, int]] = {}
        #: the camera the recording names ("name", "serial"; the ``auto`` profile's): a
        #: RealSense recording's device info, or a bag's custom_data (:data:`CAMERA_KEYS`)
        self.info: dict[str, str] = {}

    def __repr__(self) -> str:
        return f"<RosbagSource {self.path} {self.topic or '(no topic yet)'}>"

    @property
    def intrinsics(self) -> Intrinsics:
        """The frames' intrinsics (opens the bag to learn them, if needed)."""
        if self._intrinsics is None:
            self.open()
        assert self._intrinsics is not None
        return self._intrinsics

    @property
    def rectified(self) -> bool:
        """Whether the image is read as rectified (``P``) rather than raw (``K``)."""
        if self._rectified is not None:
            return self._rectified
        last = self._image_topic().rsplit("/", 1)[-1] if self.topic else ""
        return last.startswith("image_rect")

    def open(self) -> None:
        """Open the bag and start at its first frame (again, after :meth:`close`)."""
        if self._reader is not None:
            return
        reader = open_bag(self.path)
        try:
            self._reader = reader
            self._choose_topic()
            self._intrinsics = self._find_intrinsics()
            self._restart()
            self._peek()
            if self._pending is None:
                raise DepthFileError(f"{self.path}: {self.topic} holds no message")
            self._depth(self._pending[0], 0)  # encoding, size
        except BaseException:
            self.close()
            raise
        self._position = 0
        self._clock.reset()
        self._last_seq = None
        self._pacer.reset()

    def close(self) -> None:
        """Close the bag; a later :meth:`open` starts from the first frame.  Safe to repeat."""
        reader, self._reader = self._reader, None
        self._messages = None
        self._pending = None
        if reader is not None:
            try:
                reader.close()
            except Exception as exc:  # noqa: BLE001 - closing a file that failed: say, go on
                log.debug("%s: closing the bag: %s", self.path, exc)

    def read(self, timeout: float | None = 1.0) -> DepthFrame | None:
        """The next frame; ``None`` after the last one when not looping.

        With a ``rate``, waits until the frame is due; if that is more than ``timeout`` seconds
        away, waits ``timeout`` and raises :class:`FrameTimeout` (the frame stays next).  An
        image that cannot be read (another size or encoding than the first, a broken message)
        raises :class:`DepthFileError`, counts as dropped, and the next read moves on.
        """
        if self._reader is None:
            raise DeviceError(f"{self!r} is not open: call open() or use it in a 'with' block")
        if self._pending is None:
            self._peek()
            if self._pending is None and self.loop and self._clock.lap_frames:
                self._clock.next_lap()
                self._restart()
                self._peek()
            if self._pending is None:
                return None
        self._pacer.wait(timeout, repr(self))
        message, log_time = self._pending
        self._pending = None
        try:
            depth = self._depth(message, self._taken)
            self._check_size(depth)
        except (DepthFileError, FrameError):
            self.stats.dropped += 1
            raise
        finally:
            self._taken += 1
        # a 2.59+ RealSense recording's frame number and timestamp are in its metadata
        number, recorded = self._frame_numbers.get(
            log_time, (getattr(message.header, "seq", None), None))
        stamp = recorded if recorded is not None else (_stamp_us(message.header.stamp)
                                                       or log_time // 1000)
        self._count_gaps(number)
        index = number if recorded is not None and not self.loop else self._position
        self._position += 1
        frame = DepthFrame(depth, self._clock.stamp(stamp), index, self.intrinsics)
        self.stats.delivered += 1
        return frame

    # the bag's contents --------------------------------------------------------------------
    def _choose_topic(self) -> None:
        topics = self._reader.topics
        if self.topic is None:
            depth = [name for name, (_, is_depth) in self._image_topics().items() if is_depth]
            if len(depth) != 1:
                what = "no depth image topic" if not depth else "several depth image topics"
                raise DepthFileError(f"{self.path}: {what}; name one with ?topic=. "
                                     + self._listing())
            self.topic = depth[0]
            log.info("%s: reading depth from %s", self.path, self.topic)
        elif self.topic not in topics or \
                topics[self.topic].msgtype not in (IMAGE_TYPE, COMPRESSED_TYPE):
            what = ("no topic" if self.topic not in topics else
                    f"{topics[self.topic].msgtype} (not a sensor_msgs/Image or "
                    "CompressedImage) on")
            raise DepthFileError(f"{self.path}: {what} {self.topic}. " + self._listing())
        self._connections = list(topics[self.topic].connections)
        self._compressed = topics[self.topic].msgtype == COMPRESSED_TYPE
        self._realsense = is_realsense_depth(self.topic)  # a librealsense recording's depth
        self._scale = (depth_units_m(self._reader, self.topic, str(self.path)) * 1000.0
                       if self._realsense else 1.0)
        self.info = (device_info(self._reader, self.topic) if self._realsense
                     else recorded_camera(self._reader))
        self._frame_numbers = frame_numbers(self._reader, self.topic) if self._realsense else {}

    def _image_topic(self) -> str:
        """The topic of the raw image (a compressed topic is ``<image topic>/<transport>``)."""
        assert self.topic is not None
        topic = self.topic.rstrip("/")
        return topic.rsplit("/", 1)[0] if self._compressed else topic


    def _image_topics(self) -> dict[str, tuple[str, bool]]:
        """Every sensor_msgs/Image and CompressedImage topic -> (the encoding or format of its
        first message, "" if none; whether that is depth)."""
        found = {}
        for name, info in sorted(self._reader.topics.items()):
            if info.msgtype not in (IMAGE_TYPE, COMPRESSED_TYPE):
                continue
            first = next(self._reader.messages(connections=info.connections), None)
            if first is None:
                found[name] = ("", False)
            elif info.msgtype == IMAGE_TYPE:
                encoding = str(self._deserialize(first).encoding)
                found[name] = (encoding, encoding in DEPTH_ENCODINGS or
                               (encoding == "mono16" and is_realsense_depth(name)))
            else:
                text = str(self._deserialize(first).format)
                found[name] = (text, depth_format(text) is not None)
        return found

    def _listing(self) -> str:
        """The depth image topics of the bag (and what else it holds), for an error message."""
        images = self._image_topics()
        depth = [f"{name} ({enc})" for name, (enc, is_depth) in images.items() if is_depth]
        other = [f"{name} ({enc or 'empty'})" for name, (enc, is_depth) in images.items()
                 if not is_depth]
        text = ("Depth image topics in this bag: " + ", ".join(depth[:_MAX_LISTED])) if depth \
            else ("This bag has no depth image topic (sensor_msgs/Image in 16UC1 or 32FC1, or "
                  "its compressedDepth)")
        if other:
            text += "; other image topics (not depth): " + ", ".join(other[:_MAX_LISTED])
        if not images:
            names = sorted(self._reader.topics)
            text += "; its topics: " + (", ".join(f"{n} ({self._reader.topics[n].msgtype})"
                                                  for n in names[:_MAX_LISTED]) or "none")
        return text

    def _find_intrinsics(self) -> Intrinsics:
        """From ``?intrinsics=``, else the first CameraInfo on the info topic."""
        size = self._first_image_size()
        given = self._given_intrinsics
        if isinstance(given, str):
            return Intrinsics.parse(given, *size)
        if given is not None:
            if (given.width, given.height) != size:
                raise FrameError(f"{self.path}: the images on {self.topic} are "
                                 f"{size[0]}x{size[1]} but the intrinsics given are for "
                                 f"{given.width}x{given.height}")
            return given
        topics = self._reader.topics
        info_topic = self.info_topic or self._image_topic().rsplit("/", 1)[0] + "/camera_info"
        if not self.info_topic and self._realsense:
            info_topic = next((name for name in camera_info_topics(self.topic)
                               if name in topics), info_topic)
        if info_topic not in topics or topics[info_topic].msgtype != INFO_TYPE:
            infos = sorted(name for name, info in topics.items() if info.msgtype == INFO_TYPE)
            looked = f"?info={info_topic}" if self.info_topic else f"{info_topic} (beside it)"
            raise DepthFileError(
                f"{self.path}: no sensor_msgs/CameraInfo for {self.topic}: looked for {looked}; "
                + ("CameraInfo topics in this bag: " + ", ".join(infos) if infos else
                   "the bag has no CameraInfo topic")
                + ". Name the camera's with ?info=TOPIC, or give ?intrinsics=fx,fy,cx,cy")
        self.info_topic = info_topic
        self._info_connections = list(topics[info_topic].connections)
        first = next(self._reader.messages(connections=self._info_connections), None)
        if first is None:
            raise DepthFileError(f"{self.path}: {info_topic} holds no message; give "
                                 "?intrinsics=fx,fy,cx,cy")
        info = self._deserialize(first)
        intrinsics = intrinsics_from_camera_info(info, size, self.rectified,
                                                 f"{self.path} {info_topic}")
        if self._realsense:  # librealsense's float32s, as librealsense gives them
            intrinsics = dataclasses.replace(intrinsics, **{
                key: float32_decimal(getattr(intrinsics, key)) for key in ("fx", "fy", "cx", "cy")})
        self._info_key = _info_key(info)
        return intrinsics

    def _first_image_size(self) -> tuple[int, int]:
        first = next(self._reader.messages(connections=self._connections), None)
        if first is None:
            raise DepthFileError(f"{self.path}: {self.topic} holds no message")
        height, width = self._depth(self._deserialize(first), 0).shape
        return width, height

    # the stream ----------------------------------------------------------------------------
    def _restart(self) -> None:
        self._taken = 0
        self._messages = self._reader.messages(
            connections=self._connections + self._info_connections)

    def _peek(self) -> None:
        """Move to the next image message (checking CameraInfo messages on the way)."""
        assert self._messages is not None
        while self._pending is None:
            try:
                item = next(self._messages, None)
            except Exception as exc:  # noqa: BLE001 - the library's own errors, on a broken bag
                raise DepthFileError(f"{self.path}: cannot read the bag further "
                                     f"({type(exc).__name__}: {exc})") from None
            if item is None:
                return
            connection, log_time, _ = item
            try:
                message = self._deserialize(item)
            except DepthFileError:
                if connection.msgtype != INFO_TYPE:
                    self.stats.dropped += 1
                raise
            if connection.msgtype == INFO_TYPE:
                if _info_key(message) != self._info_key:
                    raise DepthFileError(
                        f"{self.path}: the CameraInfo on {self.info_topic} changes at "
                        f"{log_time / 1e9:.3f} s; this source reads one camera model: cut the "
                        "bag where it changes, or give ?intrinsics=fx,fy,cx,cy")
                continue
            self._pending = (message, log_time)

    def _deserialize(self, item: tuple[Any, int, bytes]) -> Any:
        connection, _, raw = item
        try:
            return self._reader.deserialize(raw, connection.msgtype)
        except Exception as exc:  # noqa: BLE001 - the library's own errors, on a broken message
            if not self._reader.is2 and is_realsense_depth(connection.topic):
                with contextlib.suppress(Exception):  # librealsense's ROS 1 Image slack
                    return lenient_ros1(self._reader.typestore, raw, connection.msgtype)
            raise DepthFileError(f"{self.path}: a {connection.msgtype} message on "
                                 f"{connection.topic} cannot be decoded "
                                 f"({type(exc).__name__}: {exc})") from None

    def _depth(self, message: Any, index: int) -> np.ndarray:
        """The (H, W) uint16 millimetres of image message number ``index`` of the topic."""
        if self._compressed:
            depth = decode_compressed_depth(message.format, message.data,
                                            f"{self.path} {self.topic} message {index}")
        else:
            depth = image_to_depth(message, f"{self.path} {self.topic}",
                                   mono16=self._realsense)
        if abs(self._scale - 1.0) > 1e-6:  # (librealsense's 1 mm is a float32's 0.001)
            depth = to_millimetres(depth, self._scale)
        return depth

    def _check_size(self, depth: np.ndarray) -> None:
        if self._intrinsics is None:
            return
        height, width = depth.shape
        if (width, height) != (self._intrinsics.width, self._intrinsics.height):
            raise DepthFileError(f"{self.path}: an image on {self.topic} is {width}x{height}, "
                                 f"the first was {self._intrinsics.width}x"
                                 f"{self._intrinsics.height}")

    def _count_gaps(self, seq: int | None) -> None:
        if seq is not None and self._last_seq is not None and self._clock.lap_frames and \
                seq > self._last_seq + 1:
            self.stats.dropped += seq - self._last_seq - 1
        self._last_seq = seq


def open_bag(path: Path) -> Any:
    """An opened AnyReader on ``path``; :class:`DepthFileError` for what is not a bag."""
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise DepthFileError(f"{path}: a folder without metadata.yaml is not a ROS 2 bag (a ROS "
                             "1 bag is a .bag file; for a folder of depth images use images:)")
    if path.is_file() and path.suffix.lower() not in (".bag", ".db3", ".mcap"):
        raise DepthFileError(f"{path}: not a bag by its name: a ROS 1 bag ends in .bag, a ROS 2 "
                             "bag is a folder with metadata.yaml, or a .db3 / .mcap file")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(_TYPESTORE))
        reader.open()
    except Exception as exc:  # noqa: BLE001 - whatever the library makes of a foreign file
        raise DepthFileError(f"{path}: not a readable ROS bag ({type(exc).__name__}: "
                             f"{exc})") from None
    return reader


def recorded_camera(reader: Any) -> dict[str, str]:
    """The camera a ROS 2 bag's metadata names in its ``custom_data`` (:data:`CAMERA_KEYS`, as
    :func:`write_rosbag2` writes them): ``{"name": ..., "serial": ...}``, the fields it has;
    ``{}`` for a ROS 1 bag, a bare storage file, or none named."""
    found: dict[str, str] = {}
    for bag in getattr(reader, "readers", ()):  # rosbags keeps it with the storage's metadata
        custom = getattr(getattr(getattr(bag, "storage", None), "metadata", None), "custom", None)
        if isinstance(custom, dict):
            found.update({field: custom[key].strip() for field, key in CAMERA_KEYS.items()
                          if isinstance(custom.get(key), str) and custom[key].strip()})
    return found


def image_to_depth(message: Any, where: str, mono16: bool = False) -> np.ndarray:
    """A sensor_msgs/Image in 16UC1 (mm) or 32FC1 (m) -> (H, W) uint16 millimetres, 0 = no
    reading; ``mono16``: a mono16 image is depth too (a librealsense recording's).  Rows are
    read with the message's ``step`` and byte order.  Raises :class:`DepthFileError` for
    another encoding or too little data."""
    encoding = str(message.encoding)
    if mono16 and encoding == "mono16":
        encoding = "16UC1"
    if encoding not in DEPTH_ENCODINGS:
        raise DepthFileError(f"{where}: encoding {encoding!r} is not depth; depth images are "
                             "16UC1 (millimetres) or 32FC1 (metres)")
    height, width, step = int(message.height), int(message.width), int(message.step)
    size = 2 if encoding == "16UC1" else 4
    data = np.asarray(message.data, dtype=np.uint8)
    if width < 1 or height < 1 or step < width * size or data.size < step * height:
        raise DepthFileError(f"{where}: a {width}x{height} {encoding} image with step {step} "
                             f"needs {max(step, width * size) * height} bytes, the message has "
                             f"{data.size}")
    rows = data[:step * height].reshape(height, step)[:, :width * size]
    order = ">" if message.is_bigendian else "<"
    if encoding == "16UC1":
        return np.ascontiguousarray(rows).view(f"{order}u2").astype(np.uint16)
    metres = np.ascontiguousarray(rows).view(f"{order}f4").astype(np.float64)
    millimetres = np.floor(metres * 1000.0 + 0.5)
    good = np.isfinite(millimetres) & (millimetres > 0) & (millimetres <= 65535)
    return np.where(good, millimetres, 0).astype(np.uint16)


def intrinsics_from_camera_info(info: Any, size: tuple[int, int], rectified: bool,
                                where: str) -> Intrinsics:
    """Pinhole intrinsics of images of ``size`` (width, height) from a sensor_msgs/CameraInfo
    (ROS 1 ``K``/``D``/``P`` or ROS 2 ``k``/``d``/``p``): ``P`` when ``rectified``, else ``K``
    after checking the image is undistorted (see the module docstring).  Raises
    :class:`DepthFileError` saying what to do otherwise."""
    K, D, P = (np.asarray(_field(info, name), dtype=np.float64) for name in ("k", "d", "p"))
    width, height = size
    if (int(info.width), int(info.height)) != (width, height):
        raise DepthFileError(f"{where}: the CameraInfo is for {info.width}x{info.height} images "
                             f"but the depth images are {width}x{height} (binning or a region "
                             "of interest?); give ?intrinsics=fx,fy,cx,cy for them")
    model = str(info.distortion_model)
    if rectified and P.size == 12 and P[0] > 0 and P[5] > 0:
        fx, fy, cx, cy = P[0], P[5], P[2], P[6]
    else:
        if not rectified and (model not in PINHOLE_MODELS or np.any(D != 0)):
            coefficients = ", ".join(f"{v:g}" for v in D)
            raise DepthFileError(
                f"{where}: distortion model {model!r} with coefficients [{coefficients}]: the "
                "image is not undistorted, and this source reads pinhole depth. Read the "
                "rectified topic (image_rect / image_rect_raw, as depth_image_proc or the "
                "driver publish it), or, if this image is rectified, say so with "
                "?rectified=1")
        fx, fy, cx, cy = K[0], K[4], K[2], K[5]
    try:
        return Intrinsics(width, height, float(fx), float(fy), float(cx), float(cy))
    except FrameError as exc:
        raise DepthFileError(f"{where}: its camera matrix makes no pinhole camera ({exc}); an "
                             "uncalibrated camera publishes zeros: give "
                             "?intrinsics=fx,fy,cx,cy") from None


def _field(message: Any, name: str) -> Any:
    """A CameraInfo field by its ROS 2 (lower case) or ROS 1 (upper case) name."""
    return getattr(message, name) if hasattr(message, name) else getattr(message, name.upper())


def _info_key(info: Any) -> tuple:
    """What must not change between CameraInfo messages of one stream."""
    return (int(info.width), int(info.height), str(info.distortion_model),
            *(tuple(np.asarray(_field(info, name), dtype=np.float64).tolist())
              for name in ("k", "d", "p")))


def _stamp_us(stamp: Any) -> int:
    """A builtin_interfaces/Time (sec, nanosec) -> µs, rounded half up."""
    return (int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec) + 500) // 1000


def open_rosbag(target: str, *, topic: Any = None, info: Any = None, intrinsics: Any = None,
                rectified: Any = None, rate: Any = None, loop: Any = False,
                **unknown: Any) -> RosbagSource:
    """The ``rosbag:`` backend of :func:`hw.depth.open_depth`.

    ``target``: a ``.bag`` file, a ROS 2 bag folder, or a ``.db3`` / ``.mcap`` file.  Options
    (Python values, or the strings of a URI query): ``topic`` the depth image topic (default:
    the bag's only one); ``info`` its CameraInfo topic (default: ``camera_info`` beside it);
    ``intrinsics`` an :class:`Intrinsics` or ``"fx,fy,cx,cy"`` instead of CameraInfo;
    ``rectified`` 1/0 (default: from the topic's name); ``rate`` Hz to pace delivery at;
    ``loop`` 1/0.  Raises :class:`UriError` for bad or unknown options and
    :class:`DepthFileError` when the target is missing.  The source is returned unopened.
    """
    if unknown:
        raise UriError(f"rosbag option(s) {', '.join(sorted(unknown))} unknown; the rosbag "
                       f"backend takes {', '.join(_OPTIONS)}")
    names = {}
    for name, value in (("topic", topic), ("info", info)):
        if value is None or value == "":
            continue
        if not isinstance(value, str) or any(c.isspace() for c in value):
            raise UriError(f"rosbag option {name}={value!r}: expected a topic name such as "
                           "/camera/depth/image_raw")
        names[name] = value if value.startswith("/") else "/" + value
    rate_value = None if rate is None or rate == "" else positive(
        "rosbag", "rate", rate, "frames per second; leave it out to read as fast as possible")
    rectified_value = None if rectified is None else flag("rosbag", "rectified", rectified)
    intrinsics = intrinsics_option("rosbag", intrinsics)
    path = Path(target)
    if not path.exists():
        raise DepthFileError(f"{target}: no such file or folder (expected a .bag file, a ROS 2 "
                             "bag folder, or a .db3 / .mcap file)")
    return RosbagSource(path, topic=names.get("topic"), info=names.get("info"),
                        intrinsics=intrinsics, rectified=rectified_value, rate=rate_value,
                        loop=flag("rosbag", "loop", loop))


# --- writing ----------------------------------------------------------------------------------
def write_rosbag2(path: str | os.PathLike[str], frames: Iterable[DepthFrame], *,
                  topic: str = DEFAULT_TOPIC, frame_id: str = DEFAULT_FRAME_ID,
                  camera: Mapping[str, Any] | None = None,
                  on_frame: Callable[[int, int], None] | None = None) -> int:
    """Write depth frames to a new ROS 2 bag folder ``path`` with MCAP storage (zstd-compressed
    chunks, lossless), as ``ros2 bag record -s mcap -o path`` would: ``path/<name>.mcap`` and
    ``metadata.yaml``.  Each frame becomes a sensor_msgs/msg/Image in 16UC1 on ``topic`` and a
    sensor_msgs/msg/CameraInfo (plumb_bob, zero distortion, ``K`` and ``P`` from the frame's
    intrinsics) on the ``camera_info`` beside it, both stamped with the frame's timestamp and
    ``frame_id``.  ``camera``: the source's ``info`` (its ``name`` and ``serial``, when it
    gives them, go to the bag's ``custom_data`` as :data:`CAMERA_KEYS` say, so reading the bag
    names the camera and ``auto`` picks its noise profile).  Returns the number of frames.  The
    folder appears only when complete (built
    under a temporary name, then renamed); ``path`` must not exist.  ``on_frame(frames, bytes)``
    is called after each frame.  Raises :class:`DepthFileError` when it cannot be written,
    :class:`FrameError` for no frames or a negative timestamp.
    """
    target = Path(path)
    if target.exists():
        raise DepthFileError(f"{target}: exists; a bag is not written over it (nor does ros2 bag "
                             "record): remove it or choose another name")
    if target.suffix.lower() in (".mcap", ".db3", ".bag"):
        raise DepthFileError(f"{target}: a ROS 2 bag is a folder (ros2 bag record -o NAME makes "
                             f"NAME/NAME.mcap): name the folder, e.g. {target.with_suffix('')}")
    parent = target.parent
    if not parent.is_dir():
        raise DepthFileError(f"cannot write {target}: the folder {parent} does not exist")
    info_topic = topic.rstrip("/").rsplit("/", 1)[0] + "/camera_info"
    store = get_typestore(_TYPESTORE)
    Image, Info = store.types[IMAGE_TYPE], store.types[INFO_TYPE]
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    RegionOfInterest = store.types["sensor_msgs/msg/RegionOfInterest"]
    try:
        scratch = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent))
    except OSError as exc:
        raise DepthFileError(f"cannot write {target}: {exc.strerror or exc}") from None
    staged = scratch / target.name
    count = 0
    try:
        writer = Writer(staged, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        for field, key in CAMERA_KEYS.items():
            value = (camera or {}).get(field)
            if isinstance(value, str) and value:
                writer.set_custom_data(key, value)
        with writer:
            images = writer.add_connection(topic, IMAGE_TYPE, typestore=store)
            infos = writer.add_connection(info_topic, INFO_TYPE, typestore=store)
            storage_file = staged / f"{target.name}.mcap"
            for frame in frames:
                if frame.timestamp_us < 0:
                    raise FrameError(f"{target}: timestamp {frame.timestamp_us} µs: a ROS time "
                                     "is >= 0")
                stamp_ns = int(frame.timestamp_us) * 1000
                header = Header(stamp=Time(sec=stamp_ns // 1_000_000_000,
                                           nanosec=stamp_ns % 1_000_000_000),
                                frame_id=frame_id)
                height, width = frame.depth.shape
                depth = np.ascontiguousarray(frame.depth, dtype="<u2")
                image = Image(header=header, height=height, width=width, encoding="16UC1",
                              is_bigendian=0, step=width * 2,
                              data=depth.view(np.uint8).reshape(-1))
                cam = frame.intrinsics
                info = Info(header=header, height=height, width=width,
                            distortion_model="plumb_bob", d=np.zeros(5),
                            k=np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1.0]),
                            r=np.eye(3).reshape(-1),
                            p=np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1.0,
                                        0]),
                            binning_x=0, binning_y=0,
                            roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0,
                                                 do_rectify=False))
                writer.write(images, stamp_ns, store.serialize_cdr(image, IMAGE_TYPE))
                writer.write(infos, stamp_ns, store.serialize_cdr(info, INFO_TYPE))
                count += 1
                if on_frame is not None:
                    on_frame(count, _size(storage_file))
            if not count:
                raise FrameError(f"{target}: no frames to write; a bag needs at least one")
        commit_folder(staged, target)
    except OSError as exc:
        raise DepthFileError(f"cannot write {target}: {exc.strerror or exc}") from None
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return count


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0
