"""Pictures: the geometry behind them, and that they are written."""

from __future__ import annotations

import itertools
import re
from types import SimpleNamespace

import numpy as np
import pytest

from hw.depth import Intrinsics
from robot_change.change.results import Region
from robot_change.cloud.chain import clean_cloud
from robot_change.errors import InputError
from robot_change.mixture.model import Mixture
from robot_change.tools.report import (
    FULL_LABELS_PER_PANEL,
    LABEL_GID,
    TAG_GID,
    change_figure,
    draw_change,
    draw_cloud,
    mixture_ellipses,
)


def test_a_sphere_straight_ahead_projects_to_a_centred_circle():
    camera = Intrinsics.openni_default()
    sigma, z = 0.1, 2.0
    [outline] = mixture_ellipses(np.array([[0.0, 0.0, z]]), np.eye(3)[None] * sigma**2, camera,
                                 n_sigma=2.0)
    centre = np.array([camera.cx, camera.cy])
    radii = np.linalg.norm(outline - centre, axis=1)
    np.testing.assert_allclose(radii, 2.0 * sigma * camera.fx / z, rtol=1e-9)


def test_an_elongated_gaussian_projects_along_its_long_axis():
    camera = Intrinsics.openni_default()
    covariance = np.diag([0.3**2, 0.01**2, 0.01**2])  # long along x (image right)
    [outline] = mixture_ellipses(np.array([[0.5, -0.2, 3.0]]), covariance[None], camera)
    extent = outline.max(axis=0) - outline.min(axis=0)
    assert extent[0] > 10 * extent[1]
    u0 = camera.fx * 0.5 / 3.0 + camera.cx
    assert abs(outline[:, 0].mean() - u0) < 1.0


def test_a_component_behind_the_camera_has_no_outline():
    camera = Intrinsics.openni_default()
    [outline] = mixture_ellipses(np.array([[0.0, 0.0, -1.0]]), np.eye(3)[None] * 0.01, camera)
    assert outline.shape == (0, 2)


def test_draw_cloud_writes_a_png(tmp_path):
    camera = Intrinsics.openni_default(160, 120)
    depth = np.full((120, 160), 2000, np.uint16)
    depth[40:80, 50:110] = 1500
    cloud = clean_cloud(depth, camera)
    path = draw_cloud(depth, camera, cloud, tmp_path / "cloud.png", title="box")
    assert path.read_bytes().startswith(b"\x89PNG")
    assert [p.name for p in tmp_path.iterdir()] == ["cloud.png"]


# --------------------------------------------------------------------------- change pictures

def _regions(kind: str, count: int, seed: int, clustered: bool = False) -> tuple[Region, ...]:
    """``count`` boxy regions in front of the camera: spread over the view, or ``clustered``
    in a small spot straight ahead (the case where labels collide most)."""
    rng = np.random.default_rng(seed)
    regions = []
    for _ in range(count):
        z = rng.uniform(1.5, 4.0)
        spread = np.array([0.3, 0.2]) if clustered else np.array([0.6, 0.4]) * z
        centroid = np.array([*rng.uniform(-spread, spread), z])
        extent = rng.uniform(0.04, 0.4, 3)
        regions.append(Region(kind, centroid, extent, centroid - extent / 2,
                              centroid + extent / 2, int(rng.integers(20, 3000)), 10, (0,),
                              np.arange(2), np.array([centroid - extent / 2,
                                                      centroid + extent / 2], np.float32)))
    return tuple(regions)


@pytest.fixture
def plt():
    """matplotlib's pyplot (the viz extra); skips where it is not installed."""
    return pytest.importorskip("matplotlib.pyplot")


def _changes(appeared: tuple[Region, ...], disappeared: tuple[Region, ...]):
    """What draw_change reads of a ChangeSet, with one small mixture per panel."""
    mixture = Mixture(np.array([0.5, 0.5]), np.array([[0.0, 0.0, 2.0], [0.5, 0.2, 3.0]]),
                      np.repeat(np.eye(3)[None] * 0.02, 2, axis=0))
    return SimpleNamespace(changed=bool(appeared or disappeared), appeared=appeared,
                           disappeared=disappeared, appeared_mask=None, disappeared_mask=None,
                           appeared_mixture=mixture, disappeared_mixture=mixture)


def _drawn_change(changes, **options):
    """The change figure of a VGA scene with ``changes``, drawn (so extents are final)."""
    camera = Intrinsics.openni_default()
    depth = np.full((camera.height, camera.width), 2500, np.uint16)
    depth[:, camera.width // 2:] = 3500
    figure = change_figure(depth, depth, camera, changes, title="many", **options)
    figure.canvas.draw()
    return figure


def _texts(axis, gid: str) -> list:
    return [text for text in axis.texts if text.get_gid() == gid]


def _background(text):
    """The window extent of a label's coloured background (what a reader sees)."""
    return text.get_bbox_patch().get_window_extent()


def _intersect(first, second) -> bool:
    """Whether two display boxes share area (touching edges do not count)."""
    return (first.x0 < second.x1 and second.x0 < first.x1
            and first.y0 < second.y1 and second.y0 < first.y1)


def _not_labelled(axis) -> int:
    found = re.search(r"\+ (\d+) (?:smaller )?regions? not labelled", axis.get_title())
    return int(found.group(1)) if found else 0


@pytest.mark.parametrize("clustered", [False, True])
def test_labels_of_many_regions_never_overlap_and_stay_in_the_image(clustered, plt):
    changes = _changes(_regions("appeared", 40, seed=1, clustered=clustered),
                       _regions("disappeared", 25, seed=2, clustered=clustered))
    figure = _drawn_change(changes)
    try:
        for axis in figure.axes[:2]:  # the two image panels (then the colour bars)
            labels = _texts(axis, LABEL_GID) + _texts(axis, TAG_GID)
            assert len(_texts(axis, LABEL_GID)) == FULL_LABELS_PER_PANEL
            assert len(_texts(axis, TAG_GID)) > 10  # most small regions still get a number
            extents = [_background(text) for text in labels]
            extents.append(axis.get_legend().get_window_extent())
            for first, second in itertools.combinations(extents, 2):
                assert not _intersect(first, second), (first, second)
            image = axis.get_window_extent()
            for extent in extents:
                assert image.x0 - 0.5 <= extent.x0 and extent.x1 <= image.x1 + 0.5
                assert image.y0 - 0.5 <= extent.y0 and extent.y1 <= image.y1 + 0.5
    finally:
        plt.close(figure)


@pytest.mark.parametrize("max_full_labels", [FULL_LABELS_PER_PANEL, 2, 0])
def test_only_the_largest_regions_get_a_full_label_and_the_title_counts_the_rest(
        max_full_labels, plt):
    appeared = _regions("appeared", 30, seed=3)
    disappeared = _regions("disappeared", 12, seed=4, clustered=True)
    figure = _drawn_change(_changes(appeared, disappeared), max_full_labels=max_full_labels)
    try:
        # numbered as the CLI, report.json and Foxglove count them: appeared, then
        # disappeared
        for axis, regions, first in zip(figure.axes[:2], (disappeared, appeared),
                                        (len(appeared) + 1, 1), strict=True):
            labels = _texts(axis, LABEL_GID)
            assert len(labels) == max_full_labels
            numbers = {int(re.match(r"\w+ (\d+): ", text.get_text()).group(1))
                       for text in labels}
            by_size = sorted(range(len(regions)), key=lambda i: -regions[i].n_points)
            assert numbers == {first + i for i in by_size[:max_full_labels]}
            assert _not_labelled(axis) == len(regions) - max_full_labels
            smaller = "smaller " if max_full_labels else ""
            assert f"; + {_not_labelled(axis)} {smaller}regions not labelled" in axis.get_title()
            tags = {int(text.get_text()) for text in _texts(axis, TAG_GID)}
            assert not tags & numbers  # a region has a label or a tag, never both
    finally:
        plt.close(figure)


def test_a_few_regions_are_all_labelled_and_the_title_has_no_note(plt):
    appeared = _regions("appeared", 3, seed=5)
    figure = _drawn_change(_changes(appeared, ()))
    try:
        reference, current = figure.axes[:2]
        assert len(_texts(current, LABEL_GID)) == 3 and not _texts(current, TAG_GID)
        assert "not labelled" not in current.get_title()
        assert "3 region(s)" in current.get_title()
        assert not reference.texts and "0 region(s)" in reference.get_title()
    finally:
        plt.close(figure)


def test_draw_change_writes_a_png_with_many_regions_and_closes_its_figure(tmp_path, plt):
    camera = Intrinsics.openni_default(160, 120)
    depth = np.full((120, 160), 2000, np.uint16)
    changes = _changes(_regions("appeared", 20, seed=6), _regions("disappeared", 20, seed=7))
    figures_before = plt.get_fignums()
    path = draw_change(depth, depth, camera, changes, tmp_path / "report.png", title="many",
                       max_full_labels=4)
    assert path.read_bytes().startswith(b"\x89PNG")
    assert [p.name for p in tmp_path.iterdir()] == ["report.png"]
    assert plt.get_fignums() == figures_before


def test_a_negative_number_of_labels_is_refused(tmp_path):
    camera = Intrinsics.openni_default(160, 120)
    depth = np.full((120, 160), 2000, np.uint16)
    with pytest.raises(InputError, match="max_full_labels"):
        draw_change(depth, depth, camera, _changes((), ()), tmp_path / "report.png",
                    max_full_labels=-1)
