"""Codec speed: frames decoded (and encoded) per second on one core.

    .venv/bin/python bench/bench_protocol.py [--frames 20000] [--repeat 5] [--json]

Streams of frames are fed to a FrameDecoder in 4 KiB chunks (what a port read returns), per
message kind and as a realistic mix.  The best of ``--repeat`` runs is reported.  Target
(issue 6): >= 50 000 frames/s, so the codec is never what slows the daemon.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robot_change.link import protocol as p  # noqa: E402

REGIONS = [p.Region(p.RegionKind.APPEARED, (i, -i, 2000), (300, 200, 100), 1000 + i)
           for i in range(11)]
KINDS = {
    "ACK (9 B)": [(p.Ack(), 5, 0)],
    "PAUSE (10 B)": [(p.Pause(p.PauseCause.CHANGE_WATCH), 6, p.FLAG_URGENT)],
    "HEARTBEAT (17 B)": [(p.Heartbeat(p.ModuleState.WATCHING, True, True, False, 299, 123456),
                          0, 0)],
    "CHANGE_REPORT 11 regions (~210 B)": [(p.ChangeReport(3, 0, 1, "kitchen", tuple(REGIONS)),
                                           9, 0)],
    # what the module's receiver mostly sees: base heartbeats, ACKs, a few commands
    "mix": [(p.BaseHeartbeat(p.Motion.PARKED), 0, 0)] * 6 + [(p.Ack(), 7, 0)] * 3
           + [(p.Check("kitchen"), 8, 0), (p.SetParam(1, 3), 9, 0)],
}


def stream(kind: list, frames: int) -> bytes:
    wires = [p.encode(m, seq, flags) for m, seq, flags in kind]
    return b"".join(wires[i % len(wires)] for i in range(frames))


def decode_rate(data: bytes, frames: int, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        decoder = p.FrameDecoder()
        t0 = time.perf_counter()
        for i in range(0, len(data), 4096):
            decoder.feed(data[i:i + 4096])
        best = min(best, time.perf_counter() - t0)
        assert decoder.frames == frames and decoder.errors == 0
    return frames / best


def encode_rate(kind: list, frames: int, repeat: int) -> float:
    best = float("inf")
    items = [kind[i % len(kind)] for i in range(frames)]
    for _ in range(repeat):
        t0 = time.perf_counter()
        for m, seq, flags in items:
            p.encode(m, seq, flags)
        best = min(best, time.perf_counter() - t0)
    return frames / best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    results = {}
    for name, kind in KINDS.items():
        data = stream(kind, args.frames)
        results[name] = {
            "decode_frames_per_s": round(decode_rate(data, args.frames, args.repeat)),
            "encode_frames_per_s": round(encode_rate(kind, args.frames, args.repeat)),
            "bytes_per_frame": round(len(data) / args.frames, 1),
        }
    machine = (f"{platform.python_implementation()} {platform.python_version()} "
               f"on {platform.machine()}")
    if args.json:
        print(json.dumps({"machine": machine, "frames": args.frames, "results": results}))
        return 0
    print(f"codec speed, best of {args.repeat} x {args.frames} frames, one core ({machine})")
    for name, r in results.items():
        print(f"  {name:36s} decode {r['decode_frames_per_s']:>9,d} /s   "
              f"encode {r['encode_frames_per_s']:>9,d} /s")
    worst = min(r["decode_frames_per_s"] for r in results.values())
    print(f"slowest decode: {worst:,d} frames/s (target >= 50,000)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
