"""A whole check against Open3D's nearest-neighbour change baseline, same frames, interleaved in
one process (issue 15: ours / Open3D <= 0.30).

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_vs_open3d.py [--runs 5] [--rounds 3]
        [--scenes a,b,...] [--json OUT]

Per scene (the bundled room scenes of bench/bench_detect.py): the station's reference is fused
from its 3 frames, and the current is the first frame of its recording.

* ours: the reference saved and loaded (a SceneModel), then ``detect_changes(reference, frame)``
  -- registration, cleaning, mixtures, free space, regions -- with ``threads=1`` (and, as a
  second row, the default ``threads=2``);
* Open3D (open3d-cpu, the ``bench`` extra): the reference *prepared* once, outside the timing:
  back-projected (0.3-5 m), a 3 cm voxel grid (``voxel_down_sample``), statistical outlier
  removal (20 neighbours, 2 sigma), the dominant plane removed (``segment_plane``, 2 cm, 1000
  RANSAC iterations); per frame, timed: the same for the current, then the nearest-neighbour
  distance both ways (``compute_point_cloud_distance``), a point farther than 5 cm from the
  other cloud is changed.  No registration: the plain baseline at the station.

The methods alternate call by call (ours, Open3D, ours with two threads), ``--runs`` calls per
scene per round, so they share the machine's load; medians and p95 over all calls.  Needs the
``bench`` extra (``pip install -e '.[bench]'``).  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_detect import room_cases, room_scenes  # noqa: E402

from robot_change.change.detect import detect_changes  # noqa: E402
from robot_change.change.params import ChangeParams  # noqa: E402
from robot_change.cloud.geometry import depth_to_points  # noqa: E402
from robot_change.tools.benchmark import machine_info  # noqa: E402

LEAF_M = 0.03
CHANGE_M = 0.05


def open3d_clean(o3d, depth: np.ndarray, intrinsics):
    """Depth (H, W) uint16 mm -> Open3D cloud: 3 cm voxels, outliers, dominant plane out."""
    points, _ = depth_to_points(depth, intrinsics, min_depth_m=0.3, max_depth_m=5.0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pcd = pcd.voxel_down_sample(LEAF_M)
    pcd, _ = pcd.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    _, inliers = pcd.segment_plane(distance_threshold=0.02, ransac_n=3, num_iterations=1000)
    return pcd.select_by_index(inliers, invert=True)


def open3d_check(o3d, reference, depth: np.ndarray, intrinsics) -> int:
    """The baseline's check of one frame against a prepared reference: changed points."""
    current = open3d_clean(o3d, depth, intrinsics)
    appeared = np.asarray(current.compute_point_cloud_distance(reference)) > CHANGE_M
    disappeared = np.asarray(reference.compute_point_cloud_distance(current)) > CHANGE_M
    return int(appeared.sum() + disappeared.sum())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--scenes")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    try:
        import open3d as o3d
    except ImportError:
        raise SystemExit("needs Open3D: pip install -e '.[bench]'") from None
    scenes = args.scenes.split(",") if args.scenes else room_scenes(ROOT)
    cases = [(name, ref, open3d_clean(o3d, np.asarray(ref.depth), intr), frame, intr)
             for name, ref, frame, intr in room_cases(scenes)]
    methods = {
        "ours (1 thread)": lambda ref, pre, f, intr: detect_changes(
            ref, f, ChangeParams(threads=1), intrinsics=intr),
        "Open3D NN": lambda ref, pre, f, intr: open3d_check(o3d, pre, f, intr),
        "ours (2 threads)": lambda ref, pre, f, intr: detect_changes(
            ref, f, ChangeParams(threads=2), intrinsics=intr),
    }
    times: dict[str, list[float]] = {m: [] for m in methods}
    for _name, ref, pre, frame, intr in cases:  # warm-up: compiles, the reference's kept results
        for fn in methods.values():
            fn(ref, pre, frame, intr)
    load_before = os.getloadavg()
    for _ in range(args.rounds):
        for _name, ref, pre, frame, intr in cases:
            for _ in range(args.runs):
                for m, fn in methods.items():
                    t0 = time.perf_counter()
                    fn(ref, pre, frame, intr)
                    times[m].append((time.perf_counter() - t0) * 1e3)
    load_after = os.getloadavg()
    rows = {}
    for m, ts in times.items():
        s = sorted(ts)
        rows[m] = {"median_ms": round(statistics.median(s), 2),
                   "p95_ms": round(s[min(len(s) - 1, int(round(0.95 * (len(s) - 1))))], 2),
                   "n": len(s)}
    o3d_med = rows["Open3D NN"]["median_ms"]
    for m, r in rows.items():
        r["ratio_to_open3d"] = round(r["median_ms"] / o3d_med, 3)
        print(f"{m:18s} median {r['median_ms']:7.2f} ms  p95 {r['p95_ms']:7.2f} ms  "
              f"ours/Open3D {r['ratio_to_open3d']:.3f}  (n = {r['n']})")
    print(f"{len(cases)} scenes, load {load_before[0]:.2f} -> {load_after[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"machine": machine_info(), "loadavg_before": load_before,
                                         "loadavg_after": load_after, "scenes": scenes,
                                         "runs": args.runs, "rounds": args.rounds,
                                         "results": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
