"""RealSense recordings written by librealsense itself, with no camera: a ``software_device``
with one depth sensor (Z16) fed our frames while librealsense's ``recorder`` writes them.

    write_realsense_recording("run.db3", frames, intrinsics, fps=30, depth_units=0.001)

librealsense 2.59 and later writes a ROS 2 bag (``.db3``): depth on
``/device_0/sensor_0/Depth_0/image/data/compressedDepth`` (image_transport's ``16UC1;
compressedDepth png``), a CameraInfo beside it, the sensor's options (``Depth_Units``) as
strings.  This is what a RealSense camera recorded by ``rs-record``, the RealSense Viewer or
``rs.config.enable_record_to_file`` looks like, so the tests read the real format written by the
real library.  Needs ``pyrealsense2``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Iterable

import numpy as np

from hw.depth import Intrinsics

__all__ = ["write_realsense_recording"]


def write_realsense_recording(path: str | os.PathLike[str], frames: Iterable[np.ndarray],
                              intrinsics: Intrinsics, *, fps: int = 30,
                              depth_units: float = 0.001, serial: str = "000000000001") -> int:
    """Write (H, W) uint16 depth ``frames`` (in ``depth_units`` metres a sample) to a new
    librealsense recording ``path`` (``.db3``) at ``fps``; returns the number of frames."""
    import pyrealsense2 as rs

    target = Path(path)
    if target.exists():
        raise FileExistsError(f"{target}: exists")
    device = rs.software_device()
    device.register_info(rs.camera_info.name, "Intel RealSense D435 (software)")
    device.register_info(rs.camera_info.serial_number, serial)
    sensor = device.add_sensor("Stereo Module")
    camera = rs.intrinsics()
    camera.width, camera.height = intrinsics.width, intrinsics.height
    camera.fx, camera.fy, camera.ppx, camera.ppy = (intrinsics.fx, intrinsics.fy, intrinsics.cx,
                                                    intrinsics.cy)
    camera.model = rs.distortion.brown_conrady
    camera.coeffs = [0.0] * 5
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = rs.stream.depth, 0, 0
    stream.width, stream.height, stream.fps = intrinsics.width, intrinsics.height, fps
    stream.bpp, stream.fmt, stream.intrinsics = 2, rs.format.z16, camera
    profile = sensor.add_video_stream(stream)
    sensor.add_read_only_option(rs.option.depth_units, depth_units)
    recorder = rs.recorder(str(target), device)
    queue = rs.frame_queue(64)
    sensor.open(profile)
    sensor.start(queue)
    count = 0
    try:
        for depth in frames:
            depth = np.ascontiguousarray(depth, dtype=np.uint16)
            if depth.shape != (intrinsics.height, intrinsics.width):
                raise ValueError(f"a frame of {depth.shape}, the stream is "
                                 f"{intrinsics.height}x{intrinsics.width}")
            frame = rs.software_video_frame()
            frame.pixels = depth
            frame.bpp, frame.stride = 2, 2 * intrinsics.width
            frame.timestamp = count * 1000.0 / fps
            frame.domain = rs.timestamp_domain.hardware_clock
            frame.frame_number = count
            frame.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(frame)
            while queue.poll_for_frame():  # keep the queue from filling: frames are recorded
                pass
            count += 1
        time.sleep(0.05)
    finally:
        sensor.stop()
        sensor.close()
        del recorder  # the file is complete when the recorder goes
    return count
