"""From per-pixel truth masks to per-point truth, the rule every evaluation here uses."""

from __future__ import annotations

import numpy as np


def point_truth(pixel_voxel: np.ndarray, truth: np.ndarray, n_points: int) -> np.ndarray:
    """(n_points,) bool: at least half of the point's depth pixels lie in ``truth``.

    ``pixel_voxel`` (H, W) int32 maps each pixel to its point's row in the clean cloud (-1 for
    none); ``truth`` (H, W) bool is the scene's truth mask over the same image.
    """
    pv = pixel_voxel.ravel()
    ok = pv >= 0
    total = np.bincount(pv[ok], minlength=n_points)
    inside = np.bincount(pv[ok], weights=truth.ravel()[ok].astype(np.float64),
                         minlength=n_points)
    return (total > 0) & (2 * inside >= total)
