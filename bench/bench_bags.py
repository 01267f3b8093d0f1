"""Benchmark of reading depth from bags (not a test): frames per second through the rosbag backend.

    .venv/bin/python bench/bench_bags.py [--frames 300] [--repeats 7]

Bags of 640x480 depth are written with rosbags' own writers (a ROS 2 MCAP bag, a ROS 2 .db3, a
ROS 1 .bag), as raw 16UC1 and as image_transport's compressedDepth (PNG at its default level 9,
and RVL); with pyrealsense2 present, also a RealSense recording written by librealsense, read
by the bag backend and played by librealsense (``realsense:``, in its reader process).  The
depth is the real SUN3D Xtion frames of ../shared/data (cycled), else the bundled Kinect-like
fixture frames.  Each bag is read through ``open_depth`` from its first frame to its last;
the rate is the median over the repeats, the kinds interleaved within each repeat.  Target
(issue 43): compressedDepth at least 300 frames/s.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_rosbag import CAMERA, write_bag  # noqa: E402

from hw.compressed_depth import encode_compressed_depth  # noqa: E402
from hw.depth import DepthFrame, open_depth  # noqa: E402
from hw.errors import BackendUnavailable  # noqa: E402
from hw.imagefile import read_image  # noqa: E402

SUN3D = Path(__file__).resolve().parents[2] / "shared" / "data" / \
    "sun3d-studyroom-xtion-50f-pose" / "frames"
TOPIC = "/camera/depth/image_raw"


def depth_frames(count: int) -> tuple[list[np.ndarray], str]:
    files = sorted(SUN3D.glob("*.depth.png")) if SUN3D.is_dir() else []
    if files:
        images = [read_image(path) for path in files]
        return [images[k % len(images)] for k in range(count)], f"SUN3D Xtion ({len(files)} cycled)"
    from hw.oni import read_oni_frames
    scene = Path(__file__).resolve().parents[1] / "sim_fixtures" / "scenes" / "office_box_added"
    images = [frame.depth for frame in read_oni_frames(scene / "reference.oni")]
    return [images[k % len(images)] for k in range(count)], "fixture office_box_added (cycled)"


def write_all(folder: Path, frames: list[np.ndarray]) -> dict[str, str]:
    """kind -> URI of a bag holding ``frames``."""
    stamps = [1_000_000_000 + k * 33_333_333 for k in range(len(frames))]
    png = lambda k, d: encode_compressed_depth(d, "png", png_level=9)  # noqa: E731
    rvl = lambda k, d: encode_compressed_depth(d, "rvl")  # noqa: E731
    bags = {
        "mcap raw 16UC1": write_bag(folder / "raw", "mcap", frames, stamps=stamps),
        "mcap compressedDepth png": write_bag(folder / "png", "mcap", frames, stamps=stamps,
                                              topic=TOPIC + "/compressedDepth", compressed=png),
        "db3 compressedDepth png": write_bag(folder / "png3", "db3", frames, stamps=stamps,
                                             topic=TOPIC + "/compressedDepth", compressed=png),
        "ros1 compressedDepth png": write_bag(folder / "png1", "ros1", frames, stamps=stamps,
                                              topic=TOPIC + "/compressedDepth", compressed=png),
        "mcap compressedDepth rvl": write_bag(folder / "rvl", "mcap", frames, stamps=stamps,
                                              topic=TOPIC + "/compressedDepth", compressed=rvl),
    }
    uris = {kind: f"rosbag:{path}" for kind, path in bags.items()}
    try:
        from hw.realsense_record import write_realsense_recording
        write_realsense_recording(folder / "rs.db3", [DepthFrame(depth, k * 33_333, k, CAMERA)
                                                      for k, depth in enumerate(frames)])
    except BackendUnavailable:
        return uris
    uris["librealsense .db3, bag backend"] = f"rosbag:{folder / 'rs.db3'}"
    uris["librealsense .db3, librealsense"] = f"realsense:{folder / 'rs.db3'}"
    return uris


def read_rate(uri: str) -> tuple[float, int]:
    """(frames per second, frames) reading ``uri`` from open to its last frame."""
    start = time.perf_counter()
    count = 0
    with open_depth(uri) as source:
        while source.read() is not None:
            count += 1
    return count / (time.perf_counter() - start), count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    frames, what = depth_frames(args.frames)
    with tempfile.TemporaryDirectory() as scratch:
        uris = write_all(Path(scratch), frames)
        sizes = {kind: sum(f.stat().st_size for f in Path(uri.split(":", 1)[1]).rglob("*"))
                 if Path(uri.split(":", 1)[1]).is_dir() else
                 Path(uri.split(":", 1)[1]).stat().st_size for kind, uri in uris.items()}
        rates: dict[str, list[float]] = {kind: [] for kind in uris}
        read_rate(next(iter(uris.values())))  # warm the kernels and the imports
        for _ in range(args.repeats):
            for kind, uri in uris.items():
                rate, count = read_rate(uri)
                assert count == len(frames), (kind, count)
                rates[kind].append(rate)
    load = os.getloadavg()[0]
    print(f"machine: {os.cpu_count()} cpus, load {load:.2f}; {len(frames)} frames of {what}; "
          f"{args.repeats} repeats, kinds interleaved; medians")
    print(f"{'bag':34s} {'frames/s':>9s} {'min':>7s} {'max':>7s} {'MB':>7s}")
    for kind, values in rates.items():
        print(f"{kind:34s} {statistics.median(values):9.0f} {min(values):7.0f} "
              f"{max(values):7.0f} {sizes[kind] / 1e6:7.1f}")


if __name__ == "__main__":
    main()
