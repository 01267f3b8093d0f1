"""The commands on depth sources themselves: ``record`` (a source to an .oni file, a ROS 2 bag
or a RealSense recording) and ``list-devices`` (the cameras connected now)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from hw.depth import open_depth
from robot_change.commands.common import _print_json
from robot_change.errors import InputError


def cmd_record(args: argparse.Namespace) -> int:
    """Record any depth source (a live camera, images, a recording, a bag) to an .oni file, a
    ROS 2 bag folder (MCAP storage) or a RealSense recording (.db3, by librealsense)."""
    from hw.record import record

    suffix = Path(args.out).suffix.lower()
    out_format = args.format or {".oni": "oni", ".db3": "realsense"}.get(suffix, "rosbag2")
    codecs = {"oni": ("16zt", "16z", "none"), "realsense": ("png", "none")}.get(out_format, ())
    if args.codec is not None and args.codec not in codecs:
        raise InputError(f"--codec {args.codec} is not for a {out_format} recording: "
                         + (f"choose {' or '.join(codecs)}" if codecs else "a ROS 2 bag is "
                            "written with zstd-compressed MCAP chunks (lossless)"))
    shown = [0.0]

    def progress(frames: int, seconds: float, size: int) -> None:
        if time.monotonic() - shown[0] >= 0.25:  # a line on a terminal, 4 times a second
            shown[0] = time.monotonic()
            print(f"\rrecording: {frames} frames, {seconds:.1f} s, {size / 1e6:.1f} MB "
                  "(Ctrl-C stops and keeps them)", end="", file=sys.stderr, flush=True)

    with open_depth(args.source) as source:
        written = record(source, args.out, frames=args.frames,
                         codec=args.codec or (codecs[0] if codecs else "16zt"),
                         progress=progress if sys.stderr.isatty() else None, format=out_format)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    out = Path(args.out)
    size = sum(item.stat().st_size for item in out.iterdir()) if out.is_dir() else \
        out.stat().st_size
    what = {"oni": "", "rosbag2": " (a ROS 2 bag: ros2 bag info / play it)",
            "realsense": " (a RealSense recording: play it with realsense:FILE or the "
                         "RealSense Viewer)"}[out_format]
    print(f"wrote {written} frame(s), {size / 1e6:.1f} MB, to {args.out}{what}")
    return 0


def cmd_list_devices(args: argparse.Namespace) -> int:
    """The OpenNI2 and RealSense cameras connected now, each with its URI."""
    import importlib

    from hw.errors import BackendUnavailable

    devices, missing = [], {}
    for backend, module in (("openni2", "hw.openni2"), ("realsense", "hw.realsense")):
        try:
            found = importlib.import_module(module).list_devices()
        except (ImportError, BackendUnavailable) as exc:
            missing[backend] = str(exc)
            continue
        for device in found:
            serial = device.get("serial") or ""
            uri = f"realsense://{serial}" if backend == "realsense" else \
                f"openni2://{serial or device['uri']}"
            devices.append({"backend": backend, "source": uri, **device})
    if args.json:
        _print_json({"devices": devices, **({"unavailable": missing} if missing else {})})
        return 0
    for device in devices:
        what = " ".join(str(device.get(key) or "") for key in ("vendor", "name")).strip()
        firmware = f"  firmware {device['firmware']}" if device.get("firmware") else ""
        print(f"{device['source']}  {what}{firmware}")
    if not devices:
        print("no OpenNI2 camera found (is it plugged in? a Kinect v1 needs libfreenect's "
              "OpenNI2 driver; see the README)")
        print("no RealSense camera found" if "realsense" not in missing else
              "RealSense cameras are not looked for: install the realsense extra "
              "(pip install pyrealsense2)")
    return 0
