"""detect_ms on the bundled room scenes: a saved station reference (loaded from disk) and one
VGA frame -> ChangeSet, registration included (issue 15's target: <= 33 ms median and <= 50 ms
p95 on one thread, <= 20 ms with the second core).

    .venv/bin/python bench/bench_detect.py [--runs 5] [--rounds 4] [--threads 1]
        [--ab OTHER_CHECKOUT [--ab-threads N]] [--scenes a,b,...] [--json OUT]

Scenes: every bundled room scene whose outcome is a comparison (the two not-at-station pairs
and the paper's synthetic clouds left out): at the station and the revisits at 2 / 5 / 10 cm.
For each, the reference is fused from its 3 frames, saved and loaded again (what a station's
reference is to the daemon); the current is the first frame of its recording.  A round runs
every scene ``--runs`` times after one warm-up call (so the reference's kept results are made);
every call is one sample.  Reported: the median and p95 of all samples, per-stage medians, the
machine and its load.

``--ab``: the same rounds, interleaved round by round, in a second worker process on another
checkout (e.g. a ``git worktree`` of the commit before a change): both workers' figures are
printed side by side, so they share the machine's load.  Each worker is a subprocess running
this file with ``--worker`` on its checkout.

``--threads N``: ChangeParams(threads=N) (2: registration beside cleaning, the two
directions on two threads) where the checkout has the field (before it, one thread only).
OMP / BLAS threads are pinned to 1.  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

HERE = Path(__file__).resolve().parent
NOT_COMPARED = ("office_far_offset", "storage_other_room")


def room_scenes(root: Path) -> list[str]:
    """The bundled scenes a check compares: all but the paper's clouds and the two
    not-at-station pairs."""
    names = sorted(p.name for p in (root / "sim_fixtures" / "scenes").iterdir() if p.is_dir())
    return [n for n in names if not n.startswith("paper_") and n not in NOT_COMPARED]


def room_cases(scenes: list[str]) -> list[tuple]:
    """Per scene: (name, the reference fused from its 3 frames, saved and loaded (a station's
    reference as the daemon holds it), the first current frame (H, W) uint16, intrinsics)."""
    from robot_change.change.scene import SceneModel, build_scene
    from sim_fixtures import load_scene

    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in scenes:
            sc = load_scene(name)
            build_scene(sc.reference_frames(), intrinsics=sc.intrinsics).save(
                Path(tmp) / "ref.npz")
            cases.append((name, SceneModel.load(Path(tmp) / "ref.npz"),
                          sc.current_frames()[0], sc.intrinsics))
    return cases


def worker(scenes: list[str], threads: int) -> None:
    """Load the scenes, then answer ``run N`` lines on stdin with one JSON line each."""
    sys.path.insert(0, os.getcwd())
    import dataclasses

    from robot_change.change.detect import detect_changes
    from robot_change.change.params import ChangeParams

    params = ChangeParams()
    if "threads" in {f.name for f in dataclasses.fields(ChangeParams)}:
        params = params.replace(threads=threads)
    elif threads > 1:
        raise SystemExit("this checkout has no ChangeParams.threads")
    cases = room_cases(scenes)
    print(json.dumps({"ready": len(cases)}), flush=True)
    for line in sys.stdin:
        runs = int(line.split()[1])
        samples, stages = [], {}
        for _name, ref, frame, intr in cases:
            detect_changes(ref, frame, params, intrinsics=intr)  # warm-up: the kept results
            for _ in range(runs):
                t0 = time.perf_counter()
                cs = detect_changes(ref, frame, params, intrinsics=intr)
                samples.append((time.perf_counter() - t0) * 1e3)
                for key, value in cs.timings_ms.items():
                    stages.setdefault(key, []).append(value)
        print(json.dumps({"samples": samples, "stages": stages}), flush=True)


class Worker:
    def __init__(self, checkout: Path, scenes: list[str], threads: int):
        env = dict(os.environ, PYTHONPATH=str(checkout))
        self.name = str(checkout)
        self.proc = subprocess.Popen(
            [sys.executable, str(HERE / "bench_detect.py"), "--worker", "--threads",
             str(threads), "--scenes", ",".join(scenes)], cwd=checkout, env=env,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.samples: list[float] = []
        self.stages: dict[str, list[float]] = {}

    def ready(self) -> None:
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"the worker on {self.name} ended before it was ready")

    def round(self, runs: int) -> None:
        self.proc.stdin.write(f"run {runs}\n")
        self.proc.stdin.flush()
        out = json.loads(self.proc.stdout.readline())
        self.samples += out["samples"]
        for key, values in out["stages"].items():
            self.stages.setdefault(key, []).extend(values)

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=30)

    def summary(self) -> dict:
        s = sorted(self.samples)
        return {"checkout": self.name, "n": len(s), "median_ms": round(statistics.median(s), 2),
                "p95_ms": round(s[min(len(s) - 1, int(round(0.95 * (len(s) - 1))))], 2),
                "stages_ms": {k: round(statistics.median(v), 2)
                              for k, v in sorted(self.stages.items())}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="calls per scene per round")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--ab", type=Path, help="a second checkout, interleaved round by round")
    ap.add_argument("--ab-threads", type=int, help="--threads of the second checkout")
    ap.add_argument("--scenes", help="comma-separated scene names (default: the room scenes)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    root = HERE.parent
    scenes = args.scenes.split(",") if args.scenes else room_scenes(root)
    if args.worker:
        worker(scenes, args.threads)
        return 0
    if args.ab is not None and not (args.ab / "robot_change").is_dir():
        raise SystemExit(f"--ab {args.ab}: not a checkout of robot_change")
    workers = [Worker(root, scenes, args.threads)]
    if args.ab is not None:
        workers.append(Worker(args.ab.resolve(), scenes, args.ab_threads or args.threads))
    for w in workers:
        w.ready()
    load_before = os.getloadavg()
    for _ in range(args.rounds):
        for w in workers:
            w.round(args.runs)
    load_after = os.getloadavg()
    for w in workers:
        w.close()
    sys.path.insert(0, str(root))
    from robot_change.tools.benchmark import machine_info

    report = {"machine": machine_info(), "loadavg_before": load_before,
              "loadavg_after": load_after, "scenes": len(scenes), "runs": args.runs,
              "rounds": args.rounds, "threads": args.threads,
              "results": [w.summary() for w in workers]}
    for r in report["results"]:
        print(f"{r['checkout']}: detect_ms median {r['median_ms']} p95 {r['p95_ms']} "
              f"(n = {r['n']})")
        print("   " + " ".join(f"{k.replace('_ms', '')} {v}" for k, v in r["stages_ms"].items()))
    if len(workers) == 2:
        a, b = report["results"]
        print(f"ratio (this / other): median {a['median_ms'] / b['median_ms']:.3f}, "
              f"p95 {a['p95_ms'] / b['p95_ms']:.3f}")
    print(f"load {load_before[0]:.2f} -> {load_after[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
