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
from robot_change.cloud import CloudParams, clean_cloud

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
