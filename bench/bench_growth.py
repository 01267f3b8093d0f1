"""How the fit and the check grow with the cloud's size and the mixture's K bound (issue 15:
no worse than linear in both), with a plot for docs/benchmarks.md.

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_growth.py [--runs 5]
        [--scenes a,b,c] [--leaves 0.01,0.015,0.02,0.025,0.03] [--bounds 8,16,32,48,64]
        [--json OUT] [--plot docs/img/growth.png]

For each scene (default: three rooms), the reference fused from its 3 frames and the first
current frame:

* points: the voxel leaf from 1 to 3 cm (the K bound at its default, 16): the reference's clean
  cloud has N points; ``fit_ms`` is ``fit_mixture`` on it (the library's defaults at that
  leaf), ``detect_ms`` a check of the current frame against the reference built at that leaf;
* K bound: ``max_components`` from 8 to 64 at the default 3 cm leaf: ``fit_ms`` and
  ``detect_ms`` as above (the K the criterion chose is reported beside the bound).

Medians of ``--runs`` calls after one warm-up, one thread (``threads=1``).  The growth is
summarised by the slope of log(time) against log(N) (1 = linear) and against log(bound).
A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from robot_change.change.detect import detect_changes  # noqa: E402
from robot_change.change.params import ChangeParams  # noqa: E402
from robot_change.change.scene import SceneParams, build_scene  # noqa: E402
from robot_change.cloud.chain import CloudParams  # noqa: E402
from robot_change.mixture.model import fit_mixture  # noqa: E402
from robot_change.tools.benchmark import machine_info, median_ms  # noqa: E402

SCENES = ("office_box_added", "lounge_chair_removed", "storage_carton_removed")


def measure(sc, params: SceneParams, runs: int) -> dict:
    ref = build_scene(sc.reference_frames(), params, intrinsics=sc.intrinsics)
    frame = sc.current_frames()[0]
    points = ref.cloud.points
    fit_kw = {"leaf": params.cloud.leaf_m, "max_components": params.max_components,
              "criterion": params.criterion, "seed": params.seed, "tol": params.tol,
              "max_iter": params.max_iter, "search_points": params.search_points}
    check = ChangeParams(threads=1)
    return {"n_points": int(len(points)), "k": int(ref.mixture.n_components),
            "fit_ms": median_ms(lambda: fit_mixture(points, **fit_kw), runs, warmup=1),
            "detect_ms": median_ms(lambda: detect_changes(ref, frame, check,
                                                          intrinsics=sc.intrinsics), runs,
                                   warmup=1)}


def slope(x, y) -> float:
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--leaves", default="0.01,0.015,0.02,0.025,0.03")
    ap.add_argument("--bounds", default="8,16,32,48,64")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--plot", type=Path)
    args = ap.parse_args(argv)
    from sim_fixtures import load_scene

    leaves = [float(v) for v in args.leaves.split(",")]
    bounds = [int(v) for v in args.bounds.split(",")]
    load_before = os.getloadavg()
    result = {"points": {}, "bound": {}}
    for name in args.scenes.split(","):
        sc = load_scene(name)
        rows = []
        for leaf in leaves:
            rows.append({"leaf_m": leaf, **measure(sc, SceneParams(cloud=CloudParams(leaf_m=leaf)),
                                                   args.runs)})
            print(f"{name} leaf {leaf:.3f}: {rows[-1]}", flush=True)
        result["points"][name] = rows
        rows = []
        for bound in bounds:
            rows.append({"bound": bound, **measure(sc, SceneParams(max_components=bound),
                                                   args.runs)})
            print(f"{name} bound {bound}: {rows[-1]}", flush=True)
        result["bound"][name] = rows
    summary = {}
    for name in result["points"]:
        pts, bnd = result["points"][name], result["bound"][name]
        summary[name] = {
            "fit_slope_points": round(slope([r["n_points"] for r in pts],
                                            [r["fit_ms"] for r in pts]), 2),
            "detect_slope_points": round(slope([r["n_points"] for r in pts],
                                               [r["detect_ms"] for r in pts]), 2),
            "fit_slope_bound": round(slope([r["bound"] for r in bnd],
                                           [r["fit_ms"] for r in bnd]), 2),
            "detect_slope_bound": round(slope([r["bound"] for r in bnd],
                                              [r["detect_ms"] for r in bnd]), 2)}
        print(f"{name}: log-log slopes {summary[name]}")
    result["slopes"] = summary
    result["loadavg"] = [load_before, os.getloadavg()]
    result["machine"] = machine_info()
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    if args.plot:
        plot(result, args.plot)
    return 0


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    panels = (("points", "n_points", "points in the reference's clean cloud (leaf 3 cm ... 1 cm)",
               "Growth with the cloud's size (K bound 16)"),
              ("bound", "bound", "K bound (max_components; leaf 3 cm)",
               "Growth with the mixture's K bound"))
    for ax, (sweep, key, xlabel, title) in zip(axes, panels, strict=True):
        for name, rows in result[sweep].items():
            x = [r[key] for r in rows]
            ax.plot(x, [r["fit_ms"] for r in rows], "o-", label=f"fit, {name}")
            ax.plot(x, [r["detect_ms"] for r in rows], "s--", label=f"check, {name}")
        xs = [r[key] for rows in result[sweep].values() for r in rows]
        ends = np.array([min(xs), max(xs)], float)
        top = max(r["fit_ms"] for rows in result[sweep].values() for r in rows)
        ax.plot(ends, top * ends / ends[1], "k:", label="linear (through the largest)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_title(title)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("ms (median, one thread)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
