"""How far one change's regions move between WATCH checks of a parked robot: what
``robot_change.service.watch.EPISODE_MARGIN_M`` must cover (a region of a later check farther
than it from every box of the reported change is a new change, and pauses again).

    .venv/bin/python bench/watch_episode_margin.py [--split dev|holdout|all] [--seeds 4]
        [--json OUT]

Per changed scene of the split (sim_fixtures, Kinect noise; the paper's Gaussian ones left
out), rendered again with the harsh Kinect model fitted to real Xtion depth
(``sim_fixtures.harsh_noise.harsh_scene``, ``--seeds`` noise seeds x 3 current frames): the
reference built from seed 0's reference frames with the defaults, every current frame checked
alone as WATCH does (``detect_changes``, the defaults).  For every ordered pair of checks that
both found regions: the margin the later one needs to be taken as the earlier one's change,
the largest over its regions of the smallest gap to the earlier one's boxes (the largest gap
along an axis; 0 where the boxes meet).  Prints one JSON line per scene and the largest need
per split.  A benchmark, never a test: ~3 min per split on the 2-core machine.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import sim_fixtures  # noqa: E402
from robot_change.change.detect import detect_changes  # noqa: E402
from robot_change.change.scene import build_scene  # noqa: E402
from robot_change.service.watch import EPISODE_MARGIN_M  # noqa: E402
from sim_fixtures.harsh_noise import harsh_scene  # noqa: E402


def box_gap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> float:
    """The largest gap along an axis between the boxes ``a`` and ``b`` ((lo, hi), each (3,)
    m): 0 where they meet (what widening one by a margin each way must cover)."""
    return float(np.maximum(0.0, np.maximum(a[0] - b[1], b[0] - a[1])).max())


def scene_needs(name: str, seeds: int) -> dict:
    """The checks of scene ``name`` and the margins their pairs need (module docstring)."""
    harsh = [harsh_scene(name, seed=s) for s in range(seeds)]
    reference = build_scene(harsh[0].reference_frames(), intrinsics=harsh[0].intrinsics)
    checks = []
    for scene in harsh:
        for depth in scene.current_frames():
            found = detect_changes(reference, depth)
            checks.append((found.outcome, [(r.bbox_min, r.bbox_max) for r in found.regions]))
    needs = [max(min(box_gap(r, b) for b in earlier) for r in later)
             for (_, earlier), (_, later) in itertools.permutations(checks, 2)
             if earlier and later]
    outcomes = [o for o, _ in checks]
    return {"scene": name, "checks": len(checks),
            "outcomes": {o: outcomes.count(o) for o in sorted(set(outcomes))},
            "regions": [len(r) for _, r in checks],
            "need_max_m": round(max(needs), 4) if needs else None,
            "need_p95_m": round(float(np.percentile(needs, 95)), 4) if needs else None}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", choices=("dev", "holdout", "all"), default="all")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    rows = []
    for name in sim_fixtures.scene_names():
        scene = sim_fixtures.load_scene(name)
        if not scene.has_change or name.startswith("paper_") or \
                args.split not in ("all", scene.split):
            continue
        row = dict(scene_needs(name, args.seeds), split=scene.split)
        print(json.dumps(row), flush=True)
        rows.append(row)
    for split in sorted({r["split"] for r in rows}):
        needs = [r["need_max_m"] for r in rows if r["split"] == split and r["need_max_m"]]
        print(f"{split}: {sum(r['split'] == split for r in rows)} scenes, largest need "
              f"{max(needs, default=0.0) * 100:.1f} cm (EPISODE_MARGIN_M "
              f"{EPISODE_MARGIN_M * 100:.0f} cm)")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
