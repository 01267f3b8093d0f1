"""robot_change.cloud.depth_voxels: the fused depth -> voxel grid kernel against its NumPy twin
(geometry's back-projection twin + the filters' voxel twin with image rows as band rows)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SHARED_DATA, SIM_FIXTURES
from test_filters import twin_bands, twin_keys, twin_voxel_sums
from test_geometry import twin_depth_to_points

from hw.depth import Intrinsics
from hw.images import read_depth_image
from robot_change.cloud.depth_voxels import _depth_voxel_kernel, depth_voxel_grid
from robot_change.cloud.geometry import depth_kernel_args, depth_to_points
from robot_change.cloud.voxels import voxel_grid, voxel_table_size
from robot_change.errors import InputError

RNG = np.random.default_rng(5)
INTR = Intrinsics.openni_default()


def twin_depth_voxel_grid(depth, intr, leaf, min_depth_m, max_depth_m, limit=None):
    """(centroids, counts, keys, inverse per pixel, points kept), the kernel's summation order."""
    height, width = depth.shape
    if limit is None:
        limit = voxel_table_size(width)[1]
    points, pixels = twin_depth_to_points(depth, intr, min_depth_m, max_depth_m)
    keys = np.full(depth.size, -1, dtype=np.int64)
    keys[pixels] = twin_keys(points, leaf)
    p64 = np.zeros((depth.size, 3))
    p64[pixels] = points.astype(np.float64)
    rows = np.arange(0, depth.size + 1, width)
    band_of = twin_bands(keys, rows, limit)
    centroids, counts, voxel_keys, inverse = twin_voxel_sums(p64, keys, band_of)
    return centroids, counts, voxel_keys, inverse, int(np.count_nonzero(keys >= 0))


def assert_matches_twin(depth, intr=INTR, leaf=0.03, limits=(0.4, 5.0)):
    got = depth_voxel_grid(depth, intr, leaf, min_depth_m=limits[0], max_depth_m=limits[1])
    centroids, counts, keys, inverse, kept = twin_depth_voxel_grid(depth, intr, leaf, *limits)
    grid = got.grid()
    assert len(got) == len(grid) and got.leaf_m == leaf
    assert grid.points.dtype == np.float32 and grid.inverse.dtype == np.int32
    assert grid.inverse.shape == (depth.size,)
    np.testing.assert_array_equal(grid.keys, keys)
    np.testing.assert_array_equal(grid.counts, counts)
    np.testing.assert_array_equal(grid.inverse, inverse)
    np.testing.assert_array_equal(grid.points, centroids)
    assert got.n_points == kept == grid.counts.sum()
    return got


def room_depth():
    path = SIM_FIXTURES / "frames" / "room_vga.png"
    return read_depth_image(path)


def noisy_depth(rng, holes=0.1, shape=(480, 640)):
    """A floor and a wall with Kinect-like noise and dropped pixels."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    ray_y = (v - (shape[0] - 1) / 2) / 525.0
    with np.errstate(divide="ignore"):
        z = np.where(ray_y > 0.05, 1.2 / ray_y, 4.5)
    z = np.minimum(z, 4.5) + rng.normal(0, 0.01, z.shape)
    depth = np.round(z * 1000).astype(np.uint16)
    depth[rng.random(depth.shape) < holes] = 0
    return depth


@pytest.mark.parametrize("leaf", [0.01, 0.03, 0.1])
def test_matches_twin_on_the_bundled_room_frame(leaf):
    assert_matches_twin(room_depth(), leaf=leaf)


@pytest.mark.parametrize("holes, limits", [(0.0, (0.4, 5.0)), (0.3, (0.4, 5.0)),
                                           (0.1, (1.5, 3.0)), (0.9, (0.0, 65.535))])
def test_matches_twin_on_noisy_frames(holes, limits):
    assert_matches_twin(noisy_depth(np.random.default_rng(3), holes), limits=limits)


@pytest.mark.skipif(not (SHARED_DATA / "open3d-tum-sample" / "TUM_depth.png").is_file(),
                    reason="../shared/data (real TUM frame) is not beside this checkout")
def test_matches_twin_on_a_real_frame():
    depth = read_depth_image(SHARED_DATA / "open3d-tum-sample" / "TUM_depth.png", scale=5000)
    assert_matches_twin(depth, leaf=0.02)


@pytest.mark.parametrize("limit", [1, 700, 3000])
def test_small_band_limits_match_twin(limit):
    """A band per row (limit below the row length), and bands closed mid-frame."""
    depth = noisy_depth(np.random.default_rng(9), 0.2, shape=(60, 640))
    intr = Intrinsics(640, 60, 525.0, 525.0, 319.5, 29.5)
    args = depth_kernel_args(depth, intr, 0.4, 5.0)
    bits = voxel_table_size(640)[0]
    centroids, counts, keys, pixel_record, record_voxel, kept = _depth_voxel_kernel(
        *args, 1.0 / 0.02, bits, limit)
    want = twin_depth_voxel_grid(depth, intr, 0.02, 0.4, 5.0, limit)
    np.testing.assert_array_equal(keys, want[2])
    np.testing.assert_array_equal(counts, want[1])
    inverse = np.where(pixel_record >= 0, record_voxel[np.maximum(pixel_record, 0)], -1)
    np.testing.assert_array_equal(inverse, want[3])
    np.testing.assert_array_equal(centroids, want[0])
    assert kept == want[4]


def test_same_voxels_as_the_two_separate_stages():
    depth = room_depth()
    got = depth_voxel_grid(depth, INTR, 0.03, min_depth_m=0.4, max_depth_m=5.0).grid()
    points, pixels = depth_to_points(depth, INTR, min_depth_m=0.4, max_depth_m=5.0)
    want = voxel_grid(points, 0.03)
    np.testing.assert_array_equal(got.keys, want.keys)
    np.testing.assert_array_equal(got.counts, want.counts)
    np.testing.assert_array_equal(got.inverse[pixels], want.inverse)
    assert np.count_nonzero(got.inverse >= 0) == len(points)
    # only the band boundaries differ: at most one float32 step apart
    np.testing.assert_array_max_ulp(got.points, want.points, maxulp=1)


def test_wide_and_tiny_images():
    wide = noisy_depth(np.random.default_rng(1), 0.05, shape=(4, 9000))
    assert_matches_twin(wide, Intrinsics(9000, 4, 525.0, 525.0, 4499.5, 1.5))
    one = np.zeros((1, 1), np.uint16)
    one[0, 0] = 1234
    got = assert_matches_twin(one, Intrinsics(1, 1, 525.0, 525.0, 0.0, 0.0))
    np.testing.assert_array_equal(got.points, np.float32([[0.0, 0.0, 1.234]]))


def test_empty_and_all_invalid_frames():
    for depth in (np.zeros((480, 640), np.uint16), np.full((480, 640), 9000, np.uint16)):
        got = assert_matches_twin(depth)
        assert len(got) == 0 and got.n_points == 0
        assert np.all(got.pixel_voxel() == -1)


def test_tiny_leaf_drops_what_a_key_cannot_hold():
    """At a 10 um leaf a key holds +-10 m: every pixel of a 20 m wall is dropped, never wrapped."""
    depth = np.full((4, 6), 20000, np.uint16)
    depth[0, 0] = 1000
    got = assert_matches_twin(depth, Intrinsics(6, 4, 525.0, 525.0, 2.5, 1.5), leaf=1e-5,
                              limits=(0.0, 65.535))
    assert got.n_points == 1 and np.count_nonzero(got.pixel_voxel() >= 0) == 1


def test_non_contiguous_depth_is_accepted():
    depth = np.asfortranarray(noisy_depth(np.random.default_rng(2)))
    assert_matches_twin(depth)


@pytest.mark.parametrize(
    "depth, intr, leaf, message",
    [
        (np.zeros((480, 640), np.float32), INTR, 0.03, "uint16"),
        (np.zeros((240, 320), np.uint16), INTR, 0.03, "intrinsics"),
        (np.zeros((480, 640), np.uint16), "kinect", 0.03, "Intrinsics"),
        (np.zeros((480, 640), np.uint16), INTR, 0.0, "leaf_m"),
        (np.zeros((480, 640), np.uint16), INTR, float("nan"), "leaf_m"),
    ],
)
def test_rejects_bad_input(depth, intr, leaf, message):
    with pytest.raises(InputError, match=message):
        depth_voxel_grid(depth, intr, leaf)
