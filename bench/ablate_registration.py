"""Registration audited by ablation (issue 45, item 2): each special case of
``register_depth`` switched off in turn through ``RegistrationParams``, measured on every
registration set against the baseline (the defaults).

    OMP_NUM_THREADS=1 .venv/bin/python bench/ablate_registration.py [--quick]
        [--only NAME,...] [--sets fixtures,rooms,tabletop,stations] [--rooms SEEDS]
        [--room-levels 2,5,10,15] [--room-seed-base N] [--room-tag T]
        [--tabletop SEEDS [--tabletop-seed-base N] [--tabletop-tag T]]
        [--stations SEEDS] [--station-seed-bases B,...] [--station-tag T]
        [--max-minutes M] [--json OUT] [--list]

Sets (rendered or loaded by bench/bench_registration.py's functions, imported, not copied):
``fixtures`` the 21 room revisit fixtures; ``rooms`` the sweep's rendered room pairs at 2 / 5 /
10 / 15 cm (``--rooms 3``: the 108 pairs of docs/evaluation.md); ``tabletop`` the real table
tops re-rendered 5 / 10 / 15 cm away (``--tabletop 10``: 9 pairs x 10 seeds x 3 levels = 270;
its seeds 0-5 are docs/benchmarks.md's tuning sample ``--tabletop 6``; docs/evaluation.md
states 240); ``stations`` table stations at 5 / 10 / 15 cm, every change, per seed base
(``--stations 10 --station-seed-bases 8000,...,17000``: the ten sets of docs/evaluation.md).
``--quick``: a smoke test (rooms 1 seed at 15 cm, tabletop and stations 1 seed, base 8000).
The defaults are those full sizes; held-out draws, e.g.:

    nice -n 19 .venv/bin/python bench/ablate_registration.py --quick
    nice -n 19 .venv/bin/python bench/ablate_registration.py --json /tmp/ablate.json
    nice -n 19 .venv/bin/python bench/ablate_registration.py --sets rooms,tabletop \
        --rooms 2 --room-levels 10,15 --room-seed-base 91000 --room-tag held \
        --tabletop 6 --tabletop-seed-base 99000 --tabletop-tag held3

Each pair is built once and every ablation registers it in turn (the order rotated per
pair, so they share the machine's load); a pair's checks: converged (within 1 cm and 0.5 deg
of the truth), said weak (``Registration.weak`` not empty), time (ms, one run).  One JSON
line per (ablation, set) is printed at the end of each set: pairs, converged, share, the
change from the baseline in % of the checks, the wrong ones and how many of them were said
weak, the median ms and the median over pairs of the per-pair time ratio to the baseline.
``--max-minutes``: stop building pairs after that long and report the pairs done.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import bench_registration as br  # noqa: E402

from robot_change.change.registration import (  # noqa: E402
    RegistrationParams,
    invert,
    register_depth,
    rotation_angle_deg,
)

#: name -> (overrides of RegistrationParams, what they switch off and where)
ABLATIONS: dict[str, tuple[dict, str]] = {
    "none": ({}, "baseline: the defaults"),
    "coarse_search": ({"search_reach_m": 0.0},
                      "step 6 search at search_level (agreement.weak_search: translations and "
                      "screws) and with it the fine slide search (register._coarse_to_fine "
                      "runs both under search_reach_m > 0)"),
    "screw_search": ({"search_screw_steps": 0},
                     "the screw motions of the coarse search (agreement.weak_search)"),
    "fine_search": ({"fine_search_reach_m": 0.0},
                    "the fine slide search at search_level (register._slide -> "
                    "agreement.fine_search)"),
    "final_search": ({"final_search_reach_m": 0.0},
                     "step 7b, the final search along a weak slide (register._final_search, "
                     "agreement.slide_peaks); also collapses table_station._in_reach's slide "
                     "starts of step 7c to none"),
    "station_through": ({"station_through_ratio": 0.0},
                        "step 7c, the table station's structure test "
                        "(table_station.structure_search)"),
    "wide_cut": ({"wide_cut_m": 0.0},
                 "the coarsest level's second ICP with a wide Tukey cut "
                 "(register._coarse_to_fine)"),
    "end_restart": ({"restart_end_through": 0.0},
                    "step 7d, the coarse-to-fine passes again from 12 starts "
                    "(register._restarted_end)"),
    "table_starts": ({"table_starts": 0},
                     "step 6b, the table-plane starts (table_top.table_starts); the planes "
                     "are still found for the trimming and checks"),
    "trim": ({"trim_rounds": 0},
             "the table top's trimming rounds (register._coarse_to_fine, "
             "table_top.without_changed_objects)"),
    "table_top": ({"table_starts": 0, "trim_rounds": 0},
                  "every table-top case: the planes are not looked for (table_top.table_planes "
                  "runs only when table_starts or trim_rounds > 0), a table top is a room"),
    "table_hole_weight": ({"table_hole_weight": 0.0},
                          "holes in the scores taken both ways (table tracks, slide_peaks, "
                          "_final_search, _restarted_end)"),
    "table_outline_holes": ({"table_outline_holes": 0.0},
                            "the table outline check of the weak flags "
                            "(table_top.table_pose_weak)"),
    "table_static_share": ({"table_static_share": 0.0},
                           "the no-object-stayed check of the weak flags "
                           "(table_top.table_pose_weak)"),
    "slide_support": ({"slide_support_share": 0.0},
                      "the unsupported-slide weak flag (register._unsupported_slide, steps 7 "
                      "and 7e); a weak slide gates steps 7b and 7c"),
    "slide_contested": ({"slide_contested_share": 1.0},
                        "the contested-slide weak flag (register._unsupported_slide, steps 7 "
                        "and 7e)"),
}

SETS = ("fixtures", "rooms", "tabletop", "stations")
CM, DEG = 10.0, 0.5  # converged: within 1 cm (in mm) and 0.5 deg


def ablation_params(name: str) -> RegistrationParams:
    """The default RegistrationParams with ablation ``name``'s overrides (validated)."""
    return dataclasses.replace(RegistrationParams(), **ABLATIONS[name][0])


def register_with(params: RegistrationParams, ref, cur, intrinsics):
    """bench_registration.ours with explicit params (it passes none): (T, weak, ms)."""
    t0 = time.perf_counter()
    got = register_depth(ref, cur, intrinsics, params)
    return got.T_ref_from_cur, got.weak, (time.perf_counter() - t0) * 1e3


def set_pairs(name: str, args):
    """The pairs of set ``name``, as bench_registration yields them (lazily)."""
    if name == "fixtures":
        return br.fixture_pairs()
    if name == "rooms":
        return br.sweep_pairs(args.rooms, args.room_levels, args.room_seed_base, args.room_tag)
    if name == "tabletop":
        return br.tabletop_pairs(args.tabletop, args.tabletop_seed_base, args.tabletop_tag)
    return itertools.chain.from_iterable(br.station_pairs(args.stations, base, args.station_tag)
                                         for base in args.station_seed_bases)


def check(T, truth) -> tuple[float, float]:
    """(mm, deg): the estimate's error against the truth (both T_ref_from_cur)."""
    err = invert(truth) @ T
    return float(np.linalg.norm(err[:3, 3]) * 1e3), rotation_angle_deg(err[:3, :3])


def converged(got: dict) -> bool:
    """Whether one check's estimate is within 1 cm and 0.5 deg of the truth."""
    return got["mm"] <= CM and got["deg"] <= DEG


def summarise(set_name: str, rows: list[dict], names: list[str]) -> list[dict]:
    """Per ablation: the set's figures and their change from the baseline ``none``."""
    out = []
    base = {r["pair"]: r["none"] for r in rows} if "none" in names else None
    for a in names:
        got = [r[a] for r in rows]
        ok = [converged(g) for g in got]
        wrong = [g for g, k in zip(got, ok, strict=True) if not k]
        s = {"ablation": a, "set": set_name, "pairs": len(got), "converged": sum(ok),
             "share": round(sum(ok) / len(got), 4) if got else None,
             "wrong": len(wrong), "wrong_said_weak": sum(1 for g in wrong if g["weak"]),
             "right_said_weak": sum(1 for g, k in zip(got, ok, strict=True) if k and g["weak"]),
             "median_ms": round(statistics.median(g["ms"] for g in got), 2) if got else None,
             "mean_ms": round(statistics.fmean(g["ms"] for g in got), 2) if got else None,
             "overrides": ABLATIONS[a][0]}
        if base and got:
            b_ok = sum(1 for g in base.values() if converged(g))
            s["delta_pct"] = round(100.0 * (s["converged"] - b_ok) / len(got), 2)
            s["time_ratio"] = round(statistics.median(
                r[a]["ms"] / r["none"]["ms"] for r in rows), 3)
            flips = [(r["pair"], converged(r[a])) for r in rows
                     if converged(r[a]) != converged(r["none"])]
            s["gained"] = sum(1 for _, now in flips if now)
            s["lost"] = len(flips) - s["gained"]
            s["changed_pairs"] = [p for p, _ in flips]
        out.append(s)
        print(json.dumps(s), flush=True)
    return out


def run_set(set_name: str, names: list[str], params: dict, args, deadline: float) -> list[dict]:
    """Every ablation on every pair of the set, one run each, the order rotated per pair."""
    rows = []
    for i, (pair, ref, cur, truth, intr) in enumerate(set_pairs(set_name, args)):
        if time.monotonic() > deadline:
            print(f"{set_name}: stopped at --max-minutes after {len(rows)} pairs",
                  file=sys.stderr, flush=True)
            break
        row = {"pair": pair}
        k = i % len(names)
        for a in names[k:] + names[:k]:
            T, weak, ms = register_with(params[a], ref, cur, intr)
            mm, deg = check(T, truth)
            row[a] = {"mm": round(mm, 3), "deg": round(deg, 4), "weak": list(weak),
                      "ms": round(ms, 2)}
        rows.append(row)
        if args.verbose:
            print(f"{pair:44s} " + " ".join(
                f"{a}:{'ok' if converged(row[a]) else 'WRONG'}"
                for a in names), file=sys.stderr, flush=True)
    return rows


def table(summary: list[dict]) -> str:
    """The summary as a Markdown table."""
    lines = ["| ablation | set | converged / pairs | vs none (% of checks) | lost / gained |"
             " wrong said weak | median ms | time ratio |", "|---|---|---|---|---|---|---|---|"]
    for s in summary:
        delta = f"{s['delta_pct']:+.2f}" if "delta_pct" in s else "-"
        lines.append(f"| {s['ablation']} | {s['set']} | {s['converged']} / {s['pairs']} | "
                     f"{delta} | {s.get('lost', '-')} / {s.get('gained', '-')} | "
                     f"{s['wrong_said_weak']} / {s['wrong']} | {s['median_ms']} | "
                     f"{s.get('time_ratio', '-')} |")
    return "\n".join(lines)


def parse(argv=None):
    """The command line (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="comma-separated ablations (the baseline none is added)")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated of {SETS}")
    ap.add_argument("--rooms", type=int, default=3, help="sweep seeds per scene and level")
    ap.add_argument("--room-levels", default="2,5,10,15", help="sweep offset levels, cm")
    ap.add_argument("--room-seed-base", type=int, default=7000)
    ap.add_argument("--room-tag", default="", help="mixed into each room pair's seed")
    ap.add_argument("--tabletop", type=int, default=10, help="seeds per table-top pair and level")
    ap.add_argument("--tabletop-seed-base", type=int, default=5000)
    ap.add_argument("--tabletop-tag", default="", help="mixed into each table-top pair's seed")
    ap.add_argument("--stations", type=int, default=10, help="station layouts per seed base")
    ap.add_argument("--station-tag", default="", help="mixed into each station's offset")
    ap.add_argument("--station-seed-bases",
                    default=",".join(str(b) for b in range(8000, 18000, 1000)))
    ap.add_argument("--quick", action="store_true", help="small sizes: a smoke test")
    ap.add_argument("--max-minutes", type=float, default=1e9,
                    help="stop building pairs after this long; report the pairs done")
    ap.add_argument("--json", type=Path, help="write every summary and pair here")
    ap.add_argument("--list", action="store_true", help="print the ablations and exit")
    ap.add_argument("-v", "--verbose", action="store_true", help="a line per pair (stderr)")
    args = ap.parse_args(argv)
    if args.quick:
        args.rooms, args.room_levels, args.tabletop, args.stations = 1, "15", 1, 1
        args.station_seed_bases = "8000"
    args.room_levels = tuple(int(v) for v in args.room_levels.split(","))
    args.station_seed_bases = [int(v) for v in args.station_seed_bases.split(",")]
    args.sets = args.sets.split(",")
    for s in args.sets:
        if s not in SETS:
            ap.error(f"unknown set {s!r}; known: {', '.join(SETS)}")
    names = list(ABLATIONS) if not args.only else \
        ["none"] + [a for a in args.only.split(",") if a != "none"]
    for a in names:
        if a not in ABLATIONS:
            ap.error(f"unknown ablation {a!r}; known: {', '.join(ABLATIONS)}")
    return args, names


def main(argv=None):
    args, names = parse(argv)
    if args.list:
        for a, (over, what) in ABLATIONS.items():
            print(f"{a:20s} {json.dumps(over):52s} {what}")
        return
    params = {a: ablation_params(a) for a in names}
    t0 = time.monotonic()
    deadline = t0 + 60.0 * args.max_minutes
    warm = next(iter(br.fixture_pairs()))  # compile / load the numba kernels once
    for a in names:
        register_with(params[a], warm[1], warm[2], warm[4])
    summary, pairs = [], {}
    for set_name in args.sets:
        rows = run_set(set_name, names, params, args, deadline)
        pairs[set_name] = rows
        summary += summarise(set_name, rows, names)
    wall = time.monotonic() - t0
    print(table(summary))
    print(f"wall {wall:.0f} s; load {[round(v, 2) for v in os.getloadavg()]}")
    if args.json:
        args.json.write_text(json.dumps({"argv": sys.argv[1:], "wall_s": round(wall, 1),
                                         "summary": summary, "pairs": pairs}, indent=1))


if __name__ == "__main__":
    main()
