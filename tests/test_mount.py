"""The camera's mounting on the base (robot_change.change.mount): optical frame -> base_link
(REP 103), the robot's offset from its station pose, weak directions named in the base frame,
and the mounting recorded with a reference (SceneModel, ``capture --mount``, ``detect``)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from robot_change.change.mount import CameraMount
from robot_change.change.registration import Registration, invert, rpy_deg_to_rotation
from robot_change.change.scene import SceneModel, build_scene
from robot_change.errors import InputError, SceneFileError
from robot_change.npzfile import checksum
from sim_fixtures import load_scene

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "sim_fixtures" / "scenes"


def _pose(xyz, rpy_deg):
    T = np.eye(4)
    T[:3, :3] = rpy_deg_to_rotation(*rpy_deg)
    T[:3, 3] = xyz
    return T


def _registration(T, weak=()):
    return Registration(np.asarray(T, float), 1.0, 0.0, tuple(weak), np.ones(6), 0, 0, 0, True,
                        0.0)


def test_default_mount_maps_optical_axes_to_rep103():
    base = CameraMount().to_base(np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    # forward 2 m -> x 2; optical right -> -y (y is left); optical down -> -z
    np.testing.assert_allclose(base, [[2, 0, 0], [0, -1, 0], [0, 0, -1]], atol=1e-12)


def test_a_tilted_raised_camera():
    mount = CameraMount((0.2, 0.0, 0.45), (0.0, 10.0, 0.0))  # 10 deg pitch: nose down
    got = mount.to_base(np.array([[0.0, 0.0, 1.0]]))[0]
    a = math.radians(10.0)
    np.testing.assert_allclose(got, [0.2 + math.cos(a), 0.0, 0.45 - math.sin(a)], atol=1e-12)


@pytest.mark.parametrize("mount", [CameraMount(), CameraMount((0.25, -0.05, 0.6), (2, 15, -30))])
@pytest.mark.parametrize("motion", [((0.1, 0.0, 0.0), (0, 0, 5)), ((-0.03, 0.04, 0.0),
                                                                     (0.5, -1, -4))])
def test_offset_recovers_the_robots_motion_in_its_base_frame(mount, motion):
    """The robot now stands at ``motion`` in its station pose's base frame; the camera sees
    T_ref_from_cur = B^-1 M B; the offset must give back ``motion``."""
    M = _pose(*motion)
    B = mount.base_from_optical()
    offset = mount.offset(_registration(invert(B) @ M @ B))
    np.testing.assert_allclose(offset.translation_m, motion[0], atol=1e-9)
    np.testing.assert_allclose(offset.rpy_deg, motion[1], atol=1e-9)


def test_weak_directions_are_named_in_the_base_frame():
    # a bare wall ahead: sliding along it (optical x, y) and turning about the view axis
    offset = CameraMount().offset(_registration(np.eye(4), ("x", "y", "rot_z")))
    assert offset.weak == ("y", "z", "roll")
    assert CameraMount().offset(_registration(np.eye(4), ("rot_y",))).weak == ("yaw",)


def test_a_region_s_base_box_is_the_tight_box_of_its_points():
    """A box on the floor seen by a camera pitched 14 degrees down: the base_link box is that
    of its points (it was the box round the turned camera-frame box: 7 cm below the floor and
    12 cm over the object, ROS engineer's check), and holds every point."""
    from robot_change.change.results import Region

    mount = CameraMount((0.2, 0.0, 1.0), (0, 14, 0))
    rng = np.random.default_rng(1)
    in_base = np.column_stack([rng.uniform(2.0, 2.4, 300), rng.uniform(-0.2, 0.2, 300),
                               rng.uniform(0.0, 0.3, 300)])  # x ahead, y left, z up
    B = mount.base_from_optical()
    optical = ((in_base - B[:3, 3]) @ B[:3, :3]).astype(np.float32)
    lo, hi = optical.min(axis=0), optical.max(axis=0)
    region = Region("appeared", optical.mean(axis=0), hi - lo, lo, hi, 300, 300, (),
                    np.arange(300), optical)
    blo, bhi = region.base_box(mount)
    np.testing.assert_allclose(blo, in_base.min(axis=0), atol=1e-5)
    np.testing.assert_allclose(bhi, in_base.max(axis=0), atol=1e-5)
    base = region.to_dict(mount)["base"]
    assert base["bbox_min_m"][2] > -0.001 and base["bbox_max_m"][2] < 0.301


@pytest.mark.parametrize("text", ["", "1,2,3", "a,b,c,d,e,f", "0,0,0,0,0,nan", "0,0,0,0,0,0,0",
                                  "11,0,0,0,0,0", "0,0,0,0,181,0"])
def test_bad_mounts_are_typed_errors(text):
    with pytest.raises(InputError):
        CameraMount.parse(text)


# --------------------------------------------------------------------------- recorded mounting


@pytest.fixture(scope="module")
def frames():
    return load_scene("office_no_change").reference_frames()[:1]


def test_the_mounting_is_saved_with_the_reference(tmp_path, frames):
    mount = CameraMount((0.2, 0.0, 0.45), (0.0, 10.0, 0.0))
    intr = load_scene("office_no_change").intrinsics
    build_scene(frames, intrinsics=intr, mount=mount).save(tmp_path / "m.npz")
    assert SceneModel.load(tmp_path / "m.npz").mount == mount
    build_scene(frames, intrinsics=intr).save(tmp_path / "none.npz")
    assert SceneModel.load(tmp_path / "none.npz").mount is None


def _rewrite_header(src: Path, dst: Path, change) -> None:
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: np.array(data[k]) for k in data.files if k != "header"}
        header = json.loads(str(data["header"][()]))
    change(header)
    header["sha256"] = checksum(header, arrays)
    np.savez_compressed(dst, header=np.array(json.dumps(header, sort_keys=True)), **arrays)


def test_a_file_from_before_the_mounting_was_recorded_loads_without_one(tmp_path, frames):
    intr = load_scene("office_no_change").intrinsics
    build_scene(frames, intrinsics=intr, mount=CameraMount((0.1, 0, 0), (0, 0, 0))).save(
        tmp_path / "new.npz")
    _rewrite_header(tmp_path / "new.npz", tmp_path / "old.npz", lambda h: h.pop("mount"))
    assert SceneModel.load(tmp_path / "old.npz").mount is None
    _rewrite_header(tmp_path / "new.npz", tmp_path / "bad.npz",
                    lambda h: h.update(mount={"xyz_m": [0, 0], "rpy_deg": [0, 0, 0]}))
    with pytest.raises(SceneFileError, match="CameraMount.xyz_m"):
        SceneModel.load(tmp_path / "bad.npz")


def _cli(*args):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "robot_change.cli", *args], capture_output=True,
                          text=True, env=env, cwd=ROOT, timeout=300)


def test_a_summary_says_the_frame_of_its_base_figures():
    """The library's ChangeSet.summary() without a mounting labelled the zero mounting "in
    base_link" and summary(None) raised; now it says camera_link, as the CLI's report does."""
    from robot_change import build_scene, detect_changes
    from sim_fixtures import load_scene

    sc = load_scene("office_box_added")
    changes = detect_changes(build_scene(sc.reference_frames(), intrinsics=sc.intrinsics),
                             sc.current_frames()[0])
    bare = changes.summary()
    assert bare["base_frame"] == "camera_link" and bare["mount"] is None
    assert changes.summary(None) == bare
    mounted = changes.summary(CameraMount((0.2, 0.0, 0.45), (0.0, 10.0, 0.0)))
    assert mounted["base_frame"] == "base_link" and mounted["mount"]["xyz_m"] == [0.2, 0.0, 0.45]
    json.dumps(bare, allow_nan=False)


def test_capture_records_the_mounting_and_detect_uses_it(tmp_path):
    scene = SCENES / "office_box_added"
    saved = tmp_path / "ref.npz"
    result = _cli("capture", "--source", str(scene / "reference.oni"), "--out", str(saved),
                  "--frames", "3", "--mount", "0.2,0,0.45,0,10,0")
    assert result.returncode == 0, result.stderr
    assert "mount 0.2,0,0.45,0,10,0" in result.stdout
    result = _cli("detect", "--reference", str(saved), "--current", str(scene / "current.oni"),
                  "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["mount"]["xyz_m"] == [0.2, 0.0, 0.45]
    assert summary["mount"]["rpy_deg"] == [0.0, 10.0, 0.0]
    assert summary["base_frame"] == "base_link"
    assert "warning" not in result.stderr
    # the box about 2.2 m ahead of a camera 45 cm up, tilted down: in base_link it is ahead
    [region] = summary["regions"]
    assert region["base"]["centroid_m"][0] > 1.5
    # told otherwise: the option wins, with a warning naming both
    result = _cli("detect", "--reference", str(saved), "--current", str(scene / "current.oni"),
                  "--json", "--mount", "0,0,0,0,0,0")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["mount"]["xyz_m"] == [0.0, 0.0, 0.0]
    assert "warning" in result.stderr and "0.2,0,0.45,0,10,0" in result.stderr
    # no mounting anywhere: the same figures are in the camera's body frame, and say so
    result = _cli("detect", "--reference", str(scene / "reference.oni"), "--current",
                  str(scene / "current.oni"))
    assert result.returncode == 0, result.stderr
    assert "offset from the station pose (camera_link)" in result.stdout
    assert "up (camera_link)" in result.stdout and "base_link" not in result.stdout
    result = _cli("capture", "--source", str(scene / "reference.oni"), "--out",
                  str(tmp_path / "x.npz"), "--mount", "0,0,0")
    assert result.returncode == 2 and "six numbers" in result.stderr
    assert "Traceback" not in result.stderr
