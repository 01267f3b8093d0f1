"""Registration accuracy and speed, ours against small_gicp's GICP and Open3D's point-to-plane
ICP, side by side on the same pairs in one run (docs/benchmarks.md, docs/algorithm.md).

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_registration.py [--runs 5] [--json OUT]
        [--sweep SEEDS [--no-fixtures] [--sweep-levels 2,5,10,15] [--sweep-seed-base N]
         [--sweep-tag T]] [--tabletop SEEDS [--tabletop-seed-base N] [--tabletop-tag T]
        [--tabletop-static]] [--station SEEDS [--station-seed-base N] [--station-tag T]]
        [--methods ours,small_gicp,open3d_icp] [--against REV] [--kept-reference]

Pairs: the revisit fixtures (``*_pose_2cm/5cm/10cm``: the reference fused from 3 frames, the
current one frame, the change in view) and, with ``--sweep``, freshly rendered pairs at 2, 5,
10 and 15 cm (1, 2, 4, 6 degrees) in random directions.  Every method starts from the identity
(the robot believes it is at its station) and gets the floor: ours the two depth images, the
peers the two depth images back-projected (0.4-5 m) and voxelised at 2 cm.  Open3D: Tukey loss
(k = 5 cm), correspondence distances 25 -> 10 -> 4 cm, normals from 20 neighbours within 10 cm
(ALGORITHM.md section 4's recipe).  small_gicp: GICP, 2 cm downsampling, 25 cm correspondences.
With ``--station``: table stations as a robot sees them (sim_fixtures.stations: a table with
objects on it, the wall behind, the floor; every kind of change, every object moved among them)
from a camera displaced by 5 / 10 / 15 cm; seeds from 0 were looked at while choosing the fine
search and the slide support (issue 12), ``--station-seed-base 1000 --station-tag held`` once
in between, ``2000 ... held2`` once after every choice.  With ``--tabletop``: the real
table-top pairs (../shared/data/osd-tabletop, the change in view) with the current
re-rendered from a camera displaced by 5 / 10 / 15 cm (2 / 4 / 6 deg): its back-projected
points moved and splatted into a z-buffer (disocclusions stay holes);
``--tabletop-static`` re-renders the reference instead (no change in view), and
``--tabletop-seed-base`` / ``--tabletop-tag`` draw other offsets (base 93000, tag "held": the
held-out table-top set of issue 12, looked at once after the choice).
One thread each; the methods alternate per pair and per run, so they share the machine's load.
``--against REV`` adds method ``base``: the registration as it is at git revision REV (loaded
from ``git show`` beside this one, in the same process), for an A/B of speed and accuracy; the
median over pairs of the per-pair time ratio ours / base is printed per group.  For ours (and
base) each group also counts the wrong estimates (beyond 1 cm / 0.5 deg) and the right ones
that name weak directions (``Registration.weak``): a wrong pose should say so.
``--kept-reference`` times a check as the daemon makes it: the station's reference keeps its
pyramid (``register_depth(..., keep=)``), so only the current's is built per call.
Needs the ``bench`` extra (``pip install -e '.[bench]'``).  A benchmark, never a test.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import platform
import statistics
import sys
import time
import zlib
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robot_change.change.registration import invert, register_depth, rotation_angle_deg  # noqa: E402
from robot_change.cloud.geometry import depth_to_points  # noqa: E402

LEAF = 0.02


def _cloud(depth, intrinsics):
    import open3d as o3d

    pts = depth_to_points(depth, intrinsics, min_depth_m=0.4, max_depth_m=5.0)[0]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    return pc.voxel_down_sample(LEAF)


def ours(ref, cur, intrinsics, keep=None):
    got = register_depth(ref, cur, intrinsics, keep=keep)
    return got.T_ref_from_cur, got.weak


def open3d_icp(ref, cur, intrinsics):
    import open3d as o3d

    reg = o3d.pipelines.registration
    target, source = _cloud(ref, intrinsics), _cloud(cur, intrinsics)
    target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.1, max_nn=20))
    T = np.eye(4)
    for dist in (0.25, 0.10, 0.04):
        est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=0.05))
        T = reg.registration_icp(source, target, dist, T, est,
                                 reg.ICPConvergenceCriteria(max_iteration=30)).transformation
    return np.asarray(T)


def small_gicp_align(ref, cur, intrinsics):
    import small_gicp

    target, source = (depth_to_points(d, intrinsics, min_depth_m=0.4, max_depth_m=5.0)[0]
                      .astype(np.float64) for d in (ref, cur))
    result = small_gicp.align(target, source, np.eye(4), registration_type="GICP",
                              downsampling_resolution=LEAF, max_correspondence_distance=0.25,
                              num_threads=1)
    return np.asarray(result.T_target_source)


METHODS = {"ours": ours, "small_gicp": small_gicp_align, "open3d_icp": open3d_icp}


def at_revision(rev: str):
    """``register_depth`` of robot_change/change/registration as it is at git revision ``rev``
    (the package, or the single registration.py of revisions before the split, in change/ or,
    earlier, in robot_change/), loaded under
    the name ``registration_base`` (its numba caches under a temporary folder, removed at
    exit)."""
    import atexit
    import importlib.util
    import shutil
    import subprocess
    import tempfile

    root = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True,
                              check=True).stdout

    folder = Path(tempfile.mkdtemp(prefix="registration_at_"))
    atexit.register(shutil.rmtree, folder, True)  # the copy and its numba caches
    names = git("ls-tree", "--name-only", rev, "robot_change/change/registration/").split()
    if names:  # a package: its modules import each other relatively
        package = folder / "registration_base"
        package.mkdir()
        for name in names:
            (package / Path(name).name).write_text(git("show", f"{rev}:{name}"))
        spec = importlib.util.spec_from_file_location(
            "registration_base", package / "__init__.py",
            submodule_search_locations=[str(package)])
    else:
        path = folder / "registration_base.py"
        single = [name for name in ("robot_change/change/registration.py",
                                    "robot_change/registration.py")  # before the change/ layer
                  if git("ls-tree", "--name-only", rev, name).strip()]
        if not single:
            raise SystemExit(f"--against {rev}: no registration module at that revision")
        path.write_text(git("show", f"{rev}:{single[0]}"))
        spec = importlib.util.spec_from_file_location("registration_base", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["registration_base"] = module  # its dataclasses look themselves up there
    spec.loader.exec_module(module)

    if "keep" in inspect.signature(module.register_depth).parameters:
        def base(ref, cur, intrinsics, keep=None):
            got = module.register_depth(ref, cur, intrinsics, keep=keep)
            return got.T_ref_from_cur, got.weak
    else:  # before the reference's pyramid could be kept
        def base(ref, cur, intrinsics):
            got = module.register_depth(ref, cur, intrinsics)
            return got.T_ref_from_cur, got.weak

    return base


def fixture_pairs():
    from sim_fixtures import load_scene, scene_names

    for name in scene_names():
        if "_pose_" not in name:
            continue
        sc = load_scene(name)
        ref = np.median(np.stack(sc.reference_frames()), axis=0).astype(np.uint16)
        yield name, ref, sc.current_frames()[0], sc.T_ref_from_cur, sc.intrinsics


LEVELS = {2: (0.02, 1.0), 5: (0.05, 2.0), 10: (0.10, 4.0), 15: (0.15, 6.0)}


def sweep_pairs(seeds: int, levels=(2, 5, 10, 15), seed_base: int = 7000, tag: str = ""):
    """Freshly rendered pairs, ``seeds`` per scene and level; the draw of each pair's offset is
    fixed by ``seed_base`` and ``tag`` (the defaults: the sweep of docs/benchmarks.md; base
    91000, tag "held", levels 10 and 15, 2 seeds: the held-out set rendered after the
    translation search's score was chosen)."""
    import dataclasses

    from sim_fixtures.scenes import SCENES, pose_offset, render_pair, true_transform

    names = ("office_box_added", "office_no_change", "lounge_chair_removed", "lab_crate_moved",
             "lab_two_changes", "lounge_chair_moved", "storage_small_object",
             "meeting_box_added", "meeting_two_changes")
    for tm, rd in (LEVELS[level] for level in levels):
        for name in names:
            spec = SCENES[name]
            for s in range(seeds):
                seed = seed_base + s + zlib.crc32(f"{tag}{name}{tm}".encode()) % 1000
                sp = dataclasses.replace(spec, current_pose=pose_offset(spec.reference_pose, tm,
                                                                        rd, seed))
                r, c = render_pair(sp)
                ref = np.median(np.stack([spec.noise.apply(r, np.random.default_rng(
                    [spec.seed, 0, k])) for k in range(3)]), axis=0).astype(np.uint16)
                cur = spec.noise.apply(c, np.random.default_rng([seed, 1, 0]))
                yield f"sweep_{name}_{int(tm * 100)}cm_{s}", ref, cur, true_transform(sp), \
                    spec.intrinsics


def tabletop_pairs(seeds: int, seed_base: int = 5000, tag: str = "", static: bool = False):
    """The real table-top pairs, the current displaced (module docstring); skipped with a
    message when ../shared/data is absent.  Each pair's offset is drawn from ``seed_base`` and
    ``tag`` (the defaults: the set of docs/benchmarks.md); ``static``: the displaced view is
    of the reference itself (no change in view)."""
    from sim_fixtures.scenes import Pose, pose_offset
    from sim_fixtures.tabletop import TabletopDataMissing, load_tabletop_pair, seen_from
    from sim_fixtures.tabletop import tabletop_pairs as names

    try:
        pairs = [load_tabletop_pair(name) for name in names()]
    except TabletopDataMissing as exc:
        print(f"--tabletop skipped: {exc}", file=sys.stderr)
        return
    for level in (5, 10, 15):
        tm, rd = LEVELS[level]
        for pr in pairs:
            for s in range(seeds):
                seed = seed_base + s + zlib.crc32(f"{tag}{pr.name}{tm}".encode()) % 1000
                old = Pose((0.0, 0.0, 0.0))
                truth = invert(old.matrix()) @ pose_offset(old, tm, rd, seed).matrix()
                cur = seen_from(pr.reference if static else pr.current, pr.intrinsics,
                                invert(truth))  # truth: T_ref_from_cur
                yield f"tabletop_{pr.name}_{level}cm_{s}", pr.reference, cur, truth, \
                    pr.intrinsics


def station_pairs(seeds: int, seed_base: int = 0, tag: str = ""):
    """Table stations as a robot sees them (sim_fixtures.stations: a table with objects, the
    wall behind, the floor), ``seeds`` layouts per level, each with every kind of change of
    :data:`sim_fixtures.stations.CHANGES`, the current camera displaced by 5 / 10 / 15 cm (2 /
    4 / 6 deg) in a direction drawn from ``tag``; the reference fused from 3 noisy frames."""
    from sim_fixtures.stations import station_checks, station_pair

    for name, seed, change, offset in station_checks(seeds, seed_base, tag):
        ref, cur, truth, intrinsics = station_pair(seed, change, offset)
        yield name, ref, cur, truth, intrinsics


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="timed runs per method and pair")
    ap.add_argument("--sweep", type=int, default=0, help="rendered pairs per scene and level")
    ap.add_argument("--no-fixtures", action="store_true", help="the rendered pairs only")
    ap.add_argument("--sweep-levels", default="2,5,10,15", help="offset levels in cm")
    ap.add_argument("--sweep-seed-base", type=int, default=7000)
    ap.add_argument("--sweep-tag", default="", help="mixed into each pair's seed")
    ap.add_argument("--tabletop", type=int, default=0,
                    help="displaced real table-top pairs per pair and level")
    ap.add_argument("--tabletop-seed-base", type=int, default=5000)
    ap.add_argument("--tabletop-tag", default="", help="mixed into each table-top pair's seed")
    ap.add_argument("--tabletop-static", action="store_true",
                    help="displace the reference's own view (no change in view)")
    ap.add_argument("--station", type=int, default=0,
                    help="table-station layouts per level (sim_fixtures.stations)")
    ap.add_argument("--station-seed-base", type=int, default=0)
    ap.add_argument("--station-tag", default="", help="mixed into each station's offset")
    ap.add_argument("--methods", default=",".join(METHODS),
                    help="comma-separated subset (ours alone: its speed without the peers' "
                         "threads and caches in between)")
    ap.add_argument("--against", metavar="REV",
                    help="add method base: the registration at this git revision (A/B)")
    ap.add_argument("--kept-reference", action="store_true",
                    help="methods that can keep the reference's pyramid between calls (ours, "
                         "base where its revision could) keep it between the runs of a pair, "
                         "built in an untimed first call: what a check pays in the daemon, "
                         "whose station reference keeps it")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    methods = {}
    for m in args.methods.split(","):
        if m not in METHODS:
            ap.error(f"unknown method {m!r}; known: {', '.join(METHODS)}")
        methods[m] = METHODS[m]
    if args.against:
        methods["base"] = at_revision(args.against)
    pairs = ([] if args.no_fixtures else list(fixture_pairs())) + \
        (list(sweep_pairs(args.sweep, tuple(int(v) for v in args.sweep_levels.split(",")),
                          args.sweep_seed_base, args.sweep_tag)) if args.sweep else []) + \
        (list(tabletop_pairs(args.tabletop, args.tabletop_seed_base, args.tabletop_tag,
                             args.tabletop_static)) if args.tabletop else []) + \
        (list(station_pairs(args.station, args.station_seed_base, args.station_tag))
         if args.station else [])
    for fn in methods.values():  # compile / load every library once
        fn(pairs[0][1], pairs[0][2], pairs[0][4])
    keeps = [m for m, fn in methods.items()
             if args.kept_reference and "keep" in inspect.signature(fn).parameters]
    rows = []
    for name, ref, cur, truth, intr in pairs:
        times = {m: [] for m in methods}
        est = {}
        kw = {m: {"keep": {}} if m in keeps else {} for m in methods}
        for m in keeps:
            methods[m](ref, cur, intr, **kw[m])  # builds the kept pyramid, untimed
        for run in range(args.runs):
            order = list(methods) if run % 2 == 0 else list(methods)[::-1]
            for m in order:
                t0 = time.perf_counter()
                est[m] = methods[m](ref, cur, intr, **kw[m])
                times[m].append((time.perf_counter() - t0) * 1e3)
        row = {"pair": name}
        for m in methods:
            T, weak = est[m] if isinstance(est[m], tuple) else (est[m], None)
            err = invert(truth) @ T
            row[m] = {"err_mm": float(np.linalg.norm(err[:3, 3]) * 1e3),
                      "err_deg": rotation_angle_deg(err[:3, :3]),
                      "ms": statistics.median(times[m]), "weak": weak}
        rows.append(row)
        print(f"{name:40s} " + "  ".join(f"{m} {row[m]['err_mm']:7.1f} mm {row[m]['err_deg']:5.2f}"
                                          f" deg {row[m]['ms']:6.1f} ms" for m in methods),
              flush=True)
    summary = {}
    for group in ("fixtures", "sweep", "tabletop", "station"):
        sel = [r for r in rows if r["pair"].split("_")[0] == group] if group != "fixtures" \
            else [r for r in rows if not r["pair"].startswith(("sweep_", "tabletop_",
                                                                "station_"))]
        if not sel:
            continue
        summary[group] = {}
        for m in methods:
            e = [r[m]["err_mm"] for r in sel]
            d = [r[m]["err_deg"] for r in sel]
            ok = sum(1 for r in sel if r[m]["err_mm"] <= 10 and r[m]["err_deg"] <= 0.5)
            summary[group][m] = {"pairs": len(sel), "within_1cm_0.5deg": ok,
                                 "median_err_mm": statistics.median(e), "max_err_mm": max(e),
                                 "median_err_deg": statistics.median(d), "max_err_deg": max(d),
                                 "median_ms": statistics.median(r[m]["ms"] for r in sel)}
            s = summary[group][m]
            print(f"{group:8s} {m:11s} within 1 cm / 0.5 deg {ok}/{len(sel)}; median "
                  f"{s['median_err_mm']:.1f} mm {s['median_err_deg']:.3f} deg, max "
                  f"{s['max_err_mm']:.1f} mm {s['max_err_deg']:.2f} deg; {s['median_ms']:.1f} ms")
            if sel[0][m]["weak"] is not None:  # a method that says which directions are weak
                wrong = [r for r in sel if not (r[m]["err_mm"] <= 10 and r[m]["err_deg"] <= 0.5)]
                s["wrong_said_weak"] = sum(1 for r in wrong if r[m]["weak"])
                s["right_said_weak"] = sum(1 for r in sel if r[m]["weak"]) - s["wrong_said_weak"]
                print(f"{group:8s} {m:11s} weak directions said: {s['wrong_said_weak']} of the "
                      f"{len(wrong)} wrong, {s['right_said_weak']} of the {ok} right")
        if "ours" in methods and "base" in methods:
            ratio = statistics.median(r["ours"]["ms"] / r["base"]["ms"] for r in sel)
            summary[group]["ratio_ours_to_base"] = ratio
            print(f"{group:8s} time ours / base (median of per-pair ratios): {ratio:.3f}")
    groups = ([("sweep", tm) for tm in (int(v) for v in args.sweep_levels.split(","))]
              if args.sweep else []) + ([("tabletop", tm) for tm in (5, 10, 15)]
                                        if args.tabletop else []) + \
        ([("station", tm) for tm in (5, 10, 15)] if args.station else [])
    for group, tm in groups:
        sel = [r for r in rows if r["pair"].startswith(f"{group}_") and f"_{tm}cm_" in r["pair"]]
        print(f"{group} {tm:2d} cm: " + "  ".join(
            f"{m} {sum(1 for r in sel if r[m]['err_mm'] <= 10 and r[m]['err_deg'] <= 0.5)}"
            f"/{len(sel)}" for m in methods))
    if args.station:
        from sim_fixtures.stations import CHANGES

        for change in CHANGES:
            sel = [r for r in rows if r["pair"].startswith(f"station_{change}_")]
            print(f"station {change:11s}: " + "  ".join(
                f"{m} {sum(1 for r in sel if r[m]['err_mm'] <= 10 and r[m]['err_deg'] <= 0.5)}"
                f"/{len(sel)}" for m in methods))
    load = os.getloadavg()
    machine = {"python": platform.python_version(), "cpu": platform.processor() or
               platform.machine(), "cores": os.cpu_count(), "load": [round(v, 2) for v in load]}
    print("machine:", json.dumps(machine))
    if args.json:
        args.json.write_text(json.dumps({"machine": machine, "summary": summary, "pairs": rows},
                                        indent=1))


if __name__ == "__main__":
    main()
