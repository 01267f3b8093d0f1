"""A camera is read from its own near range: a RealSense D405 on a bench 0.2-0.38 m away is
captured and checked with the defaults, and a Kinect-class camera is read from 0.4 m as before
(robot_change.noise.profile.NoiseProfile.near_m, CloudParams.min_depth_m and
RegistrationParams.min_depth_m left unset)."""

from __future__ import annotations

import numpy as np
import pytest

from hw.depth import Intrinsics
from robot_change.change.detect import detect_changes
from robot_change.change.epoch import epoch_from_depth
from robot_change.change.registration import RegistrationParams, register_depth
from robot_change.change.scene import SceneModel, build_scene
from robot_change.cloud.chain import CloudParams
from robot_change.errors import EmptySceneError, InputError
from robot_change.noise.profile import BUILTIN, DEFAULT_NEAR_M, builtin_profile
from robot_change.service.config import config_from_dict

D405 = builtin_profile("realsense_d405")
#: 848 x 480 at 87 degrees across, as a D405's depth stream
_F = 424.0 / np.tan(np.radians(43.5))
CAMERA = Intrinsics(848, 480, _F, _F, 423.5, 239.5)


def _bench(box: bool, seed: int) -> np.ndarray:
    """(480, 848) uint16 mm: a bench tilted away from the camera (0.2-0.35 m) before a board
    at 0.38 m, with a 7 x 7 cm block standing 0.2 m from the camera when ``box``; 0.5 mm
    noise.  Every reading nearer than 0.4 m."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    y = (v - CAMERA.cy) / CAMERA.fy
    t = 0.25 / (0.8 * y + 0.6)  # the bench: the plane (0, -0.8, -0.6) . p = -0.25 m
    z = np.where((t <= 0) | (t > 0.35), 0.38, t)
    if box:
        z = np.where((u > 350) & (u < 500) & (v > 200) & (v < 330), np.minimum(z, 0.2), z)
    return np.round((z + rng.normal(0.0, 0.0005, z.shape)) * 1000).astype(np.uint16)


def test_each_camera_is_read_from_its_near_range_unless_told():
    near = {name: p.near_m for name, p in BUILTIN.items()}
    assert near == {"kinect_v1": 0.4, "xtion": 0.4, "orbbec_astra": 0.4, "azure_kinect": 0.4,
                    "realsense_d455": 0.4, "realsense_d415": 0.3, "realsense_d435": 0.3,
                    "realsense_d405": 0.07}
    assert DEFAULT_NEAR_M == 0.4
    assert CloudParams().min_depth_m is None and CloudParams().near_m() == 0.4
    assert CloudParams().near_m(D405) == 0.07
    assert CloudParams().for_camera(D405) == CloudParams(min_depth_m=0.07)
    told = CloudParams(min_depth_m=0.15)  # a gripper in view: the user's value holds
    assert told.near_m(D405) == 0.15 and told.for_camera(D405) is told
    with pytest.raises(InputError, match="max_depth_m=0.1"):
        CloudParams(min_depth_m=0.15, max_depth_m=0.1)
    assert RegistrationParams().near_m == 0.4
    assert RegistrationParams(noise=D405).near_m == 0.07
    assert RegistrationParams(min_depth_m=0.15, noise=D405).near_m == 0.15
    # a check registers what its reference's cloud reads: the camera's range, or the one set
    for cloud, near in ((CloudParams(), 0.07), (told, 0.15)):
        epoch = epoch_from_depth(_bench(False, 0), CAMERA, cloud, noise=D405)
        assert epoch.registration_params(RegistrationParams()).near_m == near


def test_a_close_range_station_is_captured_and_checked_with_the_defaults(tmp_path):
    reference = build_scene([_bench(False, s) for s in range(3)], intrinsics=CAMERA, noise=D405)
    assert reference.params.cloud.min_depth_m == 0.07  # recorded with the reference
    path = tmp_path / "bench.npz"
    reference.save(path)
    loaded = SceneModel.load(path)
    assert loaded.params.cloud.min_depth_m == 0.07
    quiet = detect_changes(loaded, _bench(False, 10), intrinsics=CAMERA)
    assert quiet.outcome == "no_change", quiet.summary()
    assert quiet.registration.fitness > 0.9
    found = detect_changes(loaded, _bench(True, 11), intrinsics=CAMERA)
    assert found.outcome == "changed"
    assert [r.kind for r in found.regions] == ["appeared"]
    centre = found.regions[0].centroid
    assert abs(centre[2] - 0.2) < 0.02  # the block's face, 0.2 m from the camera


def test_a_kinect_class_camera_is_still_read_from_0_4_m():
    frames = [_bench(False, s) for s in range(3)]
    with pytest.raises(EmptySceneError, match="nearer than min_depth_m = 0.4 m"):
        build_scene(frames, intrinsics=CAMERA, noise=builtin_profile("kinect_v1"))
    # the registration alike: named the D405, it pairs the bench; unnamed (a Kinect), nothing
    assert register_depth(frames[0], frames[1], CAMERA, noise=D405).n_pairs > 1000
    assert register_depth(frames[0], frames[1], CAMERA).n_pairs == 0


def test_the_configuration_leaves_the_near_range_to_the_camera_unless_set():
    assert config_from_dict({}).scene_params().cloud.min_depth_m is None
    told = config_from_dict({"cloud": {"min_depth_mm": 150}}).scene_params().cloud
    assert told.min_depth_m == 0.15
