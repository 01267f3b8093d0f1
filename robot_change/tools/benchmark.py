"""Timing helpers for ``robot-change bench``: medians after warm-up, and what machine ran them.

Benchmarks are never unit tests: nothing here asserts a time.  The figures go to
docs/benchmarks.md together with :func:`machine_info`.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hw.depth import Intrinsics
from robot_change.change.detect import detect_changes
from robot_change.change.registration import register_depth
from robot_change.change.transport import emd, greedy_emd, ground_distance
from robot_change.cloud.chain import CloudParams, clean_cloud
from robot_change.cloud.geometry import depth_to_points
from robot_change.mixture import em
from robot_change.mixture.model import fit_mixture

#: Per-stage timings of :func:`robot_change.cloud.chain.clean_cloud` (milliseconds).
#: Back-projection runs inside the voxel pass there, so ``voxel_ms`` includes it; ``points_ms`` in
#: the bench output is back-projection on its own
#: (:func:`robot_change.cloud.geometry.depth_to_points`), timed separately for comparison, and is
#: not part of ``preprocess_ms``.
PREPROCESS_STAGES = ("voxel_ms", "outlier_ms", "plane_ms", "preprocess_ms")


def median_ms(function: Callable[[], Any], runs: int = 20, warmup: int = 3) -> float:
    """Median wall time of ``function()`` in milliseconds over ``runs`` calls after ``warmup``."""
    for _ in range(warmup):
        function()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        function()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def bench_preprocess(
    depth: np.ndarray, intrinsics: Intrinsics, params: CloudParams, runs: int = 30, warmup: int = 3
) -> dict[str, Any]:
    """Per-stage medians of :func:`robot_change.cloud.chain.clean_cloud` on one (H, W) uint16 frame.

    Returns the medians over ``runs`` after ``warmup`` runs, in milliseconds: ``voxel_ms``
    (depth to voxel grid, back-projection included), ``outlier_ms``, ``plane_ms``,
    ``preprocess_ms`` (the whole call, pixel maps included; its minimum too, as
    ``min_preprocess_ms``), and ``points_ms``: back-projection alone
    (:func:`robot_change.cloud.geometry.depth_to_points`, which the chain does not call), timed
    separately.  Also ``n_points_in`` (valid pixels), ``n_points_out`` (points of the clean
    cloud), ``stage_counts`` and ``voxel_includes_points`` (True).
    """
    for _ in range(warmup):
        cloud = clean_cloud(depth, intrinsics, params)
    per_stage: dict[str, list[float]] = {key: [] for key in PREPROCESS_STAGES}
    for _ in range(runs):
        cloud = clean_cloud(depth, intrinsics, params)
        for key in PREPROCESS_STAGES:
            per_stage[key].append(cloud.timings_ms[key])
    result: dict[str, Any] = {"points_ms": round(median_ms(
        lambda: depth_to_points(depth, intrinsics, min_depth_m=params.near_m(),
                                max_depth_m=params.max_depth_m), runs, warmup), 3)}
    result.update({key: round(statistics.median(values), 3) for key, values in per_stage.items()})
    result["min_preprocess_ms"] = round(min(per_stage["preprocess_ms"]), 3)
    result["voxel_includes_points"] = True
    result["n_points_in"] = int(np.count_nonzero(depth))
    result["n_points_out"] = int(len(cloud.points))
    result["stage_counts"] = dict(cloud.stage_counts)
    result["plane_iterations"] = int(cloud.plane.iterations)
    return result


def benchmark_em(points, n_components: int = 8, runs: int = 7, warmup: int = 2,
                 criterion: str = "mdl", iter_points: int = 18000,
                 **fit_options) -> dict[str, float | int]:
    """Times for ``robot-change bench --json``: one EM iteration and the whole fit.

    Parameters
    ----------
    points : array, shape (N, 3)
        A room-sized cloud (15k-20k points).
    n_components : int
        K of the single-iteration timing (components seeded from an 8-way split of the data
        along x, deterministic).
    iter_points : int
        The single-iteration timing uses at most this many points (evenly spaced in the input
        order).

    Returns
    -------
    dict
        ``em_iter_ms`` (median of one fused EM iteration at K = n_components), ``fit_ms``
        (median of the whole split-EM fit), ``fit_k`` (K chosen), ``n_points``.
    """
    x_all = np.ascontiguousarray(points, dtype=np.float64)
    if len(x_all) > iter_points:
        x = x_all[np.linspace(0, len(x_all) - 1, iter_points).astype(np.int64)]
    else:
        x = x_all
    order = np.argsort(x[:, 0], kind="stable")
    chunks = np.array_split(order, n_components)
    w = np.array([len(c) for c in chunks], dtype=np.float64) / len(x)
    mu = np.stack([x[c].mean(axis=0) for c in chunks])
    cov = np.stack([np.cov(x[c], rowvar=False) + 1e-4 * np.eye(3) for c in chunks])
    prec, log_det, _ = em.precision_cholesky(cov)

    def one_iter():
        em.em_step(x, w, mu, prec, log_det, 1e-4)

    def one_fit():
        return fit_mixture(x_all, criterion, **fit_options)

    iter_ms = median_ms(one_iter, runs * 5, warmup)
    fit_ms = median_ms(one_fit, runs, warmup)
    return {"em_iter_ms": iter_ms, "fit_ms": fit_ms,
            "fit_k": one_fit().n_components, "n_points": int(len(x_all)),
            "iter_points": int(len(x))}


def _covariances(rng, k):
    g = rng.standard_normal((k, 3, 3)) * 0.05
    return g @ g.transpose(0, 2, 1) + 1e-4 * np.eye(3)


def emd_scene(seed: int, k: int = 30, n_changed: int = 5):
    """Reference and current mixture parameters of one synthetic scene for the EMD benchmark:
    30 reference components in a 3 m box; the current keeps 25 (jittered 2 cm, reweighted) and
    adds 5 new ones.

    Returns
    -------
    dict
        ``w_ref`` (k,), ``mu_ref`` (k, 3), ``cov_ref`` (k, 3, 3), ``w_cur``, ``mu_cur``,
        ``cov_cur`` likewise, ``new`` (k,) bool (components of the current that appeared),
        ``gone`` (k,) bool (components of the reference that disappeared).
    """
    rng = np.random.default_rng(seed)
    mu_ref = rng.random((k, 3)) * 3.0
    cov_ref = _covariances(rng, k)
    w_ref = rng.random(k) + 0.2
    gone = np.zeros(k, bool)
    gone[rng.choice(k, n_changed, replace=False)] = True
    kept = np.flatnonzero(~gone)
    mu_cur = np.vstack([mu_ref[kept] + 0.02 * rng.standard_normal((len(kept), 3)),
                        rng.random((n_changed, 3)) * 3.0])
    cov_cur = np.concatenate([cov_ref[kept], _covariances(rng, n_changed)])
    w_cur = np.concatenate([w_ref[kept] * (1.0 + 0.1 * rng.standard_normal(len(kept))),
                            0.3 * rng.random(n_changed) + 0.05])
    new = np.zeros(k, bool)
    new[len(kept):] = True
    perm = rng.permutation(k)
    return dict(w_ref=w_ref / w_ref.sum(), mu_ref=mu_ref, cov_ref=cov_ref,
                w_cur=np.abs(w_cur[perm]) / np.abs(w_cur).sum(), mu_cur=mu_cur[perm],
                cov_cur=cov_cur[perm], new=new[perm], gone=gone)


def _both_ways(s, cost, cand_cur, cand_ref):
    appeared = greedy_emd(s["w_ref"], s["w_cur"], cost, cand_cur)
    disappeared = greedy_emd(s["w_cur"], s["w_ref"], cost.T, cand_ref)
    return appeared, disappeared


def bench_emd(runs: int = 200, warmup: int = 20, n_scenes: int = 5) -> dict[str, float]:
    """Times for ``robot-change bench --json`` (medians, one thread).

    Returns
    -------
    dict
        ``emd_10x10_us``, ``emd_30x30_us``, ``greedy_both_ways_k30_ms`` (every component a
        candidate; median over scenes of the per-scene medians), ``greedy_both_ways_k30_worst_ms``
        (the slowest scene), ``greedy_both_ways_k30_5cand_ms`` (5 candidates a side),
        ``ground_w2_30x30_ms``, ``greedy_removals_k30`` (mean removals per direction, all
        candidates), ``greedy_solves_k30`` (mean transportation problems started per
        direction).
    """
    out: dict[str, float] = {}
    for k in (10, 30):
        s = emd_scene(0, k, n_changed=2 if k == 10 else 5)
        cost = ground_distance(s["mu_ref"], s["mu_cur"])
        out[f"emd_{k}x{k}_us"] = round(
            1e3 * median_ms(lambda s=s, cost=cost: emd(s["w_ref"], s["w_cur"], cost), runs,
                            warmup), 2)
    all_ms, five_ms, removals, solves = [], [], [], []
    for seed in range(n_scenes):
        s = emd_scene(seed)
        cost = np.ascontiguousarray(ground_distance(s["mu_ref"], s["mu_cur"]))
        every = np.ones(30, bool)
        all_ms.append(median_ms(
            lambda s=s, cost=cost, every=every: _both_ways(s, cost, every, every),
            runs // 4, warmup))
        # 5 novelty candidates a side: the changed components (what the novelty step proposes)
        five_ms.append(median_ms(lambda s=s, cost=cost: _both_ways(s, cost, s["new"], s["gone"]),
                                 runs // 4, warmup))
        for r in _both_ways(s, cost, every, every):
            removals.append(len(r.order))
            solves.append(r.n_solves)
    out["greedy_both_ways_k30_ms"] = round(statistics.median(all_ms), 4)
    out["greedy_both_ways_k30_worst_ms"] = round(max(all_ms), 4)
    out["greedy_both_ways_k30_5cand_ms"] = round(statistics.median(five_ms), 4)
    out["greedy_removals_k30"] = round(float(np.mean(removals)), 2)
    out["greedy_solves_k30"] = round(float(np.mean(solves)), 1)
    s = emd_scene(0)
    out["ground_w2_30x30_ms"] = round(median_ms(
        lambda: ground_distance(s["mu_ref"], s["mu_cur"], s["cov_ref"], s["cov_cur"],
                                kind="wasserstein2"), runs // 4, warmup), 4)
    return out


def bench_detect(reference, current_frame: np.ndarray, intrinsics: Intrinsics,
                 runs: int = 10, warmup: int = 2) -> dict[str, float | int]:
    """``detect_ms``: a saved reference (a :class:`robot_change.change.scene.SceneModel`) and one
    current (H, W) uint16 frame to a ChangeSet, median over ``runs`` after ``warmup``.

    Also returns ``detect_regions`` (regions found) and ``registration_ms`` (the registration
    of the frame to the reference alone, part of ``detect_ms``).
    """
    changes = detect_changes(reference, current_frame, intrinsics=intrinsics)
    detect_ms = median_ms(lambda: detect_changes(reference, current_frame, intrinsics=intrinsics),
                          runs, warmup)
    registration_ms = median_ms(lambda: register_depth(reference.depth, current_frame,
                                                       intrinsics), runs, warmup)
    return {"detect_ms": round(detect_ms, 2), "registration_ms": round(registration_ms, 2),
            "detect_regions": len(changes.regions)}


def bench_capture(frames, runs: int = 10, warmup: int = 2) -> dict[str, float | int]:
    """``capture_ms``: a station reference from ``frames`` (a sequence of hw.depth.DepthFrame,
    e.g. 3 VGA frames already read) to a saved ``.scene.npz``: fusion, cleaning, the full fit
    and the atomic, fsynced save, median over ``runs`` after ``warmup``.

    Also returns the medians of the parts as :func:`robot_change.change.scene.build_scene`
    times them (``capture_fusion_ms``, ``capture_cloud_ms``, ``capture_fit_ms``),
    ``capture_save_ms``, and the reference's ``capture_points`` and ``capture_k``.
    """
    import tempfile
    from pathlib import Path

    from robot_change.change.scene import build_scene

    parts: dict[str, list[float]] = {"fusion": [], "cloud": [], "fit": [], "save": [],
                                     "total": []}
    with tempfile.TemporaryDirectory(prefix="robot_change_capture_") as folder:
        path = Path(folder) / "station.scene.npz"
        scene = None
        for run in range(warmup + runs):
            start = time.perf_counter()
            scene = build_scene(frames)
            built = time.perf_counter()
            scene.save(path)
            done = time.perf_counter()
            if run < warmup:
                continue
            for part in ("fusion", "cloud", "fit"):
                parts[part].append(scene.seconds[part] * 1e3)
            parts["save"].append((done - built) * 1e3)
            parts["total"].append((done - start) * 1e3)
    out: dict[str, float | int] = {"capture_ms": round(statistics.median(parts["total"]), 2)}
    for part in ("fusion", "cloud", "fit", "save"):
        out[f"capture_{part}_ms"] = round(statistics.median(parts[part]), 2)
    out["capture_points"] = len(scene)
    out["capture_k"] = scene.mixture.n_components
    return out


def machine_info() -> dict[str, Any]:
    """CPU model, cores, Python and library versions, and the thread settings in force."""
    import numba

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as handle:
            for line in handle:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "numba_threads": numba.get_num_threads(),
        "kernels": "numba, single-threaded",
    }
