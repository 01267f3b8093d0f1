"""Timing helpers for ``robot-change bench``: medians after warm-up, and what machine ran them.

Benchmarks are never unit tests: nothing here asserts a time.  The figures go to
docs/benchmarks.md together with :func:`machine_info`.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from typing import Any, Callable

import numpy as np

from hw.depth import Intrinsics
from robot_change import em
from robot_change.cloud import CloudParams, clean_cloud
from robot_change.mixture import fit_mixture

#: Keys of ``robot-change bench --json`` that come from the preprocessing chain (milliseconds).
PREPROCESS_STAGES = ("points_ms", "voxel_ms", "outlier_ms", "plane_ms", "preprocess_ms")


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
) -> dict[str, float | int]:
    """Per-stage medians of :func:`robot_change.cloud.clean_cloud` on one (H, W) uint16 frame.

    Returns ``points_ms``, ``voxel_ms``, ``outlier_ms``, ``plane_ms``, ``preprocess_ms`` (medians
    over ``runs`` after ``warmup`` runs, milliseconds) and ``n_points_in`` (valid pixels),
    ``n_points_out`` (points of the clean cloud).
    """
    for _ in range(warmup):
        cloud = clean_cloud(depth, intrinsics, params)
    per_stage: dict[str, list[float]] = {key: [] for key in PREPROCESS_STAGES}
    for _ in range(runs):
        cloud = clean_cloud(depth, intrinsics, params)
        for key in PREPROCESS_STAGES:
            per_stage[key].append(cloud.timings_ms[key])
    result: dict[str, float | int] = {
        key: round(statistics.median(values), 3) for key, values in per_stage.items()
    }
    result["n_points_in"] = int(np.count_nonzero(depth))
    result["n_points_out"] = int(len(cloud.points))
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
        The single-iteration timing uses at most this many points (evenly spaced in the input order).

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
