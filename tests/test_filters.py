"""robot_change.cloud.voxels, .outliers, .plane, .fusion: every numba kernel against a plain NumPy
twin, plus edge cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hw.depth import Intrinsics
from robot_change.cloud.fusion import fuse_depth
from robot_change.cloud.geometry import depth_to_points
from robot_change.cloud.outliers import knn_mean_distance, statistical_outliers
from robot_change.cloud.plane import (
    RANSAC_BAIL_SIGMAS,
    RANSAC_SAMPLE,
    Plane,
    _inlier_scatter,
    _plane_inliers,
    _ransac_kernel,
    fit_plane_ransac,
    ransac_sample,
    ransac_triples,
    remove_plane,
)
from robot_change.cloud.voxels import (
    KEY_MAX_INDEX,
    KEY_MIN_INDEX,
    VOXEL_CHUNK,
    _voxel_kernel,
    pack_keys,
    unpack_keys,
    voxel_grid,
    voxel_table_size,
)
from robot_change.errors import InputError

RNG = np.random.default_rng(7)


# --------------------------------------------------------------------------------------------
# voxel grid


def twin_bands(keys, rows, limit):
    """Band number of each point (the voxel kernels' rule): points go in rows (``rows``: (R + 1,)
    boundaries); a band is closed at the start of a row when it holds more than ``limit - row
    length`` distinct keys.  ``keys`` (N,) int64, -1 = dropped (not counted)."""
    band_of = np.empty(len(keys), dtype=np.int64)
    band, seen = 0, set()
    for a, b in zip(rows[:-1], rows[1:], strict=True):
        if len(seen) > limit - (b - a):
            band, seen = band + 1, set()
        seen.update(keys[a:b][keys[a:b] >= 0].tolist())
        band_of[a:b] = band
    return band_of


def twin_voxel_sums(p64, keys_all, band_of):
    """np.unique(return_inverse) + bincount, float64, the kernels' summation order: per band a
    partial sum per voxel (points in order), then per voxel the sum of its partials in band
    order.  ``keys_all`` (N,) int64 (-1 = dropped).  Returns (centroids, counts, keys, inverse)."""
    ok = keys_all >= 0
    part_keys, part_sums, part_counts = [], [], []
    for band in np.unique(band_of[ok]):
        sel = np.flatnonzero(ok & (band_of == band))
        keys, inv = np.unique(keys_all[sel], return_inverse=True)
        inv = inv.ravel()
        part_keys.append(keys)
        part_counts.append(np.bincount(inv, minlength=len(keys)).astype(np.float64))
        part_sums.append(np.stack(
            [np.bincount(inv, weights=p64[sel, j], minlength=len(keys)) for j in range(3)], axis=1
        ))
    if part_keys:
        part_keys = np.concatenate(part_keys)
        part_sums = np.concatenate(part_sums)
        part_counts = np.concatenate(part_counts)
    else:
        part_keys, part_sums, part_counts = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
    keys, pinv = np.unique(part_keys, return_inverse=True)
    pinv = pinv.ravel()
    counts = np.bincount(pinv, weights=part_counts, minlength=len(keys))
    sums = np.stack(
        [np.bincount(pinv, weights=part_sums[:, j], minlength=len(keys)) for j in range(3)], axis=1
    )
    centroids = (sums / counts[:, None]).astype(np.float32)
    inverse = np.full(len(keys_all), -1, dtype=np.int64)
    inverse[ok] = np.searchsorted(keys, keys_all[ok])
    return centroids, counts.astype(np.int64), keys, inverse


def twin_keys(points, leaf):
    """(N,) int64 packed keys of float32 points, -1 where NaN/inf or out of the key range."""
    p64 = points.astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        idx = np.floor(p64 * (1.0 / leaf))
    ok = np.all((idx >= KEY_MIN_INDEX) & (idx <= KEY_MAX_INDEX), axis=1)
    keys_all = np.full(len(points), -1, dtype=np.int64)
    keys_all[ok] = pack_keys(idx[ok].astype(np.int64))
    return keys_all


def twin_voxel_grid(points, leaf, chunk=VOXEL_CHUNK, limit=None):
    """NumPy twin of voxel_grid: chunks of ``chunk`` points are the rows of the band rule."""
    if limit is None:
        limit = voxel_table_size(chunk)[1]
    keys_all = twin_keys(points, leaf)
    rows = np.append(np.arange(0, len(points), chunk), len(points))
    band_of = twin_bands(keys_all, rows, limit)
    return twin_voxel_sums(points.astype(np.float64), keys_all, band_of)


def assert_grid_matches_twin(points, leaf):
    grid = voxel_grid(points, leaf)
    centroids, counts, keys, inverse = twin_voxel_grid(points, leaf)
    assert grid.points.dtype == np.float32 and grid.counts.dtype == np.int32
    assert grid.keys.dtype == np.int64 and grid.inverse.dtype == np.int32
    np.testing.assert_array_equal(grid.keys, keys)
    np.testing.assert_array_equal(grid.counts, counts)
    np.testing.assert_array_equal(grid.inverse, inverse)
    np.testing.assert_array_equal(grid.points, centroids)
    assert len(grid) == len(keys) and grid.leaf_m == leaf
    return grid


def depth_scene_points(rng=None):
    """A structured cloud: a VGA frame of a tilted floor with a box, plus Kinect-like noise."""
    rng = RNG if rng is None else rng
    intr = Intrinsics.openni_default()
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    ray_y = (v - intr.cy) / intr.fy
    with np.errstate(divide="ignore"):
        z = np.where(ray_y > 0.05, 1.2 / ray_y, 4.5)  # floor 1.2 m below the camera, wall
    box = (np.abs(u - 300) < 60) & (np.abs(v - 300) < 40)
    z = np.where(box, 2.0, z)
    z = np.minimum(z, 4.5) + rng.normal(0, 0.004, z.shape)
    depth = np.round(z * 1000).astype(np.uint16)
    depth[rng.random(depth.shape) < 0.1] = 0
    return depth_to_points(depth, intr, min_depth_m=0.4, max_depth_m=5.0)[0]


@pytest.mark.parametrize("leaf", [0.01, 0.02, 0.05])
def test_voxel_grid_matches_twin_on_a_depth_scene(leaf):
    points = depth_scene_points()
    grid = assert_grid_matches_twin(points, leaf)
    assert grid.counts.sum() == len(points)


@pytest.mark.parametrize("n, spread", [(1000, 0.05), (20000, 1.0), (200_000, 50.0)])
def test_voxel_grid_matches_twin_on_random_points(n, spread):
    # the last case has ~200k distinct voxels: the hash table grows many times
    points = (RNG.normal(size=(n, 3)) * spread).astype(np.float32)
    assert_grid_matches_twin(points, 0.02)


@pytest.mark.parametrize("chunk, limit", [(1, 1), (7, 5), (64, 100), (64, 30)])
def test_voxel_kernel_small_bands_match_twin(chunk, limit):
    """Many bands: voxels split over bands, stale hash slots of earlier bands reused, and a limit
    below the chunk length (a band per chunk)."""
    points = depth_scene_points(np.random.default_rng(11))[::37]
    points = np.concatenate([points, points[::-3], [[np.nan, 0, 1]]]).astype(np.float32)
    bits = voxel_table_size(chunk)[0]
    centroids, counts, keys, inverse = _voxel_kernel(points, 1.0 / 0.05, chunk, bits, limit)
    want = twin_voxel_grid(points, 0.05, chunk, limit)
    np.testing.assert_array_equal(keys, want[2])
    np.testing.assert_array_equal(counts, want[1])
    np.testing.assert_array_equal(inverse, want[3])
    np.testing.assert_array_equal(centroids, want[0])


def test_voxel_table_size_keeps_the_table_a_quarter_full_at_most():
    for row in (1, 512, 640, 4096, 100_000):
        bits, limit = voxel_table_size(row)
        assert (1 << bits) >= 4 * row and (1 << bits) >= 1 << 14
        assert max(limit, row) <= (1 << bits) // 4


def test_voxel_grid_duplicates_and_negative_coordinates():
    base = np.array([[-0.011, -0.5, 0.0], [0.011, 0.019, -0.001]], np.float32)
    points = np.repeat(base, [5, 3], axis=0)[RNG.permutation(8)]
    grid = assert_grid_matches_twin(points, 0.02)
    assert sorted(grid.counts.tolist()) == [3, 5]
    # sorted by z, then y, then x
    np.testing.assert_array_equal(unpack_keys(grid.keys), [[0, 0, -1], [-1, -25, 0]])


def test_voxel_grid_drops_nan_inf_and_huge_rows():
    leaf = 0.01
    points = np.array(
        [
            [0.1, 0.2, 1.0],
            [np.nan, 0.0, 1.0],
            [0.0, np.inf, 1.0],
            [0.0, 0.0, -np.inf],
            [1e9, 0.0, 1.0],  # voxel index 1e11: does not fit 21 bits
            [0.0, -3e38, 1.0],
            [(KEY_MAX_INDEX + 0.5) * leaf, 0.0, 1.0],  # last index that fits
            [(KEY_MAX_INDEX + 1.5) * leaf, 0.0, 1.0],  # first that does not
            [(KEY_MIN_INDEX + 0.5) * leaf, 0.0, 1.0],
            [(KEY_MIN_INDEX - 0.5) * leaf, 0.0, 1.0],
            [0.1, 0.2, 1.0],
        ],
        dtype=np.float32,
    )
    grid = assert_grid_matches_twin(points, leaf)
    assert grid.inverse.tolist().count(-1) == 7
    assert grid.inverse[0] == grid.inverse[10] >= 0
    ix = unpack_keys(grid.keys)[:, 0]
    assert KEY_MAX_INDEX in ix and KEY_MIN_INDEX in ix
    assert np.all(np.isfinite(grid.points))


def test_voxel_grid_empty_and_single_point():
    grid = voxel_grid(np.zeros((0, 3), np.float32), 0.02)
    assert grid.points.shape == (0, 3) and grid.keys.shape == (0,) and grid.inverse.shape == (0,)
    grid = voxel_grid(np.array([[np.nan, 0, 0]], np.float32), 0.02)
    assert len(grid) == 0 and grid.inverse.tolist() == [-1]
    grid = voxel_grid(np.array([[0.5, -0.5, 2.0]], np.float32), 0.02)
    np.testing.assert_array_equal(grid.points, [[0.5, -0.5, 2.0]])
    assert grid.counts.tolist() == [1] and grid.inverse.tolist() == [0]


@pytest.mark.parametrize(
    "points, leaf, message",
    [
        (np.zeros((5, 3), np.float64), 0.02, "float32"),
        (np.zeros((5, 2), np.float32), 0.02, r"\(N, 3\)"),
        (np.zeros((5, 3), np.float32), 0.0, "leaf_m"),
        (np.zeros((5, 3), np.float32), -0.01, "leaf_m"),
        (np.zeros((5, 3), np.float32), float("nan"), "leaf_m"),
        (np.zeros((5, 3), np.float32), "2cm", "leaf_m"),
    ],
)
def test_voxel_grid_rejects_bad_input(points, leaf, message):
    with pytest.raises(InputError, match=message):
        voxel_grid(points, leaf)


def test_pack_unpack_roundtrip():
    idx = RNG.integers(KEY_MIN_INDEX, KEY_MAX_INDEX + 1, size=(1000, 3))
    idx[:2] = [[KEY_MIN_INDEX] * 3, [KEY_MAX_INDEX] * 3]
    keys = pack_keys(idx)
    np.testing.assert_array_equal(unpack_keys(keys), idx)
    # key order is lexicographic (z, y, x)
    order = np.lexsort((idx[:, 0], idx[:, 1], idx[:, 2]))
    np.testing.assert_array_equal(np.argsort(keys), order)
    with pytest.raises(InputError):
        pack_keys(np.array([[KEY_MAX_INDEX + 1, 0, 0]]))


# --------------------------------------------------------------------------------------------
# statistical outliers


def twin_knn_mean(points, keys, k, cap):
    """Brute force over all pairs: neighbours = Chebyshev voxel distance 1."""
    idx = unpack_keys(keys)
    p = points.astype(np.float64)
    out = np.empty(len(points))
    for i in range(len(points)):
        cheb = np.abs(idx - idx[i]).max(axis=1)
        nb = np.flatnonzero(cheb == 1)
        d = p[nb] - p[i]
        dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
        best = np.sort(np.minimum(dist, cap))[:k]
        best = np.concatenate([best, np.full(k - len(best), cap)])
        s = 0.0
        for value in best:  # ascending, one by one, as the kernel sums
            s += value
        out[i] = s / k
    return out


def clustered_cloud(n=3000):
    """Blobs and sheets with scattered specks, as a voxel grid at 2 cm."""
    blobs = RNG.normal(size=(n, 3)) * 0.05 + RNG.integers(-2, 3, size=(n, 3)) * 0.3
    sheet = np.column_stack([RNG.uniform(-0.5, 0.5, n), RNG.uniform(-0.5, 0.5, n),
                             np.full(n, 1.0) + RNG.normal(0, 0.003, n)])
    specks = RNG.uniform(-1, 1, size=(60, 3))
    points = np.concatenate([blobs, sheet, specks]).astype(np.float32)
    return voxel_grid(points, 0.02)


@pytest.mark.parametrize("k", [1, 4, 8, 26])
def test_knn_mean_distance_matches_brute_force(k):
    grid = clustered_cloud()
    cap = 0.04
    got = knn_mean_distance(grid.points, grid.keys, k, cap)
    want = twin_knn_mean(grid.points, grid.keys, k, cap)
    np.testing.assert_array_equal(got, want)


def test_knn_mean_distance_on_masked_subset():
    grid = clustered_cloud(1000)
    keep = RNG.random(len(grid)) < 0.6
    got = knn_mean_distance(grid.points[keep], grid.keys[keep], 4, 0.04)
    np.testing.assert_array_equal(got, twin_knn_mean(grid.points[keep], grid.keys[keep], 4, 0.04))


def test_knn_no_false_neighbours_across_key_fields():
    """Keys one apart across a field boundary (x wraps into y) are not neighbours."""
    leaf = 1.0
    points = np.array(
        [
            [KEY_MAX_INDEX + 0.5, 0.5, 0.5],  # (xmax, 0, 0)
            [KEY_MIN_INDEX + 0.5, 1.5, 0.5],  # (xmin, 1, 0): packed key is the first one + 1
            [0.5, KEY_MIN_INDEX + 0.5, 1.5],  # (0, ymin, 1)
            [0.5, KEY_MAX_INDEX + 0.5, 0.5],  # (0, ymax, 0): key differs by one y-step
        ],
        dtype=np.float32,
    )
    grid = voxel_grid(points, leaf)
    assert len(grid) == 4
    assert np.diff(grid.keys).min() == 1  # the trap is really there
    got = knn_mean_distance(grid.points, grid.keys, 2, 3.0)
    np.testing.assert_array_equal(got, np.full(4, 3.0))
    np.testing.assert_array_equal(got, twin_knn_mean(grid.points, grid.keys, 2, 3.0))


@pytest.mark.parametrize("k", [3, 4])
def test_knn_no_false_neighbours_across_column_fields(k):
    """The row walk's targets (z, y + 1) and (z + 1, y - 1) carry or borrow between the y
    and z fields for y at the ends of its range, and (x + 1, y, z) would carry from x into y;
    such voxels are not neighbours.  The points sit close together whatever their keys, so a
    false neighbour would show in the statistic.  k = 4 runs the kernel's copy compiled for
    that constant, k = 3 the general one."""
    lo, hi = KEY_MIN_INDEX, KEY_MAX_INDEX
    idx = np.array(
        [
            [0, lo, 0], [0, hi, 0],  # (x + 1, y - 1) of the first borrows into the second
            [5, hi, 0], [6, lo, 1],  # (x, y + 1) of the first carries into the second
            [8, 0, hi], [8, 1, lo],  # (x, y, z + 1) of the first carries into the second
            [10, lo, 0], [10, lo + 1, 1],  # true neighbours
        ]
    )[:, ::-1]  # written as (z, y, x): the rows along x are the key's columns
    keys = pack_keys(idx)
    order = np.argsort(keys)
    keys = keys[order]
    points = (np.arange(len(keys))[:, None] * np.array([0.01, 0.02, 0.03])).astype(np.float32)
    got = knn_mean_distance(points, keys, k, 3.0)
    want = twin_knn_mean(points, keys, k, 3.0)
    np.testing.assert_array_equal(got, want)
    true_pair = np.isin(order, [6, 7])
    assert np.all(got[true_pair] < 3.0) and np.all(got[~true_pair] == 3.0)


@pytest.mark.parametrize("alpha", [0.0, 1.0, 2.0])
def test_statistical_outliers_matches_twin(alpha):
    grid = clustered_cloud()
    got = statistical_outliers(grid.points, grid.keys, grid.leaf_m, 4, alpha, 2.0)
    stat = twin_knn_mean(grid.points, grid.keys, 4, 2.0 * grid.leaf_m)
    want = stat <= stat.mean() + alpha * stat.std()
    assert got.dtype == bool
    np.testing.assert_array_equal(got, want)


def test_statistical_outliers_drops_specks_keeps_sheet_edges():
    """A 1 m square sheet sampled densely, plus isolated specks: every speck goes, the sheet
    stays, its outline included."""
    leaf = 0.02
    n = 60_000
    sheet = np.column_stack([RNG.uniform(0, 1, n), RNG.uniform(0, 1, n),
                             2.0 + RNG.normal(0, 0.002, n)])
    specks = np.column_stack([RNG.uniform(0, 1, 30), RNG.uniform(0, 1, 30),
                              RNG.uniform(1.2, 1.8, 30)])
    points = np.concatenate([sheet, specks]).astype(np.float32)
    grid = voxel_grid(points, leaf)
    inlier = statistical_outliers(grid.points, grid.keys, leaf)
    is_speck = grid.points[:, 2] < 1.9
    assert is_speck.sum() == 30
    assert not inlier[is_speck].any()
    sheet_kept = inlier[~is_speck]
    assert sheet_kept.mean() > 0.99
    idx = unpack_keys(grid.keys[~is_speck])
    outline = (idx[:, 0] == idx[:, 0].min()) | (idx[:, 0] == idx[:, 0].max()) | (
        idx[:, 1] == idx[:, 1].min()) | (idx[:, 1] == idx[:, 1].max())
    assert sheet_kept[outline].mean() > 0.95


def test_statistical_outliers_empty_and_single():
    assert statistical_outliers(np.zeros((0, 3), np.float32), np.zeros(0, np.int64),
                                0.02).shape == (0,)
    grid = voxel_grid(np.array([[0, 0, 1]], np.float32), 0.02)
    assert knn_mean_distance(grid.points, grid.keys, 4, 0.04).tolist() == [0.04]
    assert statistical_outliers(grid.points, grid.keys, 0.02).tolist() == [True]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(k=0), "k=0"),
        (dict(k=27), "k=27"),
        (dict(k=2.5), "k=2.5"),
        (dict(alpha=-1.0), "alpha"),
        (dict(alpha=float("inf")), "alpha"),
        (dict(cap_leaves=0.0), "cap_leaves"),
        (dict(leaf_m=0.0), "leaf_m"),
    ],
)
def test_statistical_outliers_rejects_bad_parameters(kwargs, message):
    grid = clustered_cloud(200)
    args = dict(points=grid.points, keys=grid.keys, leaf_m=grid.leaf_m)
    args.update(kwargs)
    with pytest.raises(InputError, match=message):
        statistical_outliers(**args)


def test_statistical_outliers_rejects_mismatched_keys():
    grid = clustered_cloud(200)
    with pytest.raises(InputError, match="rows"):
        statistical_outliers(grid.points, grid.keys[:-1], 0.02)
    with pytest.raises(InputError, match="increasing"):
        statistical_outliers(grid.points, grid.keys[::-1].copy(), 0.02)
    with pytest.raises(InputError, match="int64"):
        statistical_outliers(grid.points, grid.keys.astype(np.int32), 0.02)
    bad = grid.points.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        statistical_outliers(bad, grid.keys, 0.02)


# --------------------------------------------------------------------------------------------
# RANSAC plane


def twin_ransac(points, triples, distance, up, cos_min, confidence=1.0, sample=None,
                bail_sigmas=RANSAC_BAIL_SIGMAS):
    """Plain NumPy loop over the same triples, each scored on the sample rows (all rows when
    None) block by block (256 rows), dropped when it can no longer win or its count falls below
    n w - bail_sigmas sqrt(n w (1 - w)) - 1; first strictly best wins; the classic adaptive stop
    once t + 1 >= log(1 - confidence) / log(1 - w**3), w = best count / sample size."""
    full = points.astype(np.float64)
    p = full if sample is None else full[sample]
    use_up = bool(np.any(up != 0))
    best = (-1, 0, np.zeros(3), 0.0)
    needed = math.inf
    tried = 0
    for t, (a, b, c) in enumerate(triples):
        tried = t + 1
        u = full[b] - full[a]
        v = full[c] - full[a]
        n = np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                      u[0] * v[1] - u[1] * v[0]])
        norm = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        n = n / norm if norm >= 1e-12 else n
        ok = norm >= 1e-12 and not (
            use_up and abs(n[0] * up[0] + n[1] * up[1] + n[2] * up[2]) < cos_min)
        if ok:
            d = -(n[0] * full[a, 0] + n[1] * full[a, 1] + n[2] * full[a, 2])
            r = n[0] * p[:, 0] + n[1] * p[:, 1] + n[2] * p[:, 2] + d
            hits = np.abs(r) <= distance
            count = 0
            for start in range(0, len(p), 256):
                count += int(np.count_nonzero(hits[start:start + 256]))
                done = min(len(p), start + 256)
                if count + (len(p) - done) <= best[1]:
                    count = -1
                    break
                if best[1] > 0:
                    w = best[1] / len(p)
                    if count < done * w - bail_sigmas * math.sqrt(done * w * (1 - w)) - 1:
                        count = -1
                        break
            if count > best[1]:
                best = (t, count, n, d)
                w3 = (count / len(p)) ** 3
                if w3 >= 1.0:
                    needed = 0.0
                elif confidence < 1.0:
                    needed = math.log(1.0 - confidence) / math.log(1.0 - w3)
        if tried >= needed:
            break
    return best + (tried,)


def plane_scene(n_plane=3000, n_clutter=1500, normal=(0.1, -0.9, -0.4), offset=1.0, noise=0.003,
                rng=None):
    rng = RNG if rng is None else rng
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    basis = np.linalg.svd(normal[None, :])[2][1:]
    coords = rng.uniform(-1.5, 1.5, size=(n_plane, 2))
    on = coords @ basis - offset * normal + rng.normal(0, noise, (n_plane, 1)) * normal
    clutter = rng.uniform(-1.5, 1.5, size=(n_clutter, 3)) + [0, 0, 3]
    points = np.concatenate([on, clutter]).astype(np.float32)
    truth = np.zeros(len(points), bool)
    truth[:n_plane] = True
    return points, truth, normal


@pytest.mark.parametrize("bail", [RANSAC_BAIL_SIGMAS, 0.0, math.inf])
@pytest.mark.parametrize("sample_size", [None, 1000])
@pytest.mark.parametrize("use_up", [False, True])
@pytest.mark.parametrize("confidence", [1.0, 0.999, 0.5])
def test_ransac_kernel_matches_twin(use_up, confidence, sample_size, bail):
    # the subsample cases draw from their own generator: the module RNG's sequence, which the
    # later tests' data depend on, stays as it was
    points, _, _ = plane_scene(1500, 3000, rng=np.random.default_rng(3) if sample_size else None)
    triples = np.random.default_rng(5).integers(0, len(points), size=(300, 3))
    triples[:3] = [[0, 0, 1], [4, 4, 4], [0, 1, 2]]  # degenerate ones are skipped
    up = np.array([0.0, -1.0, 0.0]) if use_up else np.zeros(3)
    cos_min = math.cos(math.radians(30)) if use_up else 0.0
    sample = ransac_sample(len(points), sample_size or len(points))
    if sample_size:
        assert len(sample) == sample_size and len(np.unique(sample)) == sample_size
    else:
        np.testing.assert_array_equal(np.sort(sample), np.arange(len(points)))
    t, count, n, d, tried = _ransac_kernel(points, sample, triples, 0.01, up, cos_min,
                                           confidence, bail)
    wt, wcount, wn, wd, wtried = twin_ransac(points, triples, 0.01, up, cos_min, confidence,
                                             sample, bail)
    assert (t, count, tried) == (wt, wcount, wtried) and t >= 0
    np.testing.assert_array_equal(n, wn)
    assert d == wd
    if confidence == 1.0:
        assert tried == 300
    elif confidence == 0.5:
        assert tried < 300  # the plane holds a third of the points: stops early


def test_fit_plane_finds_the_plane():
    points, truth, normal = plane_scene()
    plane = fit_plane_ransac(points, 0.01, 200, seed=1, min_inliers=100)
    assert plane.found
    assert abs(abs(plane.normal @ normal) - 1) < 1e-4
    assert abs(np.linalg.norm(plane.normal) - 1) < 1e-12
    assert plane.offset >= 0  # camera on the positive side
    assert abs(plane.offset - 1.0) < 2e-3
    assert plane.inliers.shape == truth.shape and plane.n_inliers == plane.inliers.sum()
    assert plane.inliers[truth].mean() > 0.99
    assert plane.inliers[~truth].mean() < 0.05
    np.testing.assert_allclose(np.abs(plane.distances(points[truth])), 0, atol=0.012)
    # same seed, same plane
    again = fit_plane_ransac(points, 0.01, 200, seed=1, min_inliers=100)
    np.testing.assert_array_equal(again.inliers, plane.inliers)
    assert again.offset == plane.offset


def test_fit_plane_uses_the_triples_drawn_from_the_seed():
    points, _, _ = plane_scene(400, 800)
    plane = fit_plane_ransac(points, 0.01, 50, seed=9)
    triples = ransac_triples(len(points), 50, 9)
    t, count, n, d, tried = twin_ransac(points, triples, 0.01, np.zeros(3), 0.0, 0.999,
                                        ransac_sample(len(points)))
    assert t >= 0 and plane.iterations == tried
    # the refit may only gain inliers over the best triple's plane
    assert plane.n_inliers >= count


def test_fit_plane_scores_on_the_subsample():
    """A cloud larger than RANSAC_SAMPLE: triples scored on ransac_sample, the winner counted
    on every point (twins of the inlier and scatter kernels included)."""
    points, truth, normal = plane_scene(9000, 6000, rng=np.random.default_rng(12))
    assert len(points) > RANSAC_SAMPLE
    sample = ransac_sample(len(points))
    assert len(sample) == RANSAC_SAMPLE and len(np.unique(sample)) == RANSAC_SAMPLE
    np.testing.assert_array_equal(np.sort(sample), np.arange(RANSAC_SAMPLE) * len(points)
                                  // RANSAC_SAMPLE)
    plane = fit_plane_ransac(points, 0.01, 200, seed=2, min_inliers=100)
    triples = ransac_triples(len(points), 200, 2)
    t, count, n, d, tried = twin_ransac(points, triples, 0.01, np.zeros(3), 0.0, 0.999, sample)
    assert t >= 0 and plane.iterations == tried
    p = points.astype(np.float64)
    want = np.abs(n[0] * p[:, 0] + n[1] * p[:, 1] + n[2] * p[:, 2] + d) <= 0.01
    got, got_count = _plane_inliers(points, n, d, 0.01)
    np.testing.assert_array_equal(got, want)
    assert got_count == want.sum() and plane.n_inliers >= got_count
    # scatter kernel: sequential sums (cumsum is sequential), centred products
    centroid, scatter = _inlier_scatter(points, want, int(want.sum()))
    on = p[want]
    want_centroid = np.array([np.cumsum(on[:, j])[-1] for j in range(3)]) / len(on)
    np.testing.assert_array_equal(centroid, want_centroid)
    c = on - want_centroid
    want_scatter = np.array([[np.cumsum(c[:, i] * c[:, j])[-1] for j in range(3)]
                             for i in range(3)])
    np.testing.assert_array_equal(scatter, want_scatter)
    assert plane.inliers[truth].mean() > 0.99 and plane.inliers[~truth].mean() < 0.05
    assert abs(abs(plane.normal @ normal) - 1) < 1e-4


def test_up_constraint_picks_the_floor_over_a_bigger_wall():
    wall, wall_truth, _ = plane_scene(4000, 0, normal=(0, 0, -1), offset=3.0)
    floor, floor_truth, _ = plane_scene(2000, 0, normal=(0, -1, 0), offset=1.2)
    points = np.concatenate([wall, floor])
    free = fit_plane_ransac(points, 0.01, 200, seed=0)
    assert free.inliers[:4000].mean() > 0.99 and free.inliers[4000:].mean() < 0.05
    assert np.allclose(free.normal, [0, 0, -1], atol=1e-3)  # camera (z = 0) on the + side
    level = fit_plane_ransac(points, 0.01, 200, seed=0, up=(0, -2, 0), max_tilt_deg=20)
    assert level.inliers[4000:].mean() > 0.99 and level.inliers[:4000].mean() < 0.05
    assert np.allclose(level.normal, [0, -1, 0], atol=1e-3)
    assert abs(level.offset - 1.2) < 2e-3
    # no plane within 20 degrees of "forward": none found
    none = fit_plane_ransac(floor, 0.01, 200, seed=0, up=(1, 0, 0), max_tilt_deg=20)
    assert not none.found and not none.inliers.any()


def test_no_plane_cases():
    for n in (0, 1, 2):
        plane = fit_plane_ransac(np.zeros((n, 3), np.float32), 0.01, 10, 0)
        assert not plane.found and plane.inliers.shape == (n,) and np.isnan(plane.offset)
    same = np.ones((50, 3), np.float32)  # every triple degenerate
    assert not fit_plane_ransac(same, 0.01, 100, 0).found
    line = np.column_stack([np.arange(50), np.zeros(50), np.ones(50)]).astype(np.float32)
    assert not fit_plane_ransac(line, 0.01, 100, 0).found
    points, _, _ = plane_scene(300, 300)
    assert not fit_plane_ransac(points, 0.01, 100, 0, min_inliers=400).found
    assert fit_plane_ransac(points, 0.01, 100, 0, min_inliers=250).found
    assert Plane.none(4).n_inliers == 0


def test_ransac_triples_are_distinct_and_uniform():
    triples = ransac_triples(5, 20000, 4)
    assert triples.dtype == np.int64 and triples.shape == (20000, 3)
    assert triples.min() == 0 and triples.max() == 4
    assert np.all((triples[:, 0] != triples[:, 1]) & (triples[:, 0] != triples[:, 2])
                  & (triples[:, 1] != triples[:, 2]))
    # 60 ordered triples, each about equally often
    codes = triples @ [25, 5, 1]
    freq = np.bincount(codes, minlength=125)[np.unique(codes)]
    assert len(freq) == 60 and freq.min() > 250 and freq.max() < 420
    np.testing.assert_array_equal(ransac_triples(5, 10, 4), triples[:10])
    assert ransac_triples(3, 30, 0).tolist() == ransac_triples(3, 30, 0).tolist()


def test_three_points_make_a_plane():
    points = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1]], np.float32)
    plane = fit_plane_ransac(points, 0.001, 5, 0)
    assert plane.n_inliers == 3
    np.testing.assert_allclose(plane.normal, [0, 0, -1], atol=1e-12)
    assert abs(plane.offset - 1.0) < 1e-7


def test_remove_plane():
    points, truth, _ = plane_scene()
    rest, plane = remove_plane(points, 0.01, 200, 3, min_inliers=100)
    assert rest.dtype == np.float32
    assert len(rest) == len(points) - plane.n_inliers
    np.testing.assert_array_equal(rest, points[~plane.inliers])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(distance_m=0.0), "distance_m"),
        (dict(iterations=0), "iterations"),
        (dict(iterations=10.5), "iterations"),
        (dict(seed=-1), "seed"),
        (dict(min_inliers=0), "min_inliers"),
        (dict(up=(0, -1, 0)), "both"),
        (dict(max_tilt_deg=10), "both"),
        (dict(up=(0, 0, 0), max_tilt_deg=10), "up="),
        (dict(up=(0, 1), max_tilt_deg=10), "up="),
        (dict(up=(0, -1, 0), max_tilt_deg=95), "max_tilt_deg"),
        (dict(confidence=0.0), "confidence"),
        (dict(confidence=1.5), "confidence"),
        (dict(bail_sigmas=-1.0), "bail_sigmas"),
        (dict(bail_sigmas=float("nan")), "bail_sigmas"),
    ],
)
def test_fit_plane_rejects_bad_parameters(kwargs, message):
    points, _, _ = plane_scene(100, 10)
    args = dict(points=points, distance_m=0.01, iterations=10, seed=0)
    args.update(kwargs)
    with pytest.raises(InputError, match=message):
        fit_plane_ransac(**args)


def test_fit_plane_rejects_bad_points():
    with pytest.raises(InputError, match="NaN"):
        fit_plane_ransac(np.full((5, 3), np.nan, np.float32), 0.01, 10, 0)
    with pytest.raises(InputError, match="float32"):
        fit_plane_ransac(np.zeros((5, 3)), 0.01, 10, 0)


# --------------------------------------------------------------------------------------------
# temporal fusion


def twin_fuse(stack, min_valid):
    n, height, width = stack.shape
    flat = stack.reshape(n, -1).T.astype(np.int64)
    out = np.zeros(height * width, np.int64)
    for i, values in enumerate(flat):
        valid = np.sort(values[values > 0])
        c = len(valid)
        if c >= min_valid and c > 0:
            if c % 2:
                out[i] = valid[c // 2]
            else:
                out[i] = (valid[c // 2 - 1] + valid[c // 2]) // 2
                # np.median agrees up to the integer rounding
                assert abs(np.median(valid) - out[i]) <= 0.5
    return out.reshape(height, width).astype(np.uint16)


@pytest.mark.parametrize(
    "n, min_valid", [(1, 1), (2, 1), (2, 2), (3, 1), (3, 2), (4, 3), (7, 1), (7, 3), (7, 7)]
)
def test_fuse_depth_matches_twin(n, min_valid):
    stack = RNG.integers(0, 65536, size=(n, 30, 40)).astype(np.uint16)
    stack[RNG.random(stack.shape) < 0.35] = 0
    stack[:, 0, :] = 65535  # (a + b) // 2 must not overflow
    got = fuse_depth(stack, min_valid)
    assert got.dtype == np.uint16 and got.shape == (30, 40)
    np.testing.assert_array_equal(got, twin_fuse(stack, min_valid))


def test_fuse_depth_known_values():
    stack = np.array([[[0, 1000, 5, 7]], [[0, 1003, 0, 8]], [[0, 0, 0, 100]]], np.uint16)
    np.testing.assert_array_equal(fuse_depth(stack, 1), [[0, 1001, 5, 8]])
    np.testing.assert_array_equal(fuse_depth(stack, 2), [[0, 1001, 0, 8]])
    np.testing.assert_array_equal(fuse_depth(stack, 3), [[0, 0, 0, 8]])


@pytest.mark.parametrize(
    "stack, min_valid, message",
    [
        (np.zeros((3, 4, 5), np.float32), 1, "uint16"),
        (np.zeros((4, 5), np.uint16), 1, r"\(N, H, W\)"),
        (np.zeros((0, 4, 5), np.uint16), 1, "no frames"),
        (np.zeros((3, 4, 5), np.uint16), 0, "min_valid"),
        (np.zeros((3, 4, 5), np.uint16), 4, "min_valid"),
        ("frames", 1, "uint16"),
    ],
)
def test_fuse_depth_rejects_bad_input(stack, min_valid, message):
    with pytest.raises(InputError, match=message):
        fuse_depth(stack, min_valid)


@pytest.mark.parametrize("m, iterations, seed", [(3, 50, 0), (7, 200, 3), (35_000, 1000, 0)])
def test_ransac_triples_match_twin(m, iterations, seed):
    """The numba triple kernel against NumPy: scaled uniforms, then the shifts past the rows
    already taken."""
    u = np.random.default_rng(seed).random((iterations, 3))
    a = np.minimum(np.floor(u[:, 0] * m).astype(np.int64), m - 1)
    b = np.minimum(np.floor(u[:, 1] * (m - 1)).astype(np.int64), m - 2)
    c = np.minimum(np.floor(u[:, 2] * (m - 2)).astype(np.int64), m - 3)
    b = b + (b >= a)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    c = c + (c >= lo)
    c = c + (c >= hi)
    np.testing.assert_array_equal(ransac_triples(m, iterations, seed), np.stack([a, b, c], 1))
