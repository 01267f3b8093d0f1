"""Tests of robot_change.change.scene: building a SceneModel, its file, and compatibility checks.

Builds are ~0.1 s each; the sim scene's models are built once per module.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import zipfile

import numpy as np
import pytest
from conftest import SIM_FIXTURES

import robot_change
from hw.depth import DepthFrame, DepthSource, Intrinsics, open_depth
from robot_change.change.scene import (
    FILE_FORMAT,
    FILE_VERSION,
    SceneModel,
    SceneParams,
    build_scene,
    build_scene_from_source,
    check_compatible,
    scene_differences,
)
from robot_change.cloud.chain import PIXEL_KEPT, CloudParams
from robot_change.errors import (
    EmptySceneError,
    InputError,
    MixtureFileError,
    SceneFileError,
    SceneMismatchError,
)
from robot_change.mixture.model import Mixture
from robot_change.npzfile import checksum as _checksum
from sim_fixtures import load_scene

ARRAYS = ("depth", "points", "keys", "counts", "pixel_voxel", "pixel_stage", "plane_normal",
          "plane_inliers", "weights", "means", "covariances")


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def sim():
    return load_scene("office_box_added")


@pytest.fixture(scope="module")
def ref_frames(sim):
    return [DepthFrame(d, 1_000_000 + 33_333 * i, 10 + i, sim.intrinsics)
            for i, d in enumerate(sim.reference_frames())]


@pytest.fixture(scope="module")
def ref_model(ref_frames):
    return build_scene(ref_frames, source="test:reference")


@pytest.fixture(scope="module")
def cur_model(sim):
    return build_scene(np.stack(sim.current_frames()), intrinsics=sim.intrinsics)


@pytest.fixture(scope="module")
def saved(ref_model, tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "reference.npz"
    ref_model.save(path)
    return path


def read_npz(path):
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: np.array(data[k]) for k in data.files}
    header = json.loads(str(arrays.pop("header")[()]))
    return header, arrays


def write_npz(path, header, arrays, *, rehash=False):
    """``rehash``: as a crafter who knows the format would, declare the arrays as they are and
    recompute the checksum."""
    if rehash:
        header = dict(header, arrays={k: [a.dtype.str, list(a.shape)] for k, a in arrays.items()})
        header["sha256"] = _checksum(header, arrays)
    np.savez_compressed(path, header=np.array(json.dumps(header)), **arrays)


# ----------------------------------------------------------------------------- building


def test_build_from_depth_frames(ref_model, sim):
    m = ref_model
    assert m.depth.shape == (480, 640) and m.depth.dtype == np.uint16
    assert not m.depth.flags.writeable
    assert m.intrinsics == sim.intrinsics
    assert m.n_frames == 3
    assert (m.first_timestamp_us, m.last_timestamp_us) == (1_000_000, 1_066_666)
    assert (m.first_index, m.last_index) == (10, 12)
    assert m.points is m.cloud.points and m.points.dtype == np.float32
    assert m.points.shape[1] == 3 and len(m) == m.points.shape[0] > 5000
    assert m.pixel_voxel.shape == (480, 640) and m.pixel_voxel.dtype == np.int32
    assert m.mixture.n_components >= 2 and m.mixture.record.n_points == len(m)
    assert m.mixture.record.reg_covar == pytest.approx(m.params.cloud.leaf_m**2 / 12)
    # the defaults, with the camera's near range (unset: the Kinect's 0.4 m) recorded
    assert m.params == SceneParams(cloud=CloudParams(min_depth_m=0.4))
    assert set(m.seconds) == {"fusion", "voxel", "outliers", "plane", "cloud", "fit",
                              "total"}
    assert all(v >= 0 for v in m.seconds.values())
    assert m.seconds["total"] >= m.seconds["fit"] + m.seconds["cloud"]
    assert m.version == robot_change.__version__ and m.source == "test:reference"
    created = datetime.datetime.fromisoformat(m.created)
    assert created.utcoffset() == datetime.timedelta(0)
    assert abs((datetime.datetime.now(datetime.UTC) - created).total_seconds()) < 600


def test_pixel_voxel_maps_depth_pixels_to_their_points(ref_model):
    m, cam = ref_model, ref_model.intrinsics
    v, u = np.nonzero(m.pixel_voxel >= 0)
    assert len(v) > 10_000
    assert (m.depth[v, u] > 0).all()
    assert (m.cloud.pixel_stage[v, u] == PIXEL_KEPT).all()
    z = m.depth[v, u] / 1000.0
    p = np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z], axis=1)
    gap = np.linalg.norm(p - m.points[m.pixel_voxel[v, u]], axis=1)
    assert gap.max() <= m.params.cloud.leaf_m * np.sqrt(3) + 1e-6  # in its voxel, as the centroid
    assert np.isin(np.arange(len(m)), m.pixel_voxel[v, u]).all()  # every point has pixels


def test_build_from_arrays_equals_build_from_frames(ref_model, sim):
    stack = np.stack(sim.reference_frames())
    for frames in (stack, list(stack)):
        m = build_scene(frames, intrinsics=sim.intrinsics)
        np.testing.assert_array_equal(m.depth, ref_model.depth)
        np.testing.assert_array_equal(m.points, ref_model.points)
        np.testing.assert_array_equal(m.mixture.means, ref_model.mixture.means)
        assert m.n_frames == 3 and m.first_timestamp_us is None and m.last_index is None
        assert m.source == ""


def test_single_frame_is_not_fused_away(sim):
    frame = sim.reference_frames()[0]
    m = build_scene(frame, SceneParams(max_components=2), intrinsics=sim.intrinsics)
    assert m.n_frames == 1
    np.testing.assert_array_equal(m.depth, frame)
    assert m.depth is not frame and frame.flags.writeable  # a copy; the caller's is untouched


def test_fusion_lowers_noise(ref_model, cur_model, sim):
    """Fused reference and current agree better on unchanged pixels than single frames do."""
    same = ~sim.truth_appeared & ~sim.truth_disappeared

    def disagreement(a, b):
        ok = same & (a > 0) & (b > 0)
        return np.abs(a[ok].astype(np.float64) - b[ok]).mean()

    single = disagreement(sim.reference_frames()[0], sim.current_frames()[0])
    fused = disagreement(ref_model.depth, cur_model.depth)
    assert fused < 0.8 * single  # measured: 11.6 vs 17.2 mm


def test_min_valid_fraction_sets_how_many_readings_a_pixel_needs(sim):
    stack = np.stack(sim.reference_frames())
    union = build_scene(stack, SceneParams(min_valid_fraction=0.2, max_components=1),
                        intrinsics=sim.intrinsics)
    every = build_scene(stack, SceneParams(min_valid_fraction=1.0, max_components=1),
                        intrinsics=sim.intrinsics)
    np.testing.assert_array_equal(union.depth > 0, (stack > 0).any(axis=0))
    np.testing.assert_array_equal(every.depth > 0, (stack > 0).all(axis=0))
    assert np.count_nonzero(union.depth) > max(np.count_nonzero(f) for f in stack)
    assert SceneParams().min_valid(3) == 2 and SceneParams().min_valid(1) == 1
    assert SceneParams(min_valid_fraction=0.3).min_valid(10) == 3
    assert SceneParams(min_valid_fraction=1.0).min_valid(4) == 4


def test_params_reach_the_cloud_and_the_fit(sim):
    params = SceneParams(cloud=CloudParams(leaf_m=0.04), criterion="bic", max_components=3)
    m = build_scene(sim.reference_frames()[0], params, intrinsics=sim.intrinsics)
    assert m.cloud.params.leaf_m == 0.04
    assert m.mixture.record.criterion == "bic" and m.mixture.n_components <= 3
    assert m.mixture.record.reg_covar == pytest.approx(0.04**2 / 12)


def test_intrinsics_override_those_of_the_frames(ref_frames, ref_model):
    cam = dataclasses.replace(ref_frames[0].intrinsics, fx=1050.0, fy=1050.0)
    m = build_scene(ref_frames[:1], SceneParams(max_components=1), intrinsics=cam)
    assert m.intrinsics == cam
    # twice the focal length: the same pixels land half as far from the optical axis
    assert np.abs(m.points[:, :2]).max() < 0.6 * np.abs(ref_model.points[:, :2]).max()


class ListSource(DepthSource):
    """A DepthSource over a list of frames (a finite recording)."""

    def __init__(self, frames, uri="list:test"):
        super().__init__()
        self.frames, self.uri, self.opened, self._i = list(frames), uri, 0, 0

    @property
    def intrinsics(self):
        return self.frames[0].intrinsics

    def open(self):
        self.opened += 1

    def close(self):
        pass

    def read(self, timeout=1.0):
        if self._i >= len(self.frames):
            return None
        self._i += 1
        return self.frames[self._i - 1]


def test_build_from_source_reads_n_frames(ref_frames, ref_model):
    source = ListSource(ref_frames)
    m = build_scene_from_source(source, n_frames=5)  # the recording holds 3
    assert source.opened == 1 and m.n_frames == 3 and m.source == "list:test"
    assert m.seconds["read"] >= 0 and m.last_index == 12
    np.testing.assert_array_equal(m.depth, ref_model.depth)
    with pytest.raises(InputError, match="no frame"):
        build_scene_from_source(ListSource([]), n_frames=2)
    with pytest.raises(InputError, match="n_frames"):
        build_scene_from_source(ListSource(ref_frames), n_frames=0)


def test_build_from_a_real_images_source(sim):
    uri = sim.uri("reference", "images")
    with open_depth(uri) as source:
        m = build_scene_from_source(source, n_frames=2,
                                    params=SceneParams(max_components=2))
    assert m.n_frames == 2 and m.source == uri and (m.first_index, m.last_index) == (0, 1)
    expect = build_scene(np.stack(sim.reference_frames()[:2]), SceneParams(max_components=2),
                         intrinsics=sim.intrinsics)
    np.testing.assert_array_equal(m.depth, expect.depth)


# ----------------------------------------------------------------------------- bad input


def test_frames_of_different_sizes_are_refused(sim):
    big = sim.reference_frames()[0]
    small = big[::2, ::2].copy()
    cam = sim.intrinsics
    frames = [DepthFrame(big, 0, 0, cam), DepthFrame(small, 1, 1, cam.scaled(320, 240))]
    with pytest.raises(InputError, match="frame 1 .*320x240"):
        build_scene(frames)
    with pytest.raises(InputError, match="frame 1 is 320x240"):
        build_scene([big, small], intrinsics=cam)


def test_frames_with_other_intrinsics_are_refused(sim):
    d = sim.reference_frames()[0]
    other = dataclasses.replace(sim.intrinsics, fx=530.0)
    frames = [DepthFrame(d, 0, 0, sim.intrinsics), DepthFrame(d, 1, 7, other)]
    with pytest.raises(InputError, match=r"frame 1 \(index 7\) has other intrinsics.*fx"):
        build_scene(frames)


@pytest.mark.parametrize("frames, intrinsics, match", [
    (np.zeros((480, 640), np.uint16), None, "need intrinsics"),
    (np.zeros((480, 640), np.uint16), Intrinsics.openni_default(320, 240), "640x480 but"),
    (np.zeros((480, 640), np.float32), Intrinsics.openni_default(), "uint16"),
    (np.zeros((2, 2, 480, 640), np.uint16), Intrinsics.openni_default(), "uint16"),
    (np.zeros((0, 480, 640), np.uint16), Intrinsics.openni_default(), "no frame"),
    ([], Intrinsics.openni_default(), "empty"),
    ([np.zeros((480, 640), np.int32)], Intrinsics.openni_default(), "frame 0 must be"),
    (42, None, "sequence"),
])
def test_bad_frames_are_refused(frames, intrinsics, match):
    with pytest.raises(InputError, match=match):
        build_scene(frames, intrinsics=intrinsics)


def test_mixed_frames_are_refused(sim):
    d = sim.reference_frames()[0]
    with pytest.raises(InputError, match="mixes"):
        build_scene([DepthFrame(d, 0, 0, sim.intrinsics), d])


def floor_only(cam: Intrinsics) -> np.ndarray:
    """(H, W) uint16 depth of a flat floor 1 m below a camera pitched down 30 degrees."""
    v = np.mgrid[0:cam.height, 0:cam.width][0].astype(np.float64)
    dy = (v - cam.cy) / cam.fy
    down = dy * np.cos(np.radians(30)) + np.sin(np.radians(30))
    z = np.where(down > 0, 1.0 / np.maximum(down, 1e-9), 0.0)
    return np.where((down > 0) & (z < 10), np.round(z * 1000), 0).astype(np.uint16)


@pytest.mark.parametrize("depth, match", [
    (np.zeros((480, 640), np.uint16), "covered"),
    (np.full((480, 640), 8000, np.uint16), "beyond the maximum depth"),
    (np.full((480, 640), 200, np.uint16), "right in front"),
    ("floor", "only the floor"),
])
def test_empty_scene_says_what_to_check(depth, match):
    cam = Intrinsics.openni_default()
    depth = floor_only(cam) if isinstance(depth, str) else depth
    with pytest.raises(EmptySceneError, match=match) as info:
        build_scene(depth, intrinsics=cam)
    assert isinstance(info.value, InputError)


def test_empty_after_fusion_blames_motion():
    cam = Intrinsics.openni_default()
    stack = np.zeros((2, 480, 640), np.uint16)
    stack[0, :, :320] = 2000
    stack[1, :, 320:] = 2000
    with pytest.raises(EmptySceneError, match="move"):
        build_scene(stack, SceneParams(min_valid_fraction=1.0), intrinsics=cam)


@pytest.mark.parametrize("field, value", [
    ("cloud", {"leaf_m": 0.02}), ("criterion", "mml"), ("max_components", 0),
    ("max_components", 2.5), ("tol", -1.0), ("tol", float("nan")), ("max_iter", 0),
    ("seed", -1), ("search_points", 50), ("min_valid_fraction", 0.0),
    ("min_valid_fraction", 1.5), ("min_valid_fraction", True),
])
def test_scene_params_are_validated(field, value):
    with pytest.raises(InputError, match=f"SceneParams.{field}="):
        SceneParams(**{field: value})


def test_scene_params_dict_round_trip():
    p = SceneParams(cloud=CloudParams(leaf_m=0.03, plane_up=(0, -1, 0), plane_max_tilt_deg=15),
                    criterion="aic", max_components=7, search_points=None,
                    min_valid_fraction=0.75)
    d = json.loads(json.dumps(p.to_dict()))
    assert SceneParams.from_dict(d) == p
    assert SceneParams.from_dict({}) == SceneParams()
    with pytest.raises(InputError, match="unknown scene parameters.*cloud.leaf"):
        SceneParams.from_dict({"cloud": {"leaf": 0.02}})
    with pytest.raises(InputError, match="CloudParams.leaf_m"):
        SceneParams.from_dict({"cloud": {"leaf_m": -1}})


# ----------------------------------------------------------------------------- files


def test_save_load_round_trip(ref_model, saved):
    m = SceneModel.load(saved)
    for name in ("depth", "points", "keys", "counts", "pixel_voxel", "pixel_stage"):
        a = getattr(m, name) if name == "depth" else getattr(m.cloud, name)
        b = getattr(ref_model, name) if name == "depth" else getattr(ref_model.cloud, name)
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    for name in ("weights", "means", "covariances"):
        np.testing.assert_array_equal(getattr(m.mixture, name), getattr(ref_model.mixture, name))
    assert m.mixture.record == ref_model.mixture.record
    np.testing.assert_array_equal(m.cloud.plane.normal, ref_model.cloud.plane.normal)
    np.testing.assert_array_equal(m.cloud.plane.inliers, ref_model.cloud.plane.inliers)
    assert m.cloud.plane.offset == ref_model.cloud.plane.offset
    assert m.cloud.stage_counts == ref_model.cloud.stage_counts
    assert m.cloud.timings_ms == ref_model.cloud.timings_ms
    assert m.params == ref_model.params and m.cloud.params == ref_model.params.cloud
    assert m.intrinsics == ref_model.intrinsics
    for name in ("n_frames", "first_timestamp_us", "last_timestamp_us", "first_index",
                 "last_index", "seconds", "created", "version", "source"):
        assert getattr(m, name) == getattr(ref_model, name), name
    assert not m.depth.flags.writeable and not m.points.flags.writeable
    check_compatible(ref_model, m)


def test_format_1_file_loads_with_its_cloud_rebuilt(tmp_path):
    """A reference saved before the key layout change (format 1: keys packed x, y, z from the
    top) still loads: the cloud is rebuilt from its depth image with the current layout, the
    mixture is the stored one, and saving it again writes the current format."""
    from robot_change.cloud.voxels import KEY_BITS, unpack_keys

    legacy = SIM_FIXTURES / "legacy" / "office_reference_v1.npz"
    header, arrays = read_npz(legacy)
    assert header["version"] == 1
    m = SceneModel.load(legacy)
    np.testing.assert_array_equal(m.mixture.means, arrays["means"])
    np.testing.assert_array_equal(m.depth, arrays["depth"])
    # every kept pixel lies in the voxel its point's key names (current layout)
    leaf = m.params.cloud.leaf_m
    rows = m.cloud.pixel_voxel.ravel()
    v, u = np.divmod(np.flatnonzero(rows >= 0), m.depth.shape[1])
    z = m.depth.ravel()[rows >= 0] / 1000.0
    own = np.stack([(u - m.intrinsics.cx) / m.intrinsics.fx * z,
                    (v - m.intrinsics.cy) / m.intrinsics.fy * z, z], axis=1).astype(np.float32)
    np.testing.assert_array_equal(np.floor(own.astype(np.float64) / leaf).astype(np.int64),
                                  unpack_keys(m.cloud.keys[rows[rows >= 0]]))
    assert np.all(np.diff(m.cloud.keys) > 0)
    # the same voxels as the stored cloud, whose keys read with the old layout
    field = (1 << KEY_BITS) - 1
    old = arrays["keys"]
    old_idx = np.stack([(old >> (2 * KEY_BITS)) & field, (old >> KEY_BITS) & field,
                        old & field], axis=1) - (1 << (KEY_BITS - 1))
    stored = set(map(tuple, old_idx.tolist()))
    rebuilt = set(map(tuple, unpack_keys(m.cloud.keys).tolist()))
    assert len(stored & rebuilt) >= 0.99 * max(len(stored), len(rebuilt))
    m.save(tmp_path / "again.npz")
    assert read_npz(tmp_path / "again.npz")[0]["version"] == FILE_VERSION
    np.testing.assert_array_equal(SceneModel.load(tmp_path / "again.npz").cloud.keys,
                                  m.cloud.keys)


def test_file_is_a_plain_npz_with_a_json_header(saved, ref_model):
    header, arrays = read_npz(saved)  # loads with allow_pickle=False: nothing pickled inside
    assert header["format"] == FILE_FORMAT and header["version"] == FILE_VERSION
    assert header["library_version"] == robot_change.__version__
    assert header["params"] == ref_model.params.to_dict()
    assert header["intrinsics"]["fx"] == ref_model.intrinsics.fx
    assert set(arrays) == set(ARRAYS)
    assert header["sha256"] == _checksum(header, arrays)
    with zipfile.ZipFile(saved) as z:
        assert all(i.compress_type == zipfile.ZIP_DEFLATED for i in z.infolist())


def test_save_is_atomic_and_replaces(ref_model, tmp_path):
    path = tmp_path / "ref.npz"
    path.write_bytes(b"old")
    ref_model.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ["ref.npz"]  # no temp file left
    assert SceneModel.load(path).n_frames == 3
    with pytest.raises(OSError):
        ref_model.save(tmp_path / "missing-folder" / "ref.npz")
    assert [p.name for p in tmp_path.iterdir()] == ["ref.npz"]


@pytest.mark.parametrize("cut", [0.5, 0.9, 100, 10])
def test_truncated_file_is_refused(saved, tmp_path, cut):
    data = saved.read_bytes()
    bad = tmp_path / "truncated.npz"
    bad.write_bytes(data[: int(len(data) * cut) if cut < 1 else cut])
    with pytest.raises(SceneFileError, match="truncated.npz.*build and save the reference"):
        SceneModel.load(bad)


@pytest.mark.parametrize("content", [b"", b"hello, not a scene\n", bytes(range(256)) * 40])
def test_garbage_is_refused(tmp_path, content):
    bad = tmp_path / "garbage.npz"
    bad.write_bytes(content)
    with pytest.raises(SceneFileError, match="garbage.npz"):
        SceneModel.load(bad)


def test_missing_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        SceneModel.load(tmp_path / "nope.npz")


def test_other_formats_are_refused(tmp_path, ref_model):
    mix = tmp_path / "mixture.npz"
    ref_model.mixture.save(mix)
    with pytest.raises(SceneFileError, match="'robot_change.mixture' is not 'robot_change.scene'"):
        SceneModel.load(mix)
    with pytest.raises(MixtureFileError):  # and the other way round
        scene = tmp_path / "scene.npz"
        ref_model.save(scene)
        Mixture.load(scene)
    plain = tmp_path / "plain.npz"
    np.savez(plain, depth=np.zeros((4, 4), np.uint16))
    with pytest.raises(SceneFileError, match="no header"):
        SceneModel.load(plain)
    npy = tmp_path / "array.npy"
    np.save(npy, np.zeros(3))
    with pytest.raises(SceneFileError, match="single .npy"):
        SceneModel.load(npy)


def test_newer_version_is_refused_naming_the_version(saved, tmp_path):
    header, arrays = read_npz(saved)
    header.update(version=FILE_VERSION + 1, library_version="9.4")
    newer = tmp_path / "newer.npz"
    write_npz(newer, header, arrays, rehash=True)
    with pytest.raises(SceneFileError, match=r"made by robot_change 9\.4.*upgrade"):
        SceneModel.load(newer)


def test_tampered_arrays_or_header_fail_the_checksum(saved, tmp_path):
    header, arrays = read_npz(saved)
    arrays["depth"][240, 320] += 1
    bad = tmp_path / "tampered.npz"
    write_npz(bad, header, arrays)
    with pytest.raises(SceneFileError, match="checksum mismatch"):
        SceneModel.load(bad)
    header, arrays = read_npz(saved)
    header["params"]["cloud"]["leaf_m"] = 0.05
    write_npz(bad, header, arrays)
    with pytest.raises(SceneFileError, match="checksum mismatch"):
        SceneModel.load(bad)


def test_missing_array_is_refused(saved, tmp_path):
    header, arrays = read_npz(saved)
    del arrays["pixel_voxel"]
    bad = tmp_path / "missing.npz"
    write_npz(bad, header, arrays)
    with pytest.raises(SceneFileError, match=r"\['pixel_voxel'\] are missing"):
        SceneModel.load(bad)


@pytest.mark.parametrize("edit, match", [
    (lambda h, a: h["params"]["cloud"].update(leaf_m=-1.0), "CloudParams.leaf_m"),
    (lambda h, a: h["params"].update(criterion="mml"), "SceneParams.criterion"),
    (lambda h, a: h["intrinsics"].update(fx=-5.0), "fx"),
    (lambda h, a: a.update(points=a["points"].astype(np.float64)), "'points' is float64"),
    (lambda h, a: a.update(pixel_voxel=a["pixel_voxel"] + 10**6), "outside the cloud"),
    (lambda h, a: a.update(weights=a["weights"] * 2), "valid scene"),
    (lambda h, a: h.pop("n_frames"), "n_frames"),
    (lambda h, a: h.update(drift="still"), "drift = 'still' is not a finite number"),
    (lambda h, a: h.update(drift=True), "drift = True"),
])
def test_invalid_content_with_a_valid_checksum_is_refused(saved, tmp_path, edit, match):
    header, arrays = read_npz(saved)
    edit(header, arrays)
    bad = tmp_path / "invalid.npz"
    write_npz(bad, header, arrays, rehash=True)
    with pytest.raises(SceneFileError, match=match):
        SceneModel.load(bad)


class _Boom:
    def __reduce__(self):
        return (open, (str(_Boom.target), "w"))


def test_pickled_arrays_are_never_executed(saved, tmp_path):
    header, arrays = read_npz(saved)
    _Boom.target = tmp_path / "executed"
    arrays["depth"] = np.array([_Boom()], dtype=object)
    bad = tmp_path / "pickled.npz"
    write_npz(bad, header, arrays)  # np.savez pickles object arrays
    assert b"'descr': '|O'" in zipfile.ZipFile(bad).read("depth.npy")[:128]  # a pickle inside
    with pytest.raises(SceneFileError):
        SceneModel.load(bad)
    assert not _Boom.target.exists()


# ----------------------------------------------------------------------------- compatibility


def test_compatible_scenes_pass(ref_model, cur_model):
    check_compatible(ref_model, cur_model)
    check_compatible(ref_model, (ref_model.intrinsics, SceneParams()))
    check_compatible(ref_model, (ref_model.intrinsics, CloudParams()))
    nudged = dataclasses.replace(ref_model.intrinsics, fx=ref_model.intrinsics.fx + 1e-4)
    check_compatible(ref_model, (nudged, SceneParams()))
    # search effort and the fit options do not change what a point means
    check_compatible(ref_model, (ref_model.intrinsics,
                                 SceneParams(CloudParams(plane_seed=5, plane_iterations=10),
                                             criterion="bic", max_components=3)))
    assert scene_differences(ref_model, cur_model) == ([], [])


def test_other_intrinsics_are_a_mismatch(ref_model):
    cam = dataclasses.replace(ref_model.intrinsics, fx=526.0, cy=240.0)
    with pytest.raises(SceneMismatchError, match=r"fx 525 vs 526.*cy 239.5 vs 240.*intrinsics "
                                                 r"525,525,319.5,239.5.*--intrinsics.*"
                                                 r"\?intrinsics=") as info:
        check_compatible(ref_model, (cam, SceneParams()))
    assert isinstance(info.value, InputError) and "recapture the reference" in str(info.value)
    with pytest.raises(SceneMismatchError, match="image size 640x480 vs 320x240"):
        check_compatible(ref_model, (ref_model.intrinsics.scaled(320, 240), SceneParams()))


def test_other_cloud_parameters_are_a_mismatch(ref_model, cur_model):
    leaf = ref_model.params.cloud.leaf_m
    other = dataclasses.replace(cur_model, params=SceneParams(CloudParams(leaf_m=0.05,
                                                                          max_depth_m=4.0)))
    with pytest.raises(SceneMismatchError, match=rf"leaf_m {leaf} vs 0.05; max_depth_m 5.0 vs "
                                                 r"4.0.*recapture the reference"):
        check_compatible(ref_model, other)
    up = CloudParams(plane_up=(0, -1, 0), plane_max_tilt_deg=15)
    with pytest.raises(SceneMismatchError, match="plane_up None vs"):
        check_compatible(ref_model, (ref_model.intrinsics, up))
    with pytest.raises(InputError, match="SceneModel or an"):
        check_compatible(ref_model, (ref_model.intrinsics, "leaf=0.02"))
