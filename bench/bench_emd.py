"""Benchmark of robot_change.change.transport: exact EMD at 10x10 and 30x30, greedy EMD both
ways at K = 30.

    .venv/bin/python bench/bench_emd.py [--runs 200] [--json]

Prints, as medians after warm-up (one thread):

- ``emd_10x10_us`` / ``emd_30x30_us``: one call of :func:`robot_change.change.transport.emd`
  (validation included) on mixtures of a room (means spread over 3 m, Euclidean ground distance);
- ``greedy_both_ways_k30_ms``: :func:`robot_change.change.transport.greedy_emd` reference ->
  current plus current -> reference at K = 30 vs 30, every component a candidate (target <= 2 ms);
  ``greedy_both_ways_k30_5cand_ms``: the same with 5 novelty candidates per side;
  ``..._worst_ms``: the slowest of the scenes;
- ``ground_w2_30x30_ms``: the 2-Wasserstein ground distance matrix at 30x30.

A scene: 30 reference components (means uniform in a 3 m box, random weights and
covariances); the current mixture keeps 25 of them, jittered by 2 cm and reweighted, and adds 5
new components (an object that appeared); 5 reference components are gone.  Several scenes
(seeds) are timed.  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robot_change.tools.benchmark import bench_emd  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--scenes", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    result = bench_emd(runs=args.runs, n_scenes=args.scenes)
    if args.json:
        print(json.dumps(result))
    else:
        for key, value in result.items():
            print(f"{key:34s} {value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
