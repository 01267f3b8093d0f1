"""Depth frames written as a RealSense recording by librealsense itself: a ``software_device``
with one depth sensor (Z16) fed the frames while librealsense's ``recorder`` writes
them.  Needs ``pyrealsense2`` (the realsense extra); no camera.

    write_realsense_recording("run.db3", frames)        # DepthFrames; returns how many

librealsense 2.59 and later writes a ROS 2 bag (``.db3``): depth on
``/device_0/sensor_0/Depth_0/image/data/compressedDepth`` (image_transport's ``16UC1;
compressedDepth png``), a CameraInfo beside it, the sensor's options (``Depth_Units``) as
strings -- what ``rs-record`` or the RealSense Viewer write for a camera, less the camera's other
streams.  It plays in librealsense (``realsense:run.db3``, ``rs.config.enable_device_from_file``,
the Viewer) and reads through the bag backend (``rosbag:run.db3``).  Frame numbers and
timestamps are the frames' own.  The file appears only when complete: written under a
temporary name beside it, then renamed.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from hw.depth import DepthFrame
from hw.errors import BackendUnavailable, DepthFileError, FrameError

__all__ = ["UNNAMED_CAMERA", "write_realsense_recording"]

#: What a recording names a camera when its frames' source named none (no model: the ``auto``
#: noise profile's default).
UNNAMED_CAMERA = "robot-change recording"


def write_realsense_recording(path: str | os.PathLike[str], frames: Iterable[DepthFrame], *,
                              fps: int = 30, depth_units: float = 0.001,
                              name: str | None = None, serial: str = "000000000001",
                              compress: bool = True,
                              on_frame: Callable[[int, int], None] | None = None) -> int:
    """Write ``frames`` (all of one size and intrinsics, those of the first) to a new recording
    ``path`` (``.db3``, must not exist) at a nominal ``fps``; returns the number of frames.
    ``depth_units``: metres a sample (the frames' samples are written as they are: 0.001 for
    millimetres, 0.0001 for a D405's native tenths).  ``name``: the camera model the recording
    names (the source's, e.g. "Intel RealSense D435": it picks the ``auto`` noise profile);
    default :data:`UNNAMED_CAMERA`, which names no model.  ``compress``: depth as
    compressedDepth PNG (librealsense's default), else raw Images (about 5x larger; playing
    them costs about 0.4 of the CPU: docs/benchmarks.md).
    ``on_frame(frames, bytes)`` after each.  Raises :class:`DepthFileError` when it cannot be
    written, :class:`FrameError` for no frames or frames that change size,
    :class:`BackendUnavailable` without pyrealsense2."""
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise BackendUnavailable(f"writing a RealSense recording needs pyrealsense2 (the "
                                 f"realsense extra: pip install pyrealsense2): {exc}") from None
    target = Path(path)
    if target.suffix.lower() != ".db3":
        raise DepthFileError(f"{target}: a RealSense recording of librealsense 2.59+ is a .db3 "
                             "file")
    if target.exists():
        raise DepthFileError(f"{target}: exists; a recording is not written over it")
    if not target.parent.is_dir():
        raise DepthFileError(f"cannot write {target}: the folder {target.parent} does not exist")
    handle, scratch = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=".tmp.db3",
                                       dir=target.parent)
    os.close(handle)
    os.unlink(scratch)  # the recorder makes the file itself
    count = 0
    try:
        stream = iter(frames)
        first = next(stream, None)
        if first is None:
            raise FrameError(f"{target}: no frames to write; a recording needs at least one")
        device, sensor, profile = _software_camera(rs, first, fps, depth_units,
                                                   name or UNNAMED_CAMERA, serial)
        recorder = rs.recorder(scratch, device, bool(compress))
        queue = rs.frame_queue(64)
        sensor.open(profile)
        sensor.start(queue)
        try:
            for frame in itertools.chain([first], stream):
                if frame.depth.shape != first.depth.shape or \
                        frame.intrinsics != first.intrinsics:
                    raise FrameError(f"{target}: frame {frame.index} has another size or other "
                                     "intrinsics than the first; a recording holds one mode")
                _send(rs, sensor, profile, frame)
                while queue.poll_for_frame():  # keep the queue from filling: frames are recorded
                    pass
                count += 1
                if on_frame is not None:
                    on_frame(count, _size(scratch))
        finally:
            sensor.stop()
            sensor.close()
            del recorder  # the file is complete when the recorder goes
        os.replace(scratch, target)
    except RuntimeError as exc:  # librealsense's own errors
        raise DepthFileError(f"cannot write {target}: librealsense: {exc}") from None
    except OSError as exc:
        raise DepthFileError(f"cannot write {target}: {exc.strerror or exc}") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(scratch)
    return count


def _software_camera(rs, first: DepthFrame, fps: int, depth_units: float, name: str,
                     serial: str):
    """(device, depth sensor, Z16 stream profile) of a software camera with ``first``'s
    intrinsics."""
    cam = first.intrinsics
    device = rs.software_device()
    device.register_info(rs.camera_info.name, name)
    device.register_info(rs.camera_info.serial_number, serial)
    sensor = device.add_sensor("Stereo Module")
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height = cam.width, cam.height
    intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy = cam.fx, cam.fy, cam.cx, cam.cy
    intrinsics.model = rs.distortion.brown_conrady
    intrinsics.coeffs = [0.0] * 5
    video = rs.video_stream()
    video.type, video.index, video.uid = rs.stream.depth, 0, 0
    video.width, video.height, video.fps = cam.width, cam.height, int(fps)
    video.bpp, video.fmt, video.intrinsics = 2, rs.format.z16, intrinsics
    profile = sensor.add_video_stream(video)
    sensor.add_read_only_option(rs.option.depth_units, float(depth_units))
    return device, sensor, profile


def _send(rs, sensor, profile, frame: DepthFrame) -> None:
    software = rs.software_video_frame()
    software.pixels = np.ascontiguousarray(frame.depth, dtype=np.uint16)
    software.bpp, software.stride = 2, 2 * frame.depth.shape[1]
    software.timestamp = frame.timestamp_us / 1000.0
    software.domain = rs.timestamp_domain.hardware_clock
    software.frame_number = int(frame.index)
    software.profile = profile.as_video_stream_profile()
    sensor.on_video_frame(software)


def _size(path: str) -> int:
    try:
        return os.stat(path).st_size
    except OSError:
        return 0
