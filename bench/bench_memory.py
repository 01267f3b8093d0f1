"""What a warm check adds to the process's resident memory (issue 15: <= 20 MB).

    .venv/bin/python bench/bench_memory.py [--runs 10] [--scenes a,b,...] [--json OUT]

Per scene (the bundled room scenes of bench/bench_detect.py): the reference is built, saved and
loaded, and one check runs to warm the kernels and the reference's kept results.  Then, for each
of ``--runs`` checks: the kernel's peak-RSS mark is reset (``/proc/self/clear_refs``, "5"), the
RSS read (``VmRSS``), the check run, and the peak read (``VmHWM``): the check's addition is the
peak less the RSS before it.  Reported: the largest and the median addition over all checks,
with one thread and with two, and the RSS after the last check against the RSS after the
warm-up (what stays).  Linux only.  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_detect import room_scenes  # noqa: E402

from robot_change.change.detect import detect_changes  # noqa: E402
from robot_change.change.params import ChangeParams  # noqa: E402
from robot_change.change.scene import SceneModel, build_scene  # noqa: E402
from robot_change.tools.benchmark import machine_info  # noqa: E402


def _status_mb(field: str) -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    raise SystemExit(f"no {field} in /proc/self/status")


def _reset_peak() -> None:
    Path("/proc/self/clear_refs").write_text("5")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--scenes")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    from sim_fixtures import load_scene

    scenes = args.scenes.split(",") if args.scenes else room_scenes(ROOT)
    out = {}
    for threads in (1, 2):
        params = ChangeParams(threads=threads)
        added, after_warm, after_last = [], None, None
        with tempfile.TemporaryDirectory() as tmp:
            for name in scenes:
                sc = load_scene(name)
                build_scene(sc.reference_frames(), intrinsics=sc.intrinsics).save(
                    Path(tmp) / "ref.npz")
                ref = SceneModel.load(Path(tmp) / "ref.npz")
                frame = sc.current_frames()[0]
                detect_changes(ref, frame, params, intrinsics=sc.intrinsics)  # warm
                if after_warm is None:
                    after_warm = _status_mb("VmRSS")
                for _ in range(args.runs):
                    _reset_peak()
                    before = _status_mb("VmRSS")
                    detect_changes(ref, frame, params, intrinsics=sc.intrinsics)
                    added.append(_status_mb("VmHWM") - before)
                after_last = _status_mb("VmRSS")
        out[f"threads_{threads}"] = {
            "checks": len(added), "max_added_mb": round(max(added), 1),
            "median_added_mb": round(statistics.median(added), 1),
            "rss_after_first_warm_check_mb": round(after_warm, 1),
            "rss_after_last_check_mb": round(after_last, 1)}
        r = out[f"threads_{threads}"]
        print(f"threads={threads}: a check adds at most {r['max_added_mb']} MB to the RSS "
              f"(median {r['median_added_mb']} MB, {r['checks']} checks); RSS "
              f"{r['rss_after_first_warm_check_mb']} MB after the first warm check, "
              f"{r['rss_after_last_check_mb']} MB after the last")
    if args.json:
        args.json.write_text(json.dumps({"machine": machine_info(), "scenes": scenes,
                                         "results": out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
