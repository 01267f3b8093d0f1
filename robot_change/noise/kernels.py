"""The noise of a profile inside numba kernels: sigma(z) read from the table of
:meth:`robot_change.noise.profile.NoiseProfile.kernel_table`, and the margin of a comparison of
two readings in units of it.  Inlined into the kernels that call them; NumPy twins in
tests/test_noise.py."""

from __future__ import annotations

import math

import numba
import numpy as np

from robot_change.noise.profile import TABLE_STEP_M

__all__ = ["floored_margin_at", "margin_at", "sigma_at", "table_sigma"]


@numba.njit(inline="always")
def sigma_at(table, z):
    """sigma (m) of one reading at depth ``z`` (m): ``table`` (n,) float64, sigma every
    TABLE_STEP_M metres from 0, linearly interpolated; beyond its end, the last entry grown
    with z^2."""
    x = z / TABLE_STEP_M
    n = table.shape[0]
    if x <= 0.0:
        return table[0]
    if x >= n - 1:
        last = (n - 1) * TABLE_STEP_M
        return table[n - 1] * (z / last) * (z / last)
    i = int(x)
    t = x - i
    return table[i] * (1.0 - t) + table[i + 1] * t


@numba.njit(inline="always")
def margin_at(table, z, k, pose_sigma):
    """How much farther than a point at depth ``z`` (m) a reading of the other epoch must lie
    to see through it: ``k`` sigmas of the difference of two readings, each of ``sigma_at``,
    and of what the registration leaves (``pose_sigma``, m): k sqrt(2 sigma(z)^2 + pose^2)."""
    s = sigma_at(table, z)
    return k * math.sqrt(2.0 * s * s + pose_sigma * pose_sigma)


@numba.njit(inline="always")
def floored_margin_at(table, z, k, floor_m, floor_per_m2):
    """The registration's margin at depth ``z`` (m): ``floor_m + floor_per_m2 z^2``, or ``k``
    sigmas of the difference of two readings (k sqrt(2) sigma(z)) where the camera's noise
    makes that wider (a far wall, a noisy camera)."""
    return max(floor_m + floor_per_m2 * z * z, k * math.sqrt(2.0) * sigma_at(table, z))


def table_sigma(table: np.ndarray, z) -> np.ndarray:
    """:func:`sigma_at` over an array of depths ``z`` (m), in NumPy (the same arithmetic)."""
    z = np.asarray(z, dtype=np.float64)
    n = table.shape[0]
    x = z / TABLE_STEP_M
    i = np.clip(x.astype(np.int64), 0, n - 2)
    t = x - i
    inside = table[i] * (1.0 - t) + table[i + 1] * t
    last = (n - 1) * TABLE_STEP_M
    return np.where(x <= 0.0, table[0], np.where(x >= n - 1, table[-1] * (z / last) * (z / last),
                                                 inside))
