"""Benchmark of the depth -> clean cloud chain (ALGORITHM.md section 1), stage by stage.

    .venv/bin/python bench/bench_preprocess.py [--runs 30] [--warmup 3] [--json]

For each real VGA frame in ../shared/data (the TUM office frame, depth / 5000 m, and OSD
table-top frames, millimetres) prints the medians over ``--runs`` calls of
``robot_change.cloud.chain.clean_cloud`` after ``--warmup`` calls (``robot_change.tools.benchmark.
bench_preprocess``): ``voxel_ms`` (depth to voxel grid, back-projection included),
``outlier_ms`` (statistical outlier removal), ``plane_ms`` (RANSAC + refit), ``preprocess_ms``
(the whole call), with the point counts after each stage; ``points_ms`` is back-projection alone,
timed separately (the chain runs it inside the voxel pass).  The room
defaults (``CloudParams()``) run on every frame, the table-top parameters (1 cm leaf, 1 cm
plane distance) on the OSD frames too.  Also times ``fuse_depth`` over 10 frames.  Single
thread, as the kernels are written.  A benchmark, never a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hw.depth import Intrinsics  # noqa: E402
from hw.images import read_depth_image  # noqa: E402
from robot_change.cloud.chain import CloudParams  # noqa: E402
from robot_change.cloud.fusion import fuse_depth  # noqa: E402
from robot_change.tools.benchmark import bench_preprocess, machine_info  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
STAGES = ("points_ms", "voxel_ms", "outlier_ms", "plane_ms", "preprocess_ms")
COUNTS = ("pixels", "points", "voxels", "after_outliers", "plane_inliers", "kept")
TABLETOP = CloudParams(leaf_m=0.01, plane_distance_m=0.01)


def frames() -> list[tuple[str, np.ndarray]]:
    """(name, (480, 640) uint16 mm) for the frames that exist beside the repository."""
    found = []
    tum = DATA / "open3d-tum-sample" / "TUM_depth.png"
    if tum.is_file():
        found.append(("tum-office", read_depth_image(tum, scale=5000)))
    for name in ("test9", "learn38"):
        path = DATA / "osd-tabletop" / "derived" / f"{name}_depth_mm.png"
        if path.is_file():
            found.append((f"osd-{name}", read_depth_image(path)))
    return found


def bench_frame(depth: np.ndarray, params: CloudParams, runs: int, warmup: int) -> dict:
    intrinsics = Intrinsics.openni_default(depth.shape[1], depth.shape[0])
    result = bench_preprocess(depth, intrinsics, params, runs, warmup)
    result.update({f"n_{key}": value for key, value in result.pop("stage_counts").items()})
    return result


def bench_fusion(depth: np.ndarray, runs: int, warmup: int, n_frames: int = 10) -> dict:
    rng = np.random.default_rng(0)
    noisy = depth.astype(np.float64) + rng.normal(0, 5, (n_frames, *depth.shape))
    stack = np.where(depth > 0, np.clip(noisy, 1, 65535), 0).astype(np.uint16)
    stack[rng.random(stack.shape) < 0.05] = 0
    for _ in range(warmup):
        fuse_depth(stack, 3)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fuse_depth(stack, 3)
        times.append((time.perf_counter() - start) * 1e3)
    return {"fuse_ms": round(statistics.median(times), 3), "frames": n_frames}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    found = frames()
    if not found:
        print(f"no frames found under {DATA}", file=sys.stderr)
        return 1
    results = []
    for name, depth in found:
        configs = [("room-defaults", CloudParams())]
        if name.startswith("osd"):
            configs.append(("tabletop", TABLETOP))
        for label, params in configs:
            row = {"frame": name, "params": label,
                   **bench_frame(depth, params, args.runs, args.warmup)}
            results.append(row)
    fusion = bench_fusion(found[0][1], args.runs, args.warmup)
    if args.json:
        print(json.dumps({"machine": machine_info(), "runs": args.runs, "preprocess": results,
                          "fusion": fusion}, indent=2))
        return 0
    print(f"medians of {args.runs} runs after {args.warmup} warm-up, ms; one thread")
    header = (f"{'frame':12s} {'params':13s} " + " ".join(f"{k[:-3]:>8s}" for k in STAGES)
              + "  " + " ".join(f"{k:>8s}" for k in ("pixels", "voxels", "no_out", "plane",
                                                       "kept")))
    print(header)
    for row in results:
        print(f"{row['frame']:12s} {row['params']:13s} "
              + " ".join(f"{row[k]:8.2f}" for k in STAGES) + "  "
              + " ".join(f"{row['n_' + k]:8d}" for k in ("pixels", "voxels", "after_outliers",
                                                         "plane_inliers", "kept")))
    print(f"fuse_depth over {fusion['frames']} VGA frames: {fusion['fuse_ms']:.2f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
