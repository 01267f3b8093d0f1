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
from robot_change.export import APPEARED_RGB, DISAPPEARED_RGB


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
    for mean, covariance in zip(np.asarray(means, float), np.asarray(covariances, float),
                                strict=False):
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
    from matplotlib import colors
    from matplotlib.cm import ScalarMappable

    low, high = _depth_range(depth)
    scale = colors.LinearSegmentedColormap.from_list("depth", [(1, 1, 1), (0.25, 0.25, 0.25)])
    bar = figure.colorbar(ScalarMappable(colors.Normalize(low, high), scale), ax=axis,
                          fraction=0.035, pad=0.01)
    bar.set_label("depth (m); black: no reading", fontsize=8)


#: Regions per panel that get a full text label by default: the largest ones, by points.
FULL_LABELS_PER_PANEL = 6
#: gid of the text artists of full labels and of number tags (how tests find them).
LABEL_GID = "region-label"
TAG_GID = "region-tag"
#: Display pixels between a box and its label, and kept free between two labels.
_LABEL_GAP_PX = 3.0
_LABEL_SPACING_PX = 1.0
#: What placing a label costs, in display pixels of distance from its box: per region box
#: whose outline it crosses, and for a spot away from its box (joined by a leader line).
_CROSSED_BOX_COST_PX = 40.0
_DETACHED_COST_PX = 15.0


def _region_rectangle(region, intrinsics: Intrinsics) -> tuple[float, float, float, float] | None:
    """(u0, v0, u1, v1): the pixel rectangle around the image of a region's 3-D bounding box;
    None when no corner of the box is in front of the camera."""
    corners = np.array([[x, y, z] for x in (region.bbox_min[0], region.bbox_max[0])
                        for y in (region.bbox_min[1], region.bbox_max[1])
                        for z in (region.bbox_min[2], region.bbox_max[2])])
    uv = project_points(corners.astype(np.float64), intrinsics)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if not len(uv):
        return None
    (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
    return float(u0), float(v0), float(u1), float(v1)


def _to_display(axis, rectangle) -> np.ndarray:
    """A data rectangle (u0, v0, u1, v1) as display pixels (x0, y0, x1, y1), y up."""
    corners = axis.transData.transform([rectangle[:2], rectangle[2:]])
    return np.concatenate([corners.min(axis=0), corners.max(axis=0)])


def _overlapping(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(A, B) bool: rectangle a of (A, 4) ``first`` and b of (B, 4) ``second`` share area
    (touching edges do not count); rectangles are (x0, y0, x1, y1)."""
    a, b = first[:, None, :], second[None, :, :]
    return ((a[..., 0] < b[..., 2]) & (b[..., 0] < a[..., 2])
            & (a[..., 1] < b[..., 3]) & (b[..., 1] < a[..., 3]))


def _candidate_spots(box: np.ndarray, size: tuple[float, float], image: np.ndarray,
                     search_image: bool) -> tuple[np.ndarray, np.ndarray]:
    """Rectangles (C, 4) a label of ``size`` (w, h) could take near ``box``, in order of
    preference, and (C,) bool: adjacent to the box.  Above and below the box (slid sideways
    to stay in the image), then beside it; with ``search_image`` also a grid over the whole
    image (for a label joined to its box by a leader line)."""
    w, h = size
    x0, y0, x1, y1 = box
    gap = _LABEL_GAP_PX
    left_x = min(max(x0, image[0]), image[2] - w)
    right_x = min(max(x1 - w, image[0]), image[2] - w)
    spots = [(left_x, y1 + gap), (right_x, y1 + gap), (left_x, y0 - gap - h),
             (right_x, y0 - gap - h), (x1 + gap, y1 - h), (x1 + gap, y0),
             (x0 - gap - w, y1 - h), (x0 - gap - w, y0)]
    corners = np.array(spots, dtype=np.float64)
    adjacent = np.ones(len(corners), bool)
    if search_image:
        xs = np.arange(image[0], image[2] - w, 6.0)
        ys = np.arange(image[1], image[3] - h, max(h / 3.0, 2.0))
        grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        corners = np.concatenate([corners, grid])
        adjacent = np.concatenate([adjacent, np.zeros(len(grid), bool)])
    return np.column_stack([corners, corners + [w, h]]), adjacent


def _distances(rectangles: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(C,) display pixels between each of (C, 4) ``rectangles`` and ``box`` (0: touching)."""
    dx = np.maximum(np.maximum(box[0] - rectangles[:, 2], rectangles[:, 0] - box[2]), 0.0)
    dy = np.maximum(np.maximum(box[1] - rectangles[:, 3], rectangles[:, 1] - box[3]), 0.0)
    return np.hypot(dx, dy)


def _best_spot(box: np.ndarray, size: tuple[float, float], image: np.ndarray,
               taken: np.ndarray, boxes: np.ndarray, search_image: bool) -> np.ndarray | None:
    """The spot (x0, y0, x1, y1) for a label of ``size`` near ``box`` that lies in ``image``
    and overlaps no rectangle of ``taken`` (nor comes within the spacing of one), at the least
    cost: its distance from the box, plus a penalty per region box whose outline it crosses,
    plus one for a spot off the box (ties: the order of :func:`_candidate_spots`).  None if
    no spot is free."""
    rectangles, adjacent = _candidate_spots(box, size, image, search_image)
    tolerance = 1e-6
    usable = (np.all(rectangles[:, :2] >= image[:2] - tolerance, axis=1)
              & np.all(rectangles[:, 2:] <= image[2:] + tolerance, axis=1))
    if len(taken):
        margin = np.array([-1.0, -1.0, 1.0, 1.0]) * _LABEL_SPACING_PX
        usable &= ~_overlapping(rectangles, taken + margin).any(axis=1)
    if not usable.any():
        return None
    rectangles, adjacent = rectangles[usable], adjacent[usable]
    crossed = np.zeros(len(rectangles), int)
    if len(boxes):
        within = (np.all(rectangles[:, None, :2] >= boxes[None, :, :2], axis=2)
                  & np.all(rectangles[:, None, 2:] <= boxes[None, :, 2:], axis=2))
        crossed = (_overlapping(rectangles, boxes) & ~within).sum(axis=1)
    cost = (_distances(rectangles, box) + _CROSSED_BOX_COST_PX * crossed
            + _DETACHED_COST_PX * ~adjacent)
    return rectangles[int(np.argmin(cost))]  # argmin: the first of equal costs


def _text_at_spot(axis, renderer, text: str, colour, fontsize: float, pad: float, gid: str,
                  box: np.ndarray, image: np.ndarray, taken: list, boxes: np.ndarray,
                  search_image: bool) -> np.ndarray | None:
    """Draw ``text`` on a coloured background at the best free spot near ``box`` (display
    pixels, like every rectangle here) and add its rectangle to ``taken``; returns the
    rectangle, or None (and draws nothing) when no spot is free."""
    artist = axis.text(0.0, 0.0, text, color="white", fontsize=fontsize, ha="left",
                       va="bottom", gid=gid, zorder=5,
                       bbox={"facecolor": colour, "edgecolor": "none", "alpha": 0.85,
                             "pad": pad})
    artist.update_bbox_position_size(renderer)
    extent = artist.get_bbox_patch().get_window_extent(renderer)
    anchor = axis.transData.transform((0.0, 0.0))
    offset = np.array([extent.x0, extent.y0]) - anchor  # background's corner from the anchor
    spot = _best_spot(box, (extent.width, extent.height), image,
                      np.array(taken, dtype=np.float64).reshape(-1, 4), boxes, search_image)
    if spot is None:
        artist.remove()
        return None
    artist.set_position(axis.transData.inverted().transform(spot[:2] - offset))
    taken.append(spot)
    return spot


def _leader_line(axis, spot: np.ndarray, box: np.ndarray, colour) -> None:
    """A thin line from a label to the nearest point of its box, unless they (nearly) touch."""
    if _distances(spot[None], box)[0] <= 2.0 * _LABEL_GAP_PX:
        return
    on_box = np.clip(0.5 * (spot[:2] + spot[2:]), box[:2], box[2:])
    on_label = np.clip(on_box, spot[:2], spot[2:])
    ends = axis.transData.inverted().transform([on_label, on_box])
    axis.plot(ends[:, 0], ends[:, 1], color=colour, linewidth=1.0, zorder=4)


def _label_regions(axis, renderer, regions, first: int, rectangles: list, colour, legend,
                   max_full_labels: int) -> list[int]:
    """Label a panel's regions without overlaps: the ``max_full_labels`` largest (by points)
    get a full label (beside the box, else joined to it by a leader line), the others a
    number tag where one fits beside the box; ``regions[i]`` is number ``first + i``.  Labels
    stay inside the image and off the legend.  ``rectangles``: each region's from
    :func:`_region_rectangle`.  Returns the indices of the regions that got a full label."""
    limits = np.array([axis.get_xlim(), axis.get_ylim()]).T.ravel()  # (u0, v0, u1, v1)
    image = _to_display(axis, limits)
    taken = [np.array(legend.get_window_extent(renderer).extents)]
    drawn = [i for i, rectangle in enumerate(rectangles) if rectangle is not None]
    # of a box reaching past the image edge, the part inside the image
    boxes = {i: np.clip(_to_display(axis, rectangles[i]), image[[0, 1, 0, 1]],
                        image[[2, 3, 2, 3]]) for i in drawn}
    all_boxes = np.array([boxes[i] for i in drawn], dtype=np.float64).reshape(-1, 4)
    labelled, tag_only = [], []
    for i in sorted(drawn, key=lambda i: -regions[i].n_points):
        region = regions[i]
        if len(labelled) >= max_full_labels:
            tag_only.append(i)
            continue
        text = (f"{region.kind} {first + i}: {region.n_points} points, "
                f"{max(region.extent) * 100.0:.0f} cm, {region.centroid[2]:.2f} m away")
        spot = _text_at_spot(axis, renderer, text, colour, 8, 1.5, LABEL_GID, boxes[i], image,
                             taken, all_boxes, search_image=True)
        if spot is None:
            tag_only.append(i)
        else:
            labelled.append(i)
            _leader_line(axis, spot, boxes[i], colour)
    for i in tag_only:
        _text_at_spot(axis, renderer, str(first + i), colour, 6.5, 1.0, TAG_GID, boxes[i], image,
                      taken, all_boxes, search_image=False)
    return labelled


def _panel_title(caption: str, regions, labelled: list[int], mixture_line: str) -> str:
    """Two lines: "<caption>: 20 region(s); + 14 smaller regions not labelled" (the note
    only when some of ``regions`` have no full label; ``labelled``: the indices that have
    one; "smaller" when each of the others has at most the points of every labelled one),
    then ``mixture_line``."""
    missing = [r.n_points for i, r in enumerate(regions) if i not in set(labelled)]
    note = ""
    if missing:
        smaller = bool(labelled) and max(missing) <= min(regions[i].n_points for i in labelled)
        noun = "region" if len(missing) == 1 else "regions"
        note = f"; + {len(missing)} {'smaller ' if smaller else ''}{noun} not labelled"
    return f"{caption}: {len(regions)} region(s){note}\n{mixture_line}"


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


def change_figure(
    reference_depth: np.ndarray, current_depth: np.ndarray, intrinsics: Intrinsics, changes,
    title: str = "", *, max_full_labels: int = FULL_LABELS_PER_PANEL,
):
    """The matplotlib figure :func:`draw_change` saves (the caller closes it).  Its layout is
    fixed once drawn, so the label placement (in display pixels) stays valid."""
    if isinstance(max_full_labels, bool) or not isinstance(max_full_labels, int) \
            or max_full_labels < 0:
        raise InputError(f"max_full_labels must be an int >= 0, got {max_full_labels!r}")
    plt = _pyplot()
    from matplotlib.lines import Line2D  # (matplotlib is the optional viz extra)
    from matplotlib.patches import Patch

    figure, axes = plt.subplots(1, 2, figsize=(15, 5.8), constrained_layout=True)
    # a region's number is its place in ``changes.regions`` (appeared, then disappeared), as
    # the CLI, report.json and Foxglove count them
    panels = (
        (axes[0], reference_depth, changes.disappeared_mask, tuple(changes.disappeared),
         changes.disappeared_mixture, DISAPPEARED_RGB, "reference: what disappeared",
         len(changes.appeared) + 1),
        (axes[1], current_depth, changes.appeared_mask, tuple(changes.appeared),
         changes.appeared_mixture, APPEARED_RGB, "current: what appeared", 1),
    )
    try:
        to_label = []
        for axis, depth, mask, regions, mixture, colour, caption, first in panels:
            picture = _grey(depth)
            if mask is not None and mask.shape == depth.shape:
                picture[mask] = 0.35 * picture[mask] + 0.65 * np.array(colour)
            axis.imshow(picture, interpolation="nearest")
            highlight = {c for region in regions for c in region.components}
            _ellipses(axis, mixture, intrinsics, highlight, colour)
            rectangles = [_region_rectangle(region, intrinsics) for region in regions]
            for rectangle in rectangles:
                if rectangle is not None:
                    u0, v0, u1, v1 = rectangle
                    axis.plot([u0, u1, u1, u0, u0], [v0, v0, v1, v1, v0], color=colour,
                              linewidth=1.5)
            k = mixture.n_components if mixture is not None else 0
            mixture_line = (f"its mixture: {k} Gaussians, {len(highlight)} of them change "
                            "components (bold)")
            # for the layout: the title as it will most likely be (the same two lines)
            largest = sorted(range(len(regions)), key=lambda i: -regions[i].n_points)
            axis.set_title(_panel_title(caption, regions, largest[:max_full_labels],
                                        mixture_line), fontsize=10)
            _depth_bar(figure, axis, depth)
            legend = [Line2D([], [], color=(1.0, 0.85, 0.2), linewidth=0.8,
                             label="a Gaussian of the mixture (2-sigma outline)"),
                      Line2D([], [], color=colour, linewidth=2.0,
                             label="a change component / the box of a region"),
                      Patch(color=colour, alpha=0.65, label="its changed pixels")]
            legend = axis.legend(handles=legend, loc="lower left", fontsize=7, framealpha=0.8)
            axis.set_xlim(0, depth.shape[1] - 1)
            axis.set_ylim(depth.shape[0] - 1, 0)
            axis.set_xticks([])
            axis.set_yticks([])
            to_label.append((axis, regions, first, rectangles, colour, legend, caption,
                             mixture_line))
        verdict = "CHANGED" if changes.changed else "no change"
        figure.suptitle(f"{title}  —  {verdict}" if title else verdict)
        figure.canvas.draw()  # lays the figure out; labels are placed in its display pixels
        figure.set_layout_engine("none")
        renderer = figure.canvas.get_renderer()
        for axis, regions, first, rectangles, colour, legend, caption, mixture_line in \
                to_label:
            labelled = _label_regions(axis, renderer, regions, first, rectangles, colour,
                                      legend, max_full_labels)
            axis.set_title(_panel_title(caption, regions, labelled, mixture_line), fontsize=10)
    except BaseException:
        plt.close(figure)
        raise
    return figure


def draw_change(
    reference_depth: np.ndarray, current_depth: np.ndarray, intrinsics: Intrinsics, changes,
    path: str | Path, title: str = "", *, max_full_labels: int = FULL_LABELS_PER_PANEL,
) -> Path:
    """The picture of what changed, like the paper's Fig. 8: the reference depth image with
    what disappeared (blue) and the current one with what appeared (red), each with its
    mixture's Gaussians as 2-sigma outlines (the change components bold) and a box per
    region.  The ``max_full_labels`` largest regions of a panel (by points) get a full label,
    the others at most a number tag; no two overlap, and the panel title says how many
    regions have no full label.

    ``reference_depth`` / ``current_depth``: (H, W) uint16 mm; ``changes``: a
    :class:`robot_change.change.results.ChangeSet`.  Returns the PNG's path.
    """
    plt = _pyplot()
    figure = change_figure(reference_depth, current_depth, intrinsics, changes, title,
                           max_full_labels=max_full_labels)
    try:
        return _save(figure, Path(path))
    finally:
        plt.close(figure)
