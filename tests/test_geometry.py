"""robot_change.cloud.geometry: depth image -> points and back, against plain NumPy twins."""

from __future__ import annotations

import numpy as np
import pytest

from hw.depth import Intrinsics
from robot_change.cloud.geometry import depth_to_points, project_points
from robot_change.errors import InputError

RNG = np.random.default_rng(11)


def twin_depth_to_points(depth, intr, min_depth_m, max_depth_m):
    """NumPy twin: same float64 arithmetic, row-major order."""
    height, width = depth.shape
    v, u = np.mgrid[0:height, 0:width]
    d = depth.astype(np.int64)
    min_mm = max(1, int(np.ceil(round(min_depth_m * 1000.0, 6))))
    max_mm = int(np.floor(round(max_depth_m * 1000.0, 6)))
    keep = (d > 0) & (d >= min_mm) & (d <= max_mm)
    z = depth[keep].astype(np.float64) / 1000.0
    x = ((u[keep].astype(np.float64) - intr.cx) / intr.fx) * z
    y = ((v[keep].astype(np.float64) - intr.cy) / intr.fy) * z
    points = np.stack([x, y, z], axis=1).astype(np.float32)
    pixels = np.flatnonzero(keep.ravel()).astype(np.int32)
    return points, pixels


def twin_project(points, intr):
    p = points.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p[:, 0] / p[:, 2] + intr.cx
        v = intr.fy * p[:, 1] / p[:, 2] + intr.cy
    bad = ~(p[:, 2] > 0) | ~np.all(np.isfinite(p), axis=1)
    u[bad] = np.nan
    v[bad] = np.nan
    return np.stack([u, v], axis=1)


def random_depth(height, width, invalid=0.3):
    depth = RNG.integers(1, 9000, size=(height, width)).astype(np.uint16)
    depth[RNG.random((height, width)) < invalid] = 0
    return depth


@pytest.mark.parametrize(
    "intr",
    [
        Intrinsics.openni_default(),
        Intrinsics.openni_default(320, 240),
        Intrinsics(37, 23, 41.5, 44.25, 17.3, 10.9),
    ],
    ids=["vga", "qvga", "odd"],
)
@pytest.mark.parametrize("limits", [(0.3, 5.0), (0.0, 65.535), (1.2345, 1.2355)])
def test_depth_to_points_matches_twin(intr, limits):
    depth = random_depth(intr.height, intr.width)
    points, pixels = depth_to_points(depth, intr, min_depth_m=limits[0], max_depth_m=limits[1])
    want_points, want_pixels = twin_depth_to_points(depth, intr, *limits)
    assert points.dtype == np.float32 and points.shape == want_points.shape
    assert pixels.dtype == np.int32
    np.testing.assert_array_equal(pixels, want_pixels)
    np.testing.assert_array_equal(points, want_points)


def test_depth_limits_are_inclusive_and_zero_is_invalid():
    intr = Intrinsics(4, 1, 100.0, 100.0, 1.5, 0.0)
    depth = np.array([[0, 399, 400, 5000]], dtype=np.uint16)
    points, pixels = depth_to_points(depth, intr, min_depth_m=0.4, max_depth_m=5.0)
    np.testing.assert_array_equal(pixels, [2, 3])
    np.testing.assert_array_equal(points[:, 2], np.float32([0.4, 5.0]))
    _, pixels = depth_to_points(depth, intr, min_depth_m=0.0, max_depth_m=4.999)
    np.testing.assert_array_equal(pixels, [1, 2])


def test_known_pixel_geometry():
    """x right, y down, z forward: a pixel right of and below the centre at 2 m."""
    intr = Intrinsics(5, 5, 100.0, 50.0, 2.0, 2.0)
    depth = np.zeros((5, 5), dtype=np.uint16)
    depth[4, 3] = 2000
    points, pixels = depth_to_points(depth, intr, min_depth_m=0.1, max_depth_m=10.0)
    np.testing.assert_allclose(points, [[0.02, 0.08, 2.0]], rtol=1e-6)
    assert pixels.tolist() == [4 * 5 + 3]


@pytest.mark.parametrize("rows", [0, 1, 7, 240, 479])
def test_depth_to_points_trailing_invalid_rows(rows):
    """Valid pixels only in the first ``rows`` rows (the rest 0 or out of range): the kernel
    stops early and its spare output row never shows."""
    intr = Intrinsics.openni_default()
    depth = random_depth(480, 640, invalid=0.5)
    depth[rows:] = 0
    depth[rows:, ::3] = 9000  # out of range
    if rows:
        depth[rows - 1, -1] = 1500  # the very last valid pixel at the end of a row
    points, pixels = depth_to_points(depth, intr, min_depth_m=0.3, max_depth_m=5.0)
    want = twin_depth_to_points(depth, intr, 0.3, 5.0)
    np.testing.assert_array_equal(points, want[0])
    np.testing.assert_array_equal(pixels, want[1])
    assert points.flags.c_contiguous and pixels.flags.c_contiguous


def test_all_invalid_frame_gives_empty_arrays():
    intr = Intrinsics.openni_default()
    points, pixels = depth_to_points(np.zeros((480, 640), np.uint16), intr)
    assert points.shape == (0, 3) and points.dtype == np.float32
    assert pixels.shape == (0,) and pixels.dtype == np.int32
    # everything outside the range is no better
    far = np.full((480, 640), 9000, np.uint16)
    assert depth_to_points(far, intr, min_depth_m=0.3, max_depth_m=5.0)[0].shape == (0, 3)


def test_non_contiguous_depth_is_accepted():
    intr = Intrinsics.openni_default(320, 240)
    big = random_depth(480, 640)
    view = big[::2, ::2]
    got = depth_to_points(view, intr)
    want = depth_to_points(np.ascontiguousarray(view), intr)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize(
    "depth, message",
    [
        (np.zeros((480, 640), np.float32), "uint16"),
        (np.zeros((480, 640), np.int32), "uint16"),
        (np.zeros((480, 640, 1), np.uint16), "2-D"),
        (np.zeros((240, 320), np.uint16), "intrinsics are for 640x480"),
        ([[1, 2]], "numpy array"),
    ],
)
def test_depth_to_points_rejects_bad_depth(depth, message):
    with pytest.raises(InputError, match=message):
        depth_to_points(depth, Intrinsics.openni_default())


@pytest.mark.parametrize(
    "limits, message",
    [((-0.1, 5.0), "min_depth_m"), ((2.0, 1.0), "max_depth_m"), ((0.3, float("nan")),
     "max_depth_m"), (("a", 5.0), "must be a number")],
)
def test_depth_to_points_rejects_bad_limits(limits, message):
    depth = np.zeros((480, 640), np.uint16)
    with pytest.raises(InputError, match=message):
        depth_to_points(depth, Intrinsics.openni_default(), min_depth_m=limits[0],
                        max_depth_m=limits[1])


def test_depth_to_points_rejects_non_intrinsics():
    with pytest.raises(InputError, match="Intrinsics"):
        depth_to_points(np.zeros((480, 640), np.uint16), (525.0, 525.0, 319.5, 239.5))


def test_project_points_matches_twin_and_handles_bad_points():
    intr = Intrinsics(37, 23, 41.5, 44.25, 17.3, 10.9)
    points = RNG.normal(size=(500, 3)).astype(np.float32)
    points[:5] = [[1, 1, 0], [1, 1, -1], [np.nan, 0, 1], [0, np.inf, 1], [0, 0, np.inf]]
    got = project_points(points, intr)
    assert got.shape == (500, 2) and got.dtype == np.float64
    np.testing.assert_array_equal(got, twin_project(points, intr))
    assert np.all(np.isnan(got[:5]))
    # float64 input gives the same numbers
    np.testing.assert_array_equal(project_points(points.astype(np.float64), intr), got)


def test_project_is_inverse_of_back_projection():
    intr = Intrinsics.openni_default()
    depth = random_depth(480, 640)
    points, pixels = depth_to_points(depth, intr, min_depth_m=0.0, max_depth_m=65.535)
    uv = project_points(points, intr)
    want = np.stack([pixels % 640, pixels // 640], axis=1).astype(np.float64)
    # float32 points: a few thousandths of a pixel of rounding
    np.testing.assert_allclose(uv, want, atol=5e-3)


def test_project_empty():
    out = project_points(np.zeros((0, 3), np.float32), Intrinsics.openni_default())
    assert out.shape == (0, 2)


@pytest.mark.parametrize(
    "points, message",
    [
        (np.zeros((4, 2), np.float32), r"shape \(N, 3\)"),
        (np.zeros(3, np.float32), r"shape \(N, 3\)"),
        (np.zeros((4, 3), np.int32), "float32"),
        ("points", "numpy array"),
    ],
)
def test_project_rejects_bad_points(points, message):
    with pytest.raises(InputError, match=message):
        project_points(points, Intrinsics.openni_default())
