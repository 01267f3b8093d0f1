"""Benchmark of robot_change.mixture.model: one EM iteration (K = 8) and the whole split-EM fit.

    .venv/bin/python bench/bench_mixture.py [--runs 7] [--json]

Prints ``em_iter_ms`` (one fused EM iteration, 18k points, K = 8; target <= 3 ms),
``fit_ms`` / ``fit_k`` (split-EM to MDL on a room-sized cloud; target <= 50 ms median) and
K / time for each criterion, as medians after warm-up.  With ``--sklearn`` also times
scikit-learn's GaussianMixture at the same K for comparison.  A benchmark, never a test.

The cloud is synthetic until the real pipeline lands: the planes and boxes of a room seen from
a camera (camera optical frame: x right, y down, z forward), sampled on a 2 cm grid with 3 mm
Gaussian noise, floor already removed -- what ``clean_cloud`` hands the mixture.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robot_change.mixture.model import CRITERIA, fit_mixture  # noqa: E402
from robot_change.tools.benchmark import benchmark_em, median_ms  # noqa: E402


def _grid(origin, u, v, spacing):
    """Points on the parallelogram origin + a*u + b*v, a, b in [0, 1], on a spacing grid."""
    origin, u, v = (np.asarray(a, dtype=np.float64) for a in (origin, u, v))
    na = max(int(round(np.linalg.norm(u) / spacing)), 1)
    nb = max(int(round(np.linalg.norm(v) / spacing)), 1)
    a, b = np.meshgrid((np.arange(na) + 0.5) / na, (np.arange(nb) + 0.5) / nb, indexing="ij")
    return origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v


def _box(corner, size, spacing, faces=("front", "top", "left")):
    """Visible faces of an axis-aligned box (min corner, size (dx, dy, dz)); y is down."""
    c = np.asarray(corner, dtype=np.float64)
    dx, dy, dz = size
    parts = {
        "front": _grid(c, (dx, 0, 0), (0, dy, 0), spacing),           # facing the camera (z min)
        "top": _grid(c, (dx, 0, 0), (0, 0, dz), spacing),             # y min is the top
        "left": _grid(c, (0, dy, 0), (0, 0, dz), spacing),
        "right": _grid(c + (dx, 0, 0), (0, dy, 0), (0, 0, dz), spacing),
    }
    return np.vstack([parts[f] for f in faces])


def synthetic_room(spacing: float = 0.02, noise: float = 0.003, seed: int = 0) -> np.ndarray:
    """A room-sized clean cloud (19 893 points), camera 1.2 m above the removed floor."""
    floor_y = 1.2  # y is down: the floor is at y = +1.2
    parts = [
        _grid((-1.3, floor_y - 1.5, 3.4), (2.6, 0, 0), (0, 1.5, 0), spacing),    # back wall
        _grid((-1.3, floor_y - 1.1, 1.8), (0, 0, 1.6), (0, 1.1, 0), spacing),    # left wall
        _box((-0.2, floor_y - 0.75, 2.2), (1.0, 0.03, 0.6), spacing, ("top", "front")),  # table
        _box((0.75, floor_y - 0.72, 2.22), (0.04, 0.72, 0.04), spacing, ("front", "left")),
        _box((-0.18, floor_y - 0.72, 2.22), (0.04, 0.72, 0.04), spacing, ("front", "left")),
        _box((-1.0, floor_y - 0.4, 2.0), (0.4, 0.4, 0.4), spacing),                # box
        _box((0.6, floor_y - 0.9, 3.0), (0.5, 0.9, 0.38), spacing, ("front", "left")),  # cabinet
        _box((-0.7, floor_y - 0.3, 2.9), (0.3, 0.3, 0.3), spacing),                # small box
    ]
    pts = np.vstack(parts)
    rng = np.random.default_rng(seed)
    return pts + rng.normal(0.0, noise, pts.shape)



def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--sklearn", action="store_true", help="also time scikit-learn")
    args = parser.parse_args(argv)

    room = synthetic_room()
    out = benchmark_em(room, runs=args.runs)
    per = {}
    for crit in CRITERIA:
        fit = fit_mixture(room, crit)
        ms = median_ms(lambda crit=crit: fit_mixture(room, crit), args.runs, warmup=1)
        per[crit] = {"k": fit.n_components, "ms": ms, "em_runs": len(fit.record.steps),
                     "em_iter": fit.record.n_iter, "stop": fit.record.stop_reason}
    out["per_criterion"] = per
    if args.sklearn:
        from sklearn.mixture import GaussianMixture
        k = out["fit_k"]
        gm = GaussianMixture(k, covariance_type="full", random_state=0)
        out["sklearn_fit_ms_at_fit_k"] = median_ms(lambda: gm.fit(room), 3, warmup=1)
        gm8 = GaussianMixture(8, covariance_type="full", max_iter=1, tol=0, random_state=0)
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gm8.fit(room)
            out["sklearn_em_iter_ms"] = median_ms(lambda: (gm8._m_step(room, gm8._e_step(room)[1])),
                                                   args.runs)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"cloud: {out['n_points']} points (synthetic room, 2 cm, 3 mm noise)")
        print(f"em_iter_ms (K=8): {out['em_iter_ms']:.2f}")
        print(f"fit_ms (MDL): {out['fit_ms']:.1f}   fit_k: {out['fit_k']}")
        for crit, r in per.items():
            print(f"  {crit}: K = {r['k']:3d}  {r['ms']:8.1f} ms  EM runs {r['em_runs']:3d}  "
                  f"iterations {r['em_iter']:4d}  ({r['stop']})")
        for key in ("sklearn_em_iter_ms", "sklearn_fit_ms_at_fit_k"):
            if key in out:
                print(f"{key}: {out[key]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
