"""Benchmark of the OpenNI2 backend (not a test): .oni replay and DummyDevice live frame rates.

    .venv/bin/python bench/bench_openni2.py [--frames 200] [--repeats 5]

Replay: a 640x480 recording written with hw.oni (raw and 16z), played through the real
libOpenNI2 in the reader child process and delivered as DepthFrames to this process; the rate
counts from the first frame to the end (the reader start-up is reported separately).  Target:
>= 300 fps.  Live: frames per second delivered from OpenNI's DummyDevice (320x240, nominally
30 fps) and the frames it reports dropped.  Prints medians over the repeats.
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

from hw.oni import write_oni  # noqa: E402
from hw.openni2 import open_device, open_recording  # noqa: E402


def vga_frames(count: int) -> list[np.ndarray]:
    """Kinect-like VGA depth: a sloped room, a box, sensor noise and dropouts (mm)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:480, 0:640]
    base = 1500.0 + 4.0 * yy + 1.5 * xx
    base[120:240, 200:330] = 900.0
    out = []
    for _ in range(count):
        depth = (base + rng.normal(0.0, 2.0, base.shape)).astype(np.uint16)
        depth[rng.random(depth.shape) < 0.02] = 0
        out.append(depth)
    return out


def replay(path: Path) -> tuple[float, float, int]:
    """(start-up seconds, frames per second, frames) for one full replay."""
    t0 = time.perf_counter()
    with open_recording(str(path)) as source:
        first = source.read(10.0)
        t1 = time.perf_counter()
        count = 1
        while source.read(10.0) is not None:
            count += 1
        t2 = time.perf_counter()
    assert first is not None
    return t1 - t0, (count - 1) / (t2 - t1), count


def live(seconds: float) -> tuple[float, int, int]:
    """(frames per second, frames, dropped) from the DummyDevice over ``seconds``."""
    with open_device("Oz") as source:
        source.read(10.0)
        start = time.perf_counter()
        count = 0
        while time.perf_counter() - start < seconds:
            source.read(2.0)
            count += 1
        elapsed = time.perf_counter() - start
        return count / elapsed, count, source.stats.dropped


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--live-seconds", type=float, default=3.0)
    args = parser.parse_args()
    print(f"machine: {os.cpu_count()} cpus; {args.frames} VGA frames, {args.repeats} repeats, "
          "medians")
    frames = vga_frames(args.frames)
    with tempfile.TemporaryDirectory() as tmp:
        for codec in ("none", "16z"):
            path = Path(tmp) / f"vga-{codec}.oni"
            t = time.perf_counter()
            write_oni(path, frames, codec=codec)
            write_s = time.perf_counter() - t
            runs = [replay(path) for _ in range(args.repeats)]
            starts, rates, counts = zip(*runs, strict=True)
            assert set(counts) == {args.frames}, counts
            print(f"replay 640x480 codec={codec:4s}: {statistics.median(rates):7.1f} fps "
                  f"(min {min(rates):.1f}, max {max(rates):.1f}); reader start-up "
                  f"{statistics.median(starts) * 1000:.0f} ms; "
                  f"file {path.stat().st_size / args.frames / 1024:.0f} KB/frame; "
                  f"write {args.frames / write_s:.0f} frames/s")
    runs = [live(args.live_seconds) for _ in range(max(1, args.repeats // 2))]
    rates, counts, dropped = zip(*runs, strict=True)
    print(f"live DummyDevice 320x240: {statistics.median(rates):5.1f} fps delivered "
          f"(nominal 30), dropped per run {list(dropped)}")


if __name__ == "__main__":
    main()
