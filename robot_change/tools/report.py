"""Pictures a person wants to see, drawn with matplotlib (the ``viz`` extra).

Only the command line and the report writers import this module; the numeric modules never do.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from hw.depth import Intrinsics
from robot_change.cloud.chain import PIXEL_KEPT, PIXEL_OUTLIER, PIXEL_PLANE, CleanCloud
from robot_change.cloud.geometry import project_points
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


#: Colours of the change picture: appeared (current image), disappeared (reference image).
APPEARED_COLOUR = (0.90, 0.15, 0.15)
DISAPPEARED_COLOUR = (0.15, 0.40, 0.95)


def _depth_range(depth: np.ndarray) -> tuple[float, float]:
    """The (1st, 99th) percentile of the readings of (H, W) uint16 mm, in metres: the range
    the grey scale (and its colour bar) spans."""
    valid = depth > 0
    if not valid.any():
        return 0.0, 1.0
    low, high = np.percentile(depth[valid].astype(np.float64) / 1000.0, [1, 99])
    return float(low), float(max(high, low + 1e-3))


def _grey(depth: np.ndarray) -> np.ndarray:
    """(H, W) uint16 mm -> (H, W, 3) float grey image, near = bright, no reading = black."""
    metres = depth.astype(np.float64) / 1000.0
    low, high = _depth_range(depth)
    shade = 1.0 - 0.75 * np.clip((metres - low) / (high - low), 0.0, 1.0)
    picture = np.repeat(np.where(depth > 0, shade, 0.0)[..., None], 3, axis=2)
    return picture


def _depth_bar(figure, axis, depth: np.ndarray) -> None:
    """A colour bar of the grey scale in metres (near = bright; black: no reading)."""
    import matplotlib.colors as colors
    from matplotlib.cm import ScalarMappable

    low, high = _depth_range(depth)
    scale = colors.LinearSegmentedColormap.from_list("depth", [(1, 1, 1), (0.25, 0.25, 0.25)])
    bar = figure.colorbar(ScalarMappable(colors.Normalize(low, high), scale), ax=axis,
                          fraction=0.035, pad=0.01)
    bar.set_label("depth (m); black: no reading", fontsize=8)


def _region_box(axis, region, intrinsics: Intrinsics, colour, label: str) -> None:
    """Draw the image rectangle around a region's 3-D bounding box, with a label."""
    corners = np.array([[x, y, z] for x in (region.bbox_min[0], region.bbox_max[0])
                        for y in (region.bbox_min[1], region.bbox_max[1])
                        for z in (region.bbox_min[2], region.bbox_max[2])])
    uv = project_points(corners.astype(np.float64), intrinsics)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if not len(uv):
        return
    (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
    axis.plot([u0, u1, u1, u0, u0], [v0, v0, v1, v1, v0], color=colour, linewidth=1.5)
    width = intrinsics.width
    # inside the picture: above the box, or below it at the top edge; right-aligned at the right
    above = v0 > 0.08 * intrinsics.height
    right = u0 > 0.6 * width
    axis.text(min(max(u1, 0.0), width - 2.0) if right else max(u0, 2.0),
              v0 - 4 if above else min(v1 + 4, intrinsics.height - 2.0), label, color="white",
              fontsize=8, va="bottom" if above else "top", ha="right" if right else "left",
              bbox=dict(facecolor=colour, edgecolor="none", alpha=0.85, pad=1.5))


def _ellipses(axis, mixture, intrinsics: Intrinsics, highlight: set[int], colour) -> None:
    """Every component of ``mixture`` as a thin outline; those in ``highlight`` bold."""
    if mixture is None:
        return
    outlines = mixture_ellipses(mixture.means, mixture.covariances, intrinsics)
    for index, outline in enumerate(outlines):
        if len(outline):
            bold = index in highlight
            axis.plot(outline[:, 0], outline[:, 1], color=colour if bold else (1.0, 0.85, 0.2),
                      linewidth=2.0 if bold else 0.6, alpha=1.0 if bold else 0.55)


def draw_change(
    reference_depth: np.ndarray, current_depth: np.ndarray, intrinsics: Intrinsics, changes,
    path: str | Path, title: str = "",
) -> Path:
    """The picture of what changed, like the paper's Fig. 8: the reference depth image with
    what disappeared (blue) and the current one with what appeared (red), each with its
    mixture's Gaussians as 2-sigma outlines (the change components bold) and a labelled box
    per region.

    ``reference_depth`` / ``current_depth``: (H, W) uint16 mm; ``changes``: a
    :class:`robot_change.change.results.ChangeSet`.  Returns the PNG's path.
    """
    plt = _pyplot()
    from matplotlib.lines import Line2D  # (matplotlib is the optional viz extra)
    from matplotlib.patches import Patch

    figure, axes = plt.subplots(1, 2, figsize=(15, 5.8), constrained_layout=True)
    panels = (
        (axes[0], reference_depth, changes.disappeared_mask, changes.disappeared,
         changes.disappeared_mixture, DISAPPEARED_COLOUR, "reference: what disappeared"),
        (axes[1], current_depth, changes.appeared_mask, changes.appeared,
         changes.appeared_mixture, APPEARED_COLOUR, "current: what appeared"),
    )
    for axis, depth, mask, regions, mixture, colour, caption in panels:
        picture = _grey(depth)
        if mask is not None and mask.shape == depth.shape:
            picture[mask] = 0.35 * picture[mask] + 0.65 * np.array(colour)
        axis.imshow(picture, interpolation="nearest")
        highlight = {c for region in regions for c in region.components}
        _ellipses(axis, mixture, intrinsics, highlight, colour)
        for number, region in enumerate(regions, 1):
            size = max(region.extent) * 100.0
            _region_box(axis, region, intrinsics, colour,
                        f"{region.kind} {number}: {region.n_points} points, {size:.0f} cm, "
                        f"{region.centroid[2]:.2f} m away")
        k = mixture.n_components if mixture is not None else 0
        axis.set_title(f"{caption}: {len(regions)} region(s)\nits mixture: {k} Gaussians, "
                       f"{len(highlight)} of them change components (bold)", fontsize=10)
        _depth_bar(figure, axis, depth)
        legend = [Line2D([], [], color=(1.0, 0.85, 0.2), linewidth=0.8,
                         label="a Gaussian of the mixture (2-sigma outline)"),
                  Line2D([], [], color=colour, linewidth=2.0,
                         label="a change component / the box of a region"),
                  Patch(color=colour, alpha=0.65, label="its changed pixels")]
        axis.legend(handles=legend, loc="lower left", fontsize=7, framealpha=0.8)
        axis.set_xlim(0, depth.shape[1] - 1)
        axis.set_ylim(depth.shape[0] - 1, 0)
        axis.set_xticks([])
        axis.set_yticks([])
    verdict = "CHANGED" if changes.changed else "no change"
    figure.suptitle(f"{title}  —  {verdict}" if title else verdict)
    try:
        return _save(figure, Path(path))
    finally:
        plt.close(figure)
