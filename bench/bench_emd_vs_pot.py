"""Benchmark: our exact EMD (robot_change.change.transport.emd) against POT's network simplex.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 flock /tmp/robot_change_bench.lock \\
        .venv/bin/python bench/bench_emd_vs_pot.py [--runs 300] [--json] [--plot]

For each size (Ka x Kb: 10, 20, 30, 50, 70, 100 square and 16 x 40, 40 x 16, 100 x 30) and
each kind of problem, several problems (seeds) are timed call by call, ours and POT's
interleaved in one run (the order of the three calls rotates every round), one thread.
Printed per size and kind: median microseconds per call of

- ``ours``: the public ``emd(weights_a, weights_b, cost)`` (input checks, normalisation, the
  flow matrix and the result object included);
- ``pot_emd``: ``ot.emd(a, b, M)`` (the plan) then ``np.vdot(plan, M)`` (the cost);
- ``pot_emd2``: ``ot.emd2(a, b, M)`` (the cost);

and ``ratio`` = ours / the faster of the two POT entries (the fairer to POT), our simplex
pivots, and the largest difference of the costs (asserted <= 1e-9 against both POT entries).
For reference only, ``pot_core``: POT's compiled solver without its Python wrapper
(``ot.lp.emd_wrap.emd_c``, a private function; skipped if absent), and ``ratio_core``.
``a`` and ``b`` are already normalised and ``M`` C-contiguous float64, so POT converts nothing.

Kinds: ``mixture``: mixtures of a room (reference means uniform in a 4 x 4 x 2.5 m box, random
weights; the other side keeps 80 % of the components jittered by 2 cm and reweighted, the rest
new), Euclidean ground distance; ``degenerate``: integer weights 0..3 (ties, zero masses) and
costs on a 0.5 m grid (ties in the costs).  ``--plot`` writes docs/img/emd_vs_pot.png
(matplotlib).  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robot_change.change import transport  # noqa: E402
from robot_change.change.transport import emd  # noqa: E402

SIZES = ((10, 10), (20, 20), (30, 30), (50, 50), (70, 70), (100, 100), (16, 40), (40, 16),
         (100, 30))
KINDS = ("mixture", "degenerate")


def problem(kind: str, m: int, n: int, seed: int):
    """One transportation problem: (a (m,), b (n,), cost (m, n)), a and b summing to 1."""
    rng = np.random.default_rng([seed, m, n, KINDS.index(kind)])
    box = np.array([4.0, 4.0, 2.5])
    mu_a = rng.random((m, 3)) * box
    kept = rng.choice(m, min(n, int(round(0.8 * n))), replace=n > m)
    mu_b = np.vstack([mu_a[kept] + 0.02 * rng.standard_normal((len(kept), 3)),
                      rng.random((n - len(kept), 3)) * box])[rng.permutation(n)]
    cost = np.sqrt(((mu_a[:, None, :] - mu_b[None, :, :]) ** 2).sum(axis=-1))
    if kind == "mixture":
        a = rng.random(m) + 0.2
        b = rng.random(n) + 0.2
    else:
        a = rng.integers(0, 4, m).astype(float)
        b = rng.integers(0, 4, n).astype(float)
        a[rng.integers(m)] += 1.0  # never all zero
        b[rng.integers(n)] += 1.0
        cost = 0.5 * np.round(cost / 0.5)
    return a / a.sum(), b / b.sum(), np.ascontiguousarray(cost)


def time_size(ot, kind: str, m: int, n: int, runs: int, n_problems: int, warmup: int = 5):
    """Interleaved medians (us) of ours / ot.emd + cost / ot.emd2 on ``n_problems`` problems."""
    problems = [problem(kind, m, n, seed) for seed in range(n_problems)]
    calls = {
        "ours": lambda a, b, c: emd(a, b, c).distance,
        "pot_emd": lambda a, b, c: float(np.vdot(ot.emd(a, b, c), c)),
        "pot_emd2": lambda a, b, c: float(ot.emd2(a, b, c)),
    }
    core = getattr(getattr(ot.lp, "emd_wrap", None), "emd_c", None)
    if core is not None:
        calls["pot_core"] = lambda a, b, c: float(core(a, b, c, 100_000, 1)[1])
    names = list(calls)
    max_diff = 0.0
    pivots = []
    for a, b, c in problems:
        values = {name: fn(a, b, c) for name, fn in calls.items()}
        for name in names[1:]:
            diff = abs(values["ours"] - values[name])
            max_diff = max(max_diff, diff)
            assert diff <= 1e-9, (f"{kind} {m}x{n}: ours {values['ours']!r} vs {name} "
                                  f"{values[name]!r}")
        pivots.append(transport._emd_kernel(a, b, c, transport._REL_TOL_COST, -1)[3])
        for _ in range(warmup):
            for fn in calls.values():
                fn(a, b, c)
    times = {name: [] for name in names}
    for r in range(runs):
        a, b, c = problems[r % n_problems]
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            fn = calls[name]
            start = time.perf_counter()
            fn(a, b, c)
            times[name].append(time.perf_counter() - start)
    out = {name: round(1e6 * statistics.median(t), 1) for name, t in times.items()}
    out["ratio"] = round(out["ours"] / min(out["pot_emd"], out["pot_emd2"]), 3)
    if "pot_core" in out:
        out["ratio_core"] = round(out["ours"] / out["pot_core"], 3)
    out["pivots"] = int(np.median(pivots))
    out["max_diff"] = max_diff
    return out


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for kind, style in zip(KINDS, ("-", "--"), strict=True):
        square = [r for r in rows if r["kind"] == kind and r["m"] == r["n"]]
        k = [r["m"] for r in square]
        ax.plot(k, [r["ours"] for r in square], "o" + style, color="C0",
                label=f"ours, emd() ({kind})")
        ax.plot(k, [min(r["pot_emd"], r["pot_emd2"]) for r in square], "s" + style,
                color="C1", label=f"POT, faster of ot.emd / ot.emd2 ({kind})")
    ax.set_xlabel("K (K x K problem)")
    ax.set_ylabel("median time per call (us)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("exact EMD, one thread")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=300, help="timed calls per size and kind")
    parser.add_argument("--problems", type=int, default=6, help="problems per size and kind")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--plot", action="store_true", help="write docs/img/emd_vs_pot.png")
    args = parser.parse_args(argv)
    try:
        import ot
    except ImportError:
        print("POT is not installed (pip install pot)", file=sys.stderr)
        return 2
    import numba

    if numba.get_num_threads() != 1 or os.environ.get("OMP_NUM_THREADS") != "1":
        print("note: run with OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 (one thread)",
              file=sys.stderr)
    rows = []
    for kind in KINDS:
        for m, n in SIZES:
            row = dict(kind=kind, m=m, n=n, **time_size(ot, kind, m, n, args.runs,
                                                         args.problems))
            rows.append(row)
            if not args.json:
                print(f"{kind:10s} {m:3d} x {n:3d}  ours {row['ours']:8.1f} us  "
                      f"ot.emd {row['pot_emd']:8.1f} us  ot.emd2 {row['pot_emd2']:8.1f} us  "
                      f"ratio {row['ratio']:5.2f}  (core {row.get('pot_core', 0.0):6.1f} us, "
                      f"ratio {row.get('ratio_core', 0.0):5.2f})  pivots {row['pivots']:4d}  "
                      f"max |diff| {row['max_diff']:.1e}", flush=True)
    if args.json:
        print(json.dumps(dict(pot=ot.__version__, rows=rows)))
    if args.plot:
        plot(rows, Path(__file__).resolve().parents[1] / "docs" / "img" / "emd_vs_pot.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
