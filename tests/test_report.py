"""Pictures: the geometry behind them, and that they are written."""

from __future__ import annotations

import numpy as np

from hw.depth import Intrinsics
from robot_change.cloud.chain import clean_cloud
from robot_change.tools.report import draw_cloud, mixture_ellipses


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
