"""The camera noise profile (robot_change.noise): the built-in figures, the kernels' reading of
it against their NumPy twins, files, the measurement of a still camera's frames, and the
profile a reference keeps."""

from __future__ import annotations

import json
import logging
import math

import numba
import numpy as np
import pytest
from scipy import ndimage

from hw.depth import Intrinsics
from robot_change.change.free_space import open_mask
from robot_change.change.scene import SceneModel, build_scene
from robot_change.errors import BadValue, InputError
from robot_change.noise.estimate import measure_frames, profile_from_frames
from robot_change.noise.kernels import (
    floored_margin_at,
    margin_at,
    sigma_at,
    table_sigma,
)
from robot_change.noise.profile import (
    BUILTIN,
    DEFAULT_PROFILE,
    RAISE_TOLERANCE,
    NoiseProfile,
    ProfileFileError,
    builtin_profile,
    resolve_profile,
)

KINECT = builtin_profile("kinect_v1")
CAMERA = Intrinsics(640, 480, 570.0, 570.0, 319.5, 239.5)


@numba.njit
def _sigmas(table, z):
    out = np.empty(z.shape[0])
    for i in range(z.shape[0]):
        out[i] = sigma_at(table, z[i])
    return out


@numba.njit
def _margins(table, z, k, pose, floor_m, floor_per_m2):
    out = np.empty((2, z.shape[0]))
    for i in range(z.shape[0]):
        out[0, i] = margin_at(table, z[i], k, pose)
        out[1, i] = floored_margin_at(table, z[i], k, floor_m, floor_per_m2)
    return out


def test_the_kernels_read_the_profile_as_its_numpy_twin_does():
    z = np.concatenate([np.linspace(0.0, 12.0, 997), [0.05, 3.0, 11.999, 12.0, 13.5, 20.0]])
    for profile in BUILTIN.values():
        table = profile.kernel_table()
        got = _sigmas(table, z)
        np.testing.assert_allclose(got, table_sigma(table, z), rtol=1e-12)
        inside = (z > 0.4) & (z <= 12.0)  # the table follows the profile's own sigma (within
        np.testing.assert_allclose(got[inside], profile.sigma(z[inside]), rtol=3e-3)  # 0.3 %:
        # linear between 5 cm samples, the D405's short baseline curves most, 0.27 % at 0.4 m)
        margins = _margins(table, z, 3.0, 0.01, 0.03, 0.004)
        s = table_sigma(table, z)
        np.testing.assert_allclose(margins[0], 3.0 * np.sqrt(2 * s * s + 1e-4), rtol=1e-12)
        np.testing.assert_allclose(margins[1], np.maximum(0.03 + 0.004 * z * z,
                                                          3.0 * math.sqrt(2.0) * s),
                                   rtol=1e-12)
        np.testing.assert_allclose(profile.margin(z[inside], 3.0, 0.01),
                                   margins[0][inside], rtol=2e-3)


def test_the_kinect_profile_is_the_published_noise():
    """Nguyen et al. 2012's axial noise with Khoshelham & Oude Elberink 2012's disparity step
    (2.85e-3 z^2) as a uniform error; 14 mm steps at 2.2 m and 35 mm at 3.5 m, as the real
    Xtion's study room shows (../shared/data/sun3d-studyroom-xtion-50f-pose)."""
    z = np.linspace(0.5, 5.0, 50)
    want = np.hypot(0.0012 + 0.0019 * (z - 0.4) ** 2, 2.85e-3 * z ** 2 / math.sqrt(12))
    np.testing.assert_allclose(KINECT.sigma(z), want, rtol=1e-12)
    assert KINECT.step(2.2) == pytest.approx(0.0138, abs=5e-4)
    assert KINECT.step(3.5) == pytest.approx(0.0349, abs=5e-4)
    assert DEFAULT_PROFILE == "kinect_v1"


def test_a_stereo_cameras_noise_grows_with_the_square_of_the_depth_and_a_tofs_does_not():
    for name in ("realsense_d405", "realsense_d415", "realsense_d435", "realsense_d455"):
        p = builtin_profile(name)
        assert p.principle == "stereo"
        assert p.sigma(4.0) / p.sigma(2.0) == pytest.approx(4.0, rel=0.05)
    d435, d455 = builtin_profile("realsense_d435"), builtin_profile("realsense_d455")
    assert d455.sigma(3.0) < d435.sigma(3.0)  # a longer baseline
    tof = builtin_profile("azure_kinect")
    assert tof.step_per_m == 0.0 and tof.shadow_baseline_m == 0.0
    assert tof.sigma(3.0) / tof.sigma(1.5) < 1.7  # not 4, as the square would give


def test_unknown_profiles_and_bad_fields_are_refused():
    with pytest.raises(BadValue, match="kinect_v1"):
        builtin_profile("kinect_v3")
    good = KINECT.to_dict()
    for field, value in (("axial_m", [0.01, 0.0]), ("step_per_m", -1.0),
                         ("principle", "sonar"), ("max_range_m", 0.1),
                         ("axial_m", [-0.01, 0.0, 0.0]), ("measured_use", "raise")):
        with pytest.raises(BadValue, match=field.split("_m")[0]):
            NoiseProfile.from_dict({**good, field: value})
    with pytest.raises(BadValue, match="known fields"):
        NoiseProfile.from_dict({**good, "gain": 2})


def test_auto_picks_the_profile_of_the_camera_model_its_driver_names(caplog):
    from robot_change.noise.profile import profile_for_camera, resolve_profile

    models = {"Intel RealSense D435": "realsense_d435", "Intel RealSense D435I":
              "realsense_d435", "Intel RealSense D435F": "realsense_d435",
              "Intel RealSense D435IF": "realsense_d435", "Intel RealSense D415": "realsense_d415",
              "Intel RealSense D455": "realsense_d455", "Intel RealSense D457": "realsense_d455",
              "Intel RealSense D455F": "realsense_d455", "Intel RealSense D405": "realsense_d405",
              "PS1080": "xtion", "Xtion PRO LIVE": "xtion", "Kinect": "kinect_v1",
              "Orbbec Astra Pro": "orbbec_astra", "Azure Kinect DK": "azure_kinect",
              "robot-change recording": "kinect_v1", None: "kinect_v1", "": "kinect_v1"}
    with caplog.at_level(logging.WARNING, logger="robot_change.noise.profile"):
        for model, name in models.items():
            assert profile_for_camera(model) == name, model
            assert resolve_profile("auto", camera=model).name == name
    assert not caplog.records  # every camera known, or none named
    assert resolve_profile("xtion", camera="Intel RealSense D435").name == "xtion"  # named wins
    # a camera named but without a built-in profile: the default, and a warning saying so
    for model in ("Intel RealSense D4XX-Test", "Orbbec Femto Bolt"):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="robot_change.noise.profile"):
            assert profile_for_camera(model) == "kinect_v1"
        assert model in caplog.text and "calibrate" in caplog.text


def test_a_profile_file_round_trips_and_a_bad_one_names_the_file(tmp_path):
    raised = KINECT.raised_by(((2.0, 0.05, 900), (3.0, 0.06, 900)), "test", tolerance=1.0)
    path = raised.save(tmp_path / "camera.json")
    assert NoiseProfile.load(path) == raised
    assert resolve_profile("xtion", path) == raised  # the measured one wins
    assert resolve_profile("xtion") == builtin_profile("xtion")
    data = json.loads(path.read_text())
    cases = {"missing.json": None, "text.json": "not json",
             "foreign.json": json.dumps({"format": "other", "version": 1}),
             "newer.json": json.dumps({**data, "version": 99}),
             "bad.json": json.dumps({**data, "profile": {**data["profile"], "step_per_m": -1}})}
    for name, text in cases.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        with pytest.raises(ProfileFileError, match=name):
            NoiseProfile.load(tmp_path / name)


def test_a_measurement_raises_a_profile_where_it_is_noisier_and_never_lowers_it():
    z = np.arange(1.0, 5.0, 0.25)
    paper = KINECT.raised_by(tuple((v, 0.1, 1000) for v in z), "100 mm", tolerance=1.25)
    assert paper.name == "kinect_v1+measured" and paper.measured_use == "raise"
    np.testing.assert_allclose(paper.sigma(z), 0.1, rtol=0.01)
    assert paper.sigma(6.0) > KINECT.sigma(6.0)  # beyond the bins: the shape, scaled
    quiet = KINECT.raised_by(tuple((v, 0.5 * float(KINECT.sigma(v)), 1000) for v in z),
                             "quiet", tolerance=1.25)
    assert quiet.sigma(z).tolist() == KINECT.sigma(z).tolist() and not quiet.measured_use
    near = KINECT.raised_by(tuple((v, 1.2 * float(KINECT.sigma(v)), 1000) for v in z),
                            "within the tolerance", tolerance=RAISE_TOLERANCE)
    assert near.sigma(z).tolist() == KINECT.sigma(z).tolist()
    mixed = KINECT.raised_by(((1.0, 0.01, 1000), (4.0, 0.001, 1000)), "mixed", tolerance=1.25)
    assert mixed.sigma(1.0) == pytest.approx(0.01)
    assert mixed.sigma(4.0) == pytest.approx(float(KINECT.sigma(4.0)))


def _wall_frames(n, sigma_m, rng, step_per_m=0.0, flicker=0.0):
    """``n`` frames (uint16 mm) of a wall slanted from 1.5 to 3.5 m with a box before it,
    Gaussian noise of ``sigma_m``, optionally quantised in steps of step_per_m z^2 and with
    a share ``flicker`` of pixels dropped in each frame."""
    cols = np.linspace(1.5, 3.5, 640)
    ideal = np.tile(cols, (480, 1))
    ideal[200:280, 300:380] = 1.2  # a box: depth edges
    frames = []
    for _ in range(n):
        z = ideal + sigma_m * rng.standard_normal(ideal.shape)
        if step_per_m:
            k = np.maximum(np.rint(1.0 / (step_per_m * z)), 1.0)
            z = 1.0 / (step_per_m * k)
        depth = np.rint(z * 1000).astype(np.uint16)
        depth[rng.random(depth.shape) < flicker] = 0
        frames.append(depth)
    return np.stack(frames)


def test_the_frames_of_a_still_camera_give_its_noise():
    rng = np.random.default_rng(3)
    got = measure_frames(_wall_frames(6, 0.01, rng, flicker=0.02))
    zs = np.array([b[0] for b in got.bins])
    assert zs.min() < 1.8 and zs.max() > 3.2
    np.testing.assert_allclose([b[1] for b in got.bins], 0.01, rtol=0.1)
    assert got.flicker_valid == pytest.approx(2 * 0.02 * 0.98 / (1 - 0.02 ** 2), rel=0.15)
    assert got.step_per_m == 0.0  # millimetre readings
    assert got.drift == pytest.approx(1.0, abs=0.05)  # noise alone
    stepped = measure_frames(_wall_frames(4, 0.002, rng, step_per_m=2.85e-3))
    assert stepped.step_per_m == pytest.approx(2.85e-3, rel=0.1)
    assert stepped.flicker_step > 0.05  # readings that jump a whole step between frames
    assert stepped.drift == pytest.approx(1.0, abs=0.1)
    with pytest.raises(InputError, match="at least 2"):
        measure_frames(_wall_frames(1, 0.01, rng))


def test_frames_that_drift_are_told_from_noise():
    """A view that creeps 2 mm a frame (under half the 5 mm noise of one reading) over 30
    frames: the first and last frames lie ~10 times as far apart as consecutive ones."""
    rng = np.random.default_rng(5)
    assert measure_frames(_wall_frames(30, 0.005, rng)).drift == pytest.approx(1.0, abs=0.05)
    creep = 2 * np.arange(30, dtype=np.uint16)[:, None, None]
    drifted = measure_frames(_wall_frames(30, 0.005, rng) + creep)
    assert 7.0 < drifted.drift < 13.0


@pytest.mark.parametrize("frames", [3, 4, 5, 30])
def test_calibrate_s_drift_limit_passes_noise_and_refuses_steady_motion(frames):
    """Noise alone drifts about 1 over any number of frames; a view moving a reading's sigma
    a frame drifts beyond the limit (half the frames, at most 2.5); two frames cannot tell."""
    from robot_change.noise.estimate import drift_limit

    rng = np.random.default_rng(frames)
    still = measure_frames(_wall_frames(frames, 0.005, rng)).drift
    creep = 5 * np.arange(frames, dtype=np.uint16)[:, None, None]  # one sigma (5 mm) a frame
    moving = measure_frames(_wall_frames(frames, 0.005, rng) + creep).drift
    assert still < 1.1 < drift_limit(frames) < moving
    assert drift_limit(2) == float("inf") and drift_limit(frames) == min(2.5, frames / 2)


def test_a_reference_keeps_the_drift_of_its_frames(tmp_path):
    """A capture while the view creeps a reading's sigma a frame says so (its drift beyond a
    still view's); a still one does not; one frame has none; the file keeps it."""
    rng = np.random.default_rng(6)
    still = build_scene(_wall_frames(5, 0.005, rng), intrinsics=CAMERA)
    creep = 5 * np.arange(5, dtype=np.uint16)[:, None, None]
    moving = build_scene(_wall_frames(5, 0.005, rng) + creep, intrinsics=CAMERA)
    assert still.drift < 1.1 and not still.moved_while_captured
    assert moving.drift > 2.5 and moving.moved_while_captured
    assert build_scene(_wall_frames(1, 0.005, rng), intrinsics=CAMERA).drift is None
    moving.save(tmp_path / "moving.npz")
    assert SceneModel.load(tmp_path / "moving.npz").drift == moving.drift


def test_calibrating_replaces_the_sigma_with_the_measured_one():
    rng = np.random.default_rng(4)
    profile, noise = profile_from_frames(_wall_frames(5, 0.004, rng), KINECT, "a wall")
    assert profile.name == "measured:kinect_v1" and profile.measured_use == "replace"
    assert profile.sigma(2.5) == pytest.approx(0.004, rel=0.1)  # less than the built-in
    assert profile.sigma(2.5) < KINECT.sigma(2.5) and profile.principle == KINECT.principle
    assert "5 frames of a wall" in profile.source and noise.n_frames == 5
    with pytest.raises(InputError, match="no depth"):
        profile_from_frames(np.zeros((3, 480, 640), np.uint16), KINECT, "a covered lens")


def test_a_reference_keeps_its_profile_raised_by_its_frames(tmp_path):
    rng = np.random.default_rng(5)
    noisy = build_scene(_wall_frames(3, 0.1, rng), intrinsics=CAMERA)
    assert noisy.noise.name == "kinect_v1+measured"
    assert noisy.noise.sigma(2.5) == pytest.approx(0.1, rel=0.15)
    single = build_scene(_wall_frames(1, 0.1, rng), intrinsics=CAMERA)
    assert single.noise == KINECT  # one frame measures nothing
    stereo = build_scene(_wall_frames(3, 0.001, rng), intrinsics=CAMERA,
                         noise=builtin_profile("realsense_d455"))
    assert stereo.noise.name == "realsense_d455"
    noisy.save(tmp_path / "ref.npz")
    assert SceneModel.load(tmp_path / "ref.npz").noise == noisy.noise
    with pytest.raises(InputError, match="NoiseProfile"):
        build_scene(_wall_frames(1, 0.01, rng), intrinsics=CAMERA, noise="kinect")


def test_opening_a_mask_matches_ndimage():
    rng = np.random.default_rng(6)
    mask = ndimage.binary_dilation(rng.random((60, 80)) < 0.05, iterations=2)
    mask[10:12, :] = True  # a strip two pixels wide
    for radius in (1, 2, 3):
        square = np.ones((2 * radius + 1,) * 2)
        # the window is clipped at the image's border: what lies beyond neither erodes nor
        # grows the mask
        core = ndimage.binary_erosion(mask, square, border_value=1)
        want = ndimage.binary_dilation(core, square, border_value=0)
        np.testing.assert_array_equal(open_mask(mask, radius), want)
    strip = np.zeros_like(mask)
    strip[10:12, :] = True
    assert not open_mask(strip, 2).any() and open_mask(strip, 0).sum() == strip.sum()
