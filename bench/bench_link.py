"""Serial-link figures for docs/benchmarks.md ("Serial link"): `robot-change link-bench` in each
mode, versions 2 (whole frames), 3 and 4 (the module's messages in PARTs) and 5 (the base's
too), 1 % and 10 % mixed corruption, median of --runs.

    .venv/bin/python bench/bench_link.py [--runs 3] [--quick] [--only check restart]
"""

from __future__ import annotations

import argparse
import io
import json
import os

from robot_change.tools.linkbench import median_of, run_link_bench


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="fewer rounds per run")
    parser.add_argument("--only", nargs="+", metavar="MODE", help="run only these modes")
    args = parser.parse_args()
    n = 10 if args.quick else 1
    cases = [("report", 3, 0.10, 50 // n), ("report", 2, 0.10, 10 // n or 1),
             ("report", 3, 0.01, 30 // n), ("report", 2, 0.01, 30 // n),
             ("report", 3, 0.10, 20 // n, 11), ("status", 3, 0.10, 60 // n),
             ("status", 2, 0.10, 60 // n), ("status", 3, 0.01, 60 // n),
             ("pause", 3, 0.10, 100 // n), ("flood", 3, 0.0, 5000 // n),
             ("flood", 2, 0.0, 5000 // n), ("status", 5, 0.10, 60 // n),
             ("check", 5, 0.10, 100 // n), ("check", 4, 0.10, 100 // n),
             ("check", 5, 0.01, 100 // n), ("restart", 5, 0.10, 100 // n),
             ("idle", 5, 0.10, 120 // n), ("idle", 4, 0.10, 120 // n)]
    if args.only:
        cases = [case for case in cases if case[0] in args.only]
    print(f"# load average at start: {os.getloadavg()}")
    for mode, proto, corrupt, count, *rest in cases:
        regions = rest[0] if rest else 3
        runs = [run_link_bench(corrupt, count, json=True, out=io.StringIO(), seed=seed,
                               mode=mode, proto=proto, regions=regions)
                for seed in range(1 if mode == "flood" else args.runs)]
        print(json.dumps(median_of(runs)), flush=True)
    print(f"# load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
