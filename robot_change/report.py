"""Pictures a person wants to see, drawn with matplotlib (the ``viz`` extra).

Only the command line and the report writers import this module; the numeric modules never do.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from hw.depth import Intrinsics
from robot_change.cloud import PIXEL_KEPT, PIXEL_OUTLIER, PIXEL_PLANE, CleanCloud
from robot_change.errors import InputError


def _pyplot():
    """matplotlib's pyplot on the file-only Agg backend, or an error naming the extra."""
    try:
        import matplotlib

        matplotlib.use("Agg", force=True)
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise InputError(
            "pictures need matplotlib: install the 'viz' extra (./setup.sh viz, or "
            "pip install 'robot-change[viz]')"
        ) from exc
    return plt


def _save(figure, path: Path) -> Path:
    """Write a figure as PNG atomically (temp file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    figure.savefig(temporary, format="png", dpi=100)
    os.replace(temporary, path)
    return path


def mixture_ellipses(
    means: np.ndarray, covariances: np.ndarray, intrinsics: Intrinsics, n_sigma: float = 2.0,
    n_vertices: int = 48,
) -> list[np.ndarray]:
    """The image outlines of 3-D Gaussians: for each component, an (n_vertices, 2) array of
    (u, v) pixel coordinates of its ``n_sigma`` ellipse.

    ``means`` (K, 3) m and ``covariances`` (K, 3, 3) m^2 in the camera optical frame.  The
    projection is linearised at the mean (Jacobian of the pinhole model), so the outline is the
    ellipse of the projected covariance.  Components behind the camera give an empty (0, 2)
    array.
    """
    outlines = []
    angles = np.linspace(0.0, 2.0 * np.pi, n_vertices)
    circle = np.stack([np.cos(angles), np.sin(angles)])  # (2, V)
    for mean, covariance in zip(np.asarray(means, float), np.asarray(covariances, float)):
        x, y, z = mean
        if not z > 1e-6:
            outlines.append(np.zeros((0, 2)))
            continue
        jacobian = np.array([
            [intrinsics.fx / z, 0.0, -intrinsics.fx * x / z**2],
            [0.0, intrinsics.fy / z, -intrinsics.fy * y / z**2],
        ])
        projected = jacobian @ covariance @ jacobian.T
        values, vectors = np.linalg.eigh(0.5 * (projected + projected.T))
        axes = vectors * (n_sigma * np.sqrt(np.clip(values, 0.0, None)))
        centre = np.array([intrinsics.fx * x / z + intrinsics.cx,
                           intrinsics.fy * y / z + intrinsics.cy])
        outlines.append((centre[:, None] + axes @ circle).T)
    return outlines


def draw_cloud(
    depth: np.ndarray, intrinsics: Intrinsics, cloud: CleanCloud, path: str | Path, title: str = ""
) -> Path:
    """Three panels: the depth image; what the cleaning chain did with each pixel (kept points
    coloured by depth, the removed plane grey, outliers red); the clean cloud seen from above.

    ``depth``: (H, W) uint16 mm; ``cloud``: the result of ``clean_cloud`` on it.  Returns the
    PNG's path.
    """
    plt = _pyplot()
    metres = np.where(depth > 0, depth / 1000.0, np.nan)
    valid = metres[np.isfinite(metres)]
    low, high = (np.percentile(valid, [1, 99]) if valid.size else (0.0, 1.0))

    figure, axes = plt.subplots(1, 3, figsize=(18, 5.2), constrained_layout=True)
    shown = axes[0].imshow(metres, cmap="turbo", vmin=low, vmax=high, interpolation="nearest")
    axes[0].set_title(f"depth {intrinsics.width}x{intrinsics.height} "
                      f"({100.0 * valid.size / depth.size:.0f} % valid)")
    figure.colorbar(shown, ax=axes[0], label="depth (m)", shrink=0.8)

    stages = cloud.pixel_stage
    cmap = plt.get_cmap("turbo")
    scaled = np.clip((np.nan_to_num(metres) - low) / max(high - low, 1e-6), 0.0, 1.0)
    picture = np.zeros(depth.shape + (3,), dtype=np.float32)
    kept = stages == PIXEL_KEPT
    picture[kept] = cmap(scaled[kept])[:, :3]
    picture[stages == PIXEL_PLANE] = (0.55, 0.55, 0.55)
    picture[stages == PIXEL_OUTLIER] = (1.0, 0.1, 0.1)
    axes[1].imshow(picture, interpolation="nearest")
    counts = cloud.stage_counts
    axes[1].set_title(f"kept {counts['kept']} points (colour), plane {counts['plane_inliers']} "
                      f"(grey), outliers {counts['voxels'] - counts['after_outliers']} (red)")
    for axis in axes[:2]:
        axis.set_xticks([])
        axis.set_yticks([])

    points = cloud.points
    if len(points):
        order = np.argsort(-points[:, 1])  # draw low points first, so tops stay visible
        axes[2].scatter(points[order, 0], points[order, 2], c=-points[order, 1], s=1.5,
                        cmap="viridis", linewidths=0)
    axes[2].set_aspect("equal")
    axes[2].set_xlabel("x (m, right)")
    axes[2].set_ylabel("z (m, forward)")
    axes[2].set_title(f"clean cloud from above (leaf {cloud.params.leaf_m * 100:.1f} cm; "
                      "colour = height)")
    axes[2].grid(alpha=0.3)
    if title:
        figure.suptitle(title)
    try:
        return _save(figure, Path(path))
    finally:
        plt.close(figure)
