"""A/B timing of the depth -> clean cloud chain: this checkout against another source tree.

    .venv/bin/python bench/ab_preprocess.py --other /path/to/old/checkout [--rounds 5]
        [--runs 40] [--frame PNG] [--scale 1000] [--leaf 0.03] [--json OUT] [--plot PNG]

A shared machine drifts by tens of percent within minutes, so two versions timed one after the
other are not comparable.  This script alternates them: each round runs ``clean_cloud`` in a
fresh subprocess per tree (``sys.path`` starting at that tree; numba caches warm), ``--runs``
calls after 3 warm-up calls, and keeps the per-stage medians; the result is the median over the
rounds of those medians, per tree, with the load average.  Stages present in only one tree's
``timings_ms`` are reported for that tree only.  Make ``--other`` with ``git worktree add``.
With ``--plot``, a bar chart of the stages (matplotlib, the ``viz`` extra).  A benchmark, never
a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FRAME = ROOT / "sim_fixtures" / "frames" / "room_vga.png"

# Runs inside the subprocess: argv = tree, frame, scale, leaf, runs.  Prints one JSON object.
_CHILD = r"""
import json, statistics, sys
sys.path.insert(0, sys.argv[1])
from hw.depth import Intrinsics
from hw.images import read_depth_image
from robot_change.cloud.chain import CloudParams, clean_cloud
depth = read_depth_image(sys.argv[2], scale=float(sys.argv[3]))
camera = Intrinsics.openni_default(depth.shape[1], depth.shape[0])
params = CloudParams(leaf_m=float(sys.argv[4]))
for _ in range(3):
    cloud = clean_cloud(depth, camera, params)
samples = {}
for _ in range(int(sys.argv[5])):
    cloud = clean_cloud(depth, camera, params)
    for key, value in cloud.timings_ms.items():
        samples.setdefault(key, []).append(value)
out = {key: statistics.median(values) for key, values in samples.items()}
out["kept"] = len(cloud.points)
print(json.dumps(out))
"""


def run_tree(tree: Path, args: argparse.Namespace) -> dict:
    result = subprocess.run(
        [sys.executable, "-c", _CHILD, str(tree), str(args.frame), str(args.scale),
         str(args.leaf), str(args.runs)],
        capture_output=True, text=True, check=True, cwd=tree,
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--other", type=Path, required=True, help="the other source tree")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--runs", type=int, default=40)
    parser.add_argument("--frame", type=Path, default=FRAME)
    parser.add_argument("--scale", type=float, default=1000.0, help="depth units per metre")
    parser.add_argument("--leaf", type=float, default=0.03)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--plot", type=Path)
    args = parser.parse_args(argv)
    trees = {"other": args.other.resolve(), "this": ROOT}
    rounds: dict[str, list[dict]] = {name: [] for name in trees}
    for _ in range(args.rounds):
        for name, tree in trees.items():
            rounds[name].append(run_tree(tree, args))
    summary = {}
    for name, results in rounds.items():
        keys = [k for k in results[0] if k != "kept"]
        summary[name] = {k: round(statistics.median(r[k] for r in results), 3) for k in keys}
        summary[name]["round_medians_preprocess_ms"] = [round(r["preprocess_ms"], 3)
                                                        for r in results]
        summary[name]["kept"] = results[-1]["kept"]
        summary[name]["tree"] = str(trees[name])
    summary["load_average"] = os.getloadavg()
    summary["frame"] = str(args.frame)
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    if args.plot:
        plot(summary, args.plot)
    return 0


def plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = ["points_ms", "voxel_ms", "outlier_ms", "plane_ms"]
    fig, ax = plt.subplots(figsize=(7.5, 3.0))
    for row, name in enumerate(("other", "this")):
        left = 0.0
        for stage, colour in zip(stages, ("#9ecae1", "#3182bd", "#fd8d3c", "#74c476"), strict=True):
            width = summary[name].get(stage, 0.0)
            if width:
                label = {"points_ms": "back-projection", "voxel_ms": "voxel grid (now with "
                         "back-projection)"}.get(stage, stage[:-3])
                ax.barh(row, width, left=left, color=colour,
                        label=label if row == 1 or stage == "points_ms" else None)
                left += width
        rest = summary[name]["preprocess_ms"] - left
        ax.barh(row, rest, left=left, color="#bdbdbd", label="bookkeeping" if row else None)
        ax.text(summary[name]["preprocess_ms"] + 0.1, row,
                f"{summary[name]['preprocess_ms']:.2f} ms", va="center",
                bbox={"facecolor": "white", "edgecolor": "none", "pad": 1})
    ax.axvline(5.0, color="k", ls="--", lw=1)
    ax.set_xlim(0, 1.18 * max(summary[name]["preprocess_ms"] for name in ("other", "this")))
    ax.set_yticks([0, 1], ["before", "now"])
    ax.set_xlabel("ms per VGA frame (median of round medians); dashed: the 5 ms target")
    ax.legend(ncol=3, fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
