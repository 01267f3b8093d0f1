"""Write ``d435_ros1.bag``: a RealSense recording in librealsense's ROS 1 format (librealsense
before 2.58 wrote ``.bag``; 2.58 and later write ``.db3`` only, so the bundled file is what the
tests have of the old format), and ``d435_ros1.npy``, its depth, (6, 48, 64) uint16 mm.

Run with librealsense 2.56 (not the project's version), from the repository's top:

    python -m venv /tmp/rs56 && /tmp/rs56/bin/pip install numpy pyrealsense2==2.56.5.9235
    /tmp/rs56/bin/python sim_fixtures/realsense/make_ros1_recording.py

A software device (no camera) named "Intel RealSense D435", one Z16 stream of 64 x 48 at
30 fps, 1 mm units, fed 6 frames of random depth with holes while librealsense's recorder
writes them.  The tests read it through the bag backend and through librealsense 2.59's player.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyrealsense2 as rs

HERE = Path(__file__).resolve().parent
WIDTH, HEIGHT, FRAMES = 64, 48, 6


def main() -> None:
    device = rs.software_device()
    device.register_info(rs.camera_info.name, "Intel RealSense D435")
    device.register_info(rs.camera_info.serial_number, "000000000002")
    sensor = device.add_sensor("Stereo Module")
    camera = rs.intrinsics()
    camera.width, camera.height = WIDTH, HEIGHT
    camera.ppx, camera.ppy, camera.fx, camera.fy = 31.5, 23.5, 57.6, 57.6
    camera.model, camera.coeffs = rs.distortion.brown_conrady, [0.0] * 5
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = rs.stream.depth, 0, 0
    stream.width, stream.height, stream.fps = WIDTH, HEIGHT, 30
    stream.bpp, stream.fmt, stream.intrinsics = 2, rs.format.z16, camera
    profile = sensor.add_video_stream(stream)
    sensor.add_read_only_option(rs.option.depth_units, 0.001)
    recorder = rs.recorder(str(HERE / "d435_ros1.bag"), device)
    queue = rs.frame_queue(10)
    sensor.open(profile)
    sensor.start(queue)
    rng = np.random.default_rng(5)
    frames = []
    for index in range(FRAMES):
        depth = (1000 + 50 * index + rng.integers(0, 3000, (HEIGHT, WIDTH))).astype(np.uint16)
        depth[rng.random((HEIGHT, WIDTH)) < 0.1] = 0
        frames.append(depth)
        frame = rs.software_video_frame()
        frame.pixels, frame.bpp, frame.stride = depth, 2, 2 * WIDTH
        frame.timestamp, frame.frame_number = index * 1000 / 30, index
        frame.domain = rs.timestamp_domain.hardware_clock
        frame.profile = profile.as_video_stream_profile()
        sensor.on_video_frame(frame)
        while queue.poll_for_frame():
            pass
    sensor.stop()
    sensor.close()
    del recorder
    np.save(HERE / "d435_ros1.npy", np.stack(frames))


if __name__ == "__main__":
    main()
