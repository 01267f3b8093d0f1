"""The harsher noise models and the noise statistics (sim_fixtures.harsh_noise, .real_noise):
the old models unchanged bit for bit, what the harsh Kinect model adds (flying pixels, flicker, a
zero border, an error field per epoch), the stereo model's z^2 growth, the statistics against
hand-made pairs with known answers, and the harsh no-change pair generator."""

from __future__ import annotations

import dataclasses
import hashlib
import math

import numpy as np
import pytest

from hw.depth import Intrinsics
from sim_fixtures import load_scene
from sim_fixtures.harsh_noise import (
    RealisticKinectNoise,
    StereoNoise,
    correlated_field,
    true_camera_view,
)
from sim_fixtures.noise import GaussianNoise, KinectNoise, noise_from_json
from sim_fixtures.real_noise import (
    HARSH_LAYOUTS,
    edge_stats,
    fit_quant_c,
    harsh_pair,
    landing,
    pair_stats,
    quantisation_step,
    refine_pose,
    zero_border,
)
from sim_fixtures.render import Box, Obj, Plane, Pose, render
from sim_fixtures.scenes import SCENES, render_pair

INTR = Intrinsics.openni_default()
K = (INTR.fx, INTR.fy, INTR.cx, INTR.cy)
FLAT = Pose((0.0, 0.0, 1.0))  # 1 m up, looking along world +x, level


def wall(x: float) -> Obj:
    return Obj("wall", (Plane((x, 0.0, 0.0), (1.0, 0.0, 0.0)),))


def box_at(x: float, half: float = 0.4) -> Obj:
    """A cube whose front face is at world x, centred on the optical axis."""
    return Obj("box", (Box((x + half, 0.0, 1.0), (2 * half, 2 * half, 2 * half)),))


def sha(frame: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(frame).tobytes()).hexdigest()


@pytest.fixture(scope="module")
def office_render():
    return render_pair(SCENES["office_no_change"])[0]


# ----------------------------------------------------------------------------- old models


def test_old_kinect_noise_reproduces_the_stored_fixture_bit_for_bit(office_render):
    spec = SCENES["office_no_change"]
    stored = load_scene("office_no_change").reference_frames()[0]
    again = KinectNoise().apply(office_render, np.random.default_rng([spec.seed, 0, 0]))
    assert again.dtype == np.uint16
    np.testing.assert_array_equal(again, stored)


def test_old_models_give_the_hashes_taken_before_the_new_models(office_render):
    # computed with the unmodified noise.py (before RealisticKinectNoise / StereoNoise)
    def rng():
        return np.random.default_rng([102, 0, 0])

    assert sha(KinectNoise().apply(office_render, rng())) == \
        "ad24e64e4bde6964fde636645a7485e4cbaae1cd57d1c1dc8a16513b1d3c1bba"
    assert sha(KinectNoise(lateral_sigma_px=0.8).apply(office_render, rng())) == \
        "5b25bc71d0c3cd72c17fa120d35879fd248a813bbcdbfdc93779784122c15c79"
    assert sha(GaussianNoise(0.01).apply(office_render, rng())) == \
        "13edae11481b6eddd6734f3b2084541c44f118646482790d7ed22c2eb064e6c6"
    # their JSON and its inverse are unchanged too
    for noise in (KinectNoise(), GaussianNoise(0.01)):
        assert noise_from_json(noise.to_json()) == noise
    assert KinectNoise().to_json()["model"] == "kinect"
    assert set(KinectNoise().to_json()) == {
        "model", "near_m", "far_m", "quant_c_per_m", "grazing_start_deg", "grazing_stop_deg",
        "edge_rel_jump", "edge_band_px", "edge_drop_prob", "projector_baseline_m",
        "lateral_sigma_px", "axial_sigma", "quantisation"}


def test_new_models_round_trip_through_json():
    for noise in (RealisticKinectNoise(), RealisticKinectNoise(k1=0.0, border_px=(0, 0, 0, 0)),
                  StereoNoise.d435(), StereoNoise.d455(subpixel_px=0.05)):
        assert noise_from_json(noise.to_json()) == noise
    with pytest.raises(ValueError, match="unknown noise model"):
        noise_from_json({"model": "tof"})


# ----------------------------------------------------------------------------- harsh model


def test_harsh_model_puts_flying_pixels_at_edges_and_the_old_one_none():
    # a box face at 4.5 m before a wall at 7.8 m: flying probability 0.06 (4.5/4)^2 ~ 0.076
    # for the pixels beside the box's outline; noise alone never reads 0.4 m off the box or
    # 0.8 m off the wall (11 and 5.7 sigma)
    r = render([wall(7.8), box_at(4.5)], FLAT, INTR, None, 0.075)
    harsh = RealisticKinectNoise()
    p = float(harsh.flying(4.5))
    assert p == pytest.approx(0.06 * 1.125**2)
    # where the harsh model's true camera sees the box (its intrinsics are not the nominal)
    seen = true_camera_view(r, harsh.true_f_scale, harsh.true_cx_offset_px,
                            harsh.true_cy_offset_px, harsh.k1).depth
    ideal_box = (seen > 0) & (seen < 6.0)
    outline = _dilated(ideal_box, 1) & ~_eroded(ideal_box, 1)  # the pixels beside the jump
    band = _dilated(ideal_box, 3) & ~_eroded(ideal_box, 3)  # + the registration's resampling
    for seed in range(3):
        old = KinectNoise(far_m=8.0).apply(r, np.random.default_rng(seed)) / 1000
        assert not ((old > 4.9) & (old < 7.0)).any()
        frame = harsh.apply(r, np.random.default_rng(seed)) / 1000
        between = (frame > 4.9) & (frame < 7.0)
        assert not between[~band].any()  # only at the box's outline
        assert 0.25 * p * outline.sum() < between.sum() < 1.2 * p * outline.sum()


def _dilated(mask, n):
    out = mask.copy()
    for _ in range(n):
        out = out | np.roll(out, 1, 0) | np.roll(out, -1, 0) | np.roll(out, 1, 1) | \
            np.roll(out, -1, 1)
    return out


def _eroded(mask, n):
    return ~_dilated(~mask, n)


def test_harsh_model_flickers_between_frames_of_one_pose():
    r = render([wall(4.0)], FLAT, INTR)
    noise = RealisticKinectNoise(k1=0.0, true_f_scale=1.0, true_cx_offset_px=0.0,
                                 true_cy_offset_px=0.0)
    a = noise.apply(r, np.random.default_rng(0))
    b = noise.apply(r, np.random.default_rng(1))
    again = noise.apply(r, np.random.default_rng(0))
    np.testing.assert_array_equal(a, again)  # deterministic given the generator
    inside = np.zeros(a.shape, bool)
    inside[20:-20, 10:-45] = True  # inside the zero border (3, 37, 12, 7)
    only_one = ((a > 0) != (b > 0)) & inside
    # dropout at 4 m: 0.61 % a frame, so ~1.2 % of pixels valid in just one of two frames
    p = noise.dropout(4.0)
    assert p == pytest.approx(0.0061)
    assert 1.4 * p < only_one.sum() / inside.sum() < 2.6 * p
    st = pair_stats([(a, b, None, K)], bins_m=np.array([3.5, 4.5]))
    assert 0.7 * p < st.flicker[0] < 1.3 * p
    # whole disparity steps (46 mm at 4 m) flip, in patches: neighbours flip together
    assert st.step[0] == pytest.approx(0.00292 * 16, rel=0.1)
    assert 0.3 < st.jump[0] < 0.8
    assert st.corr[0] > 0.4  # the difference of neighbouring pixels is correlated
    old = KinectNoise(projector_baseline_m=0.0)
    o = pair_stats([(old.apply(r, np.random.default_rng(0)), old.apply(r, np.random.default_rng(1)),
                     None, K)], bins_m=np.array([3.5, 4.5]))
    assert abs(o.corr[0]) < 0.05 and o.flicker[0] == 0.0


def test_harsh_model_has_a_zero_border(office_render):
    frame = RealisticKinectNoise().apply(office_render, np.random.default_rng(0))
    left, right, top, bottom = RealisticKinectNoise().border_px
    assert (left, right, top, bottom) == (3, 37, 12, 7)
    assert not frame[:, :left].any() and not frame[:, -right:].any()
    assert not frame[:top].any() and not frame[-bottom:].any()
    assert zero_border(frame) == (left, right, top, bottom)
    assert (frame[top:-bottom, left:-right] > 0).mean() > 0.9
    assert zero_border(KinectNoise().apply(office_render, np.random.default_rng(0))) == \
        (0, 0, 0, 0)


def test_error_field_is_fixed_per_epoch_and_pose_and_differs_between_them():
    r = render([wall(3.0)], FLAT, INTR)
    noise = RealisticKinectNoise()
    f0 = noise.field(r)
    np.testing.assert_array_equal(f0, noise.field(r))
    np.testing.assert_array_equal(f0, RealisticKinectNoise().field(r))
    other_epoch = noise.for_epoch(1).field(r)
    moved = noise.field(render([wall(3.0)], FLAT.moved(dx=0.01), INTR))
    for other in (other_epoch, moved):
        assert abs(np.corrcoef(f0.ravel(), other.ravel())[0, 1]) < 0.3
    assert f0.std() == pytest.approx(1.0, abs=1e-9)
    # smooth: neighbours 10 px apart still correlate
    assert np.corrcoef(f0[:, :-10].ravel(), f0[:, 10:].ravel())[0, 1] > 0.9
    # in the frames: with a strong field, two frames of one epoch share it (their difference
    # has no low-frequency part), frames of two epochs do not
    strong = dataclasses.replace(noise, field_sigma_m_at_4m=0.05, field_exponent=0.0)
    a = strong.apply(r, np.random.default_rng(0))
    b = strong.apply(r, np.random.default_rng(1))
    c = strong.for_epoch(1).apply(r, np.random.default_rng(1))
    bins = np.array([2.5, 3.5])
    same = pair_stats([(a, b, None, K)], bins_m=bins).lowfreq_sigma[0]
    apart = pair_stats([(a, c, None, K)], bins_m=bins).lowfreq_sigma[0]
    assert same < 0.006 and apart > 0.05  # sqrt(2) x 50 mm, smoothed a little


def test_true_intrinsics_and_distortion_move_the_image():
    r = render([wall(6.0), box_at(3.0, half=1.0)], FLAT, INTR)
    ideal = RealisticKinectNoise(k1=0.0, true_f_scale=1.0, true_cx_offset_px=0.0,
                                 true_cy_offset_px=0.0, register_baseline_m=0.0,
                                 border_px=(0, 0, 0, 0), flying_at_4m=0.0)
    shifted = dataclasses.replace(ideal, true_cx_offset_px=6.0)
    a = ideal.apply(r, np.random.default_rng(0))
    b = shifted.apply(r, np.random.default_rng(0))
    def cols(f):
        return np.flatnonzero((f[240] > 0) & (f[240] < 4000))

    # the principal point 6 px to the right: the box shows 6 px to the right
    assert cols(b).min() - cols(a).min() == pytest.approx(6, abs=1)
    assert cols(b).max() - cols(a).max() == pytest.approx(6, abs=1)
    # distortion: k1 > 0 pushes the box's edges outward, ~k1 r^3 f = 6 px a side here
    c = dataclasses.replace(ideal, k1=0.2).apply(r, np.random.default_rng(0))
    assert len(cols(c)) - len(cols(a)) == pytest.approx(2 * 0.2 * (175 / 525) ** 3 * 525,
                                                        abs=2)


# ----------------------------------------------------------------------------- stereo


def test_stereo_difference_sigma_grows_with_z_squared():
    noise = StereoNoise.d435()
    pairs = []
    for x in (1.0, 2.0):
        r = render([wall(x)], FLAT, INTR)
        pairs.append((noise.apply(r, np.random.default_rng([int(x), 0])),
                      noise.apply(r, np.random.default_rng([int(x), 1])), None, K))
    st = pair_stats(pairs, bins_m=np.array([0.9, 1.1, 1.9, 2.1]))
    ratio = st.sigma[2] / st.sigma[0]
    assert 3.4 < ratio < 4.6
    # the difference of two frames: sqrt(2) x z^2 x 0.08 / (525 x 0.05) at the wall's centre
    expected = math.sqrt(2) * 2.0**2 * 0.08 / (525 * 0.05)
    assert st.sigma[2] == pytest.approx(expected, rel=0.15)
    assert noise.sigma(2.0, 525.0) == pytest.approx(2.0**2 * 0.08 / (525 * 0.05))
    assert noise.step(2.0, 525.0) == pytest.approx(4.0 / (32 * 525 * 0.05))
    d455 = StereoNoise.d455()
    assert d455.sigma(4.0, 525.0) / noise.sigma(4.0, 525.0) == pytest.approx(50 / 95)


def test_stereo_range_and_occlusion_band_beside_near_objects():
    noise = StereoNoise.d435()
    r = render([wall(3.0), box_at(1.5, half=0.2)], FLAT, INTR, None, noise.projector_baseline_m)
    frame = noise.apply(r, np.random.default_rng(0))
    row = frame[240]
    box_cols = np.flatnonzero(r.ids[240] == 2)
    left = box_cols.min()
    # the right imager, 5 cm to the right, cannot see the wall just left of the box: a band of
    # f b (1/1.5 - 1/3) = 525 x 0.05 x 0.333 = 8.75 px without depth
    band = np.flatnonzero(row[:left] == 0)
    assert len(band) == pytest.approx(8.75, abs=1.5) and band.max() == left - 1
    assert (row[box_cols.max() + 3:] > 0).all()  # nothing on the box's right
    near = render([wall(0.25)], FLAT, INTR)
    assert not noise.apply(near, np.random.default_rng(0)).any()  # below 0.3 m


# ----------------------------------------------------------------------------- statistics


def test_pair_stats_known_sigma_quantiles_and_flicker():
    rng = np.random.default_rng(0)
    a = np.full((480, 640), 2000, np.uint16)
    b = (2000 + np.rint(rng.normal(0.0, 5.0, a.shape))).astype(np.uint16)
    b[::10, ::10] = 0  # 1 % of b invalid
    # millimetre depth: dithered by the 1 mm step, and the dither taken off again
    st = pair_stats([(a, b, None, K)], bins_m=np.array([1.5, 2.5]), steps=np.array([0.001]),
                    margin_px=0)
    assert st.sigma[0] == pytest.approx(math.sqrt(0.005**2 + 0.001**2 / 12), rel=0.02)
    assert st.q99[0] == pytest.approx(2.576 * 0.005, rel=0.08)
    assert st.median[0] == pytest.approx(0.0, abs=1e-9)
    n_bad = 48 * 64
    # a -> b: n_bad of 307200 land on no reading; b -> a: none of b's 304128 readings
    assert st.flicker[0] == pytest.approx(n_bad / (307200 + 307200 - n_bad))
    assert st.n[0] == 307200 - n_bad
    assert abs(st.corr[0]) < 0.02  # independent pixels


def test_pair_stats_whole_steps_and_lowfreq():
    a = np.full((480, 640), 3000, np.uint16)
    b = a.copy()
    rows = np.arange(480)[:, None] % 10
    b[np.broadcast_to(rows == 0, a.shape)] += 30   # 10 %: one step of 30 mm
    b[np.broadcast_to(rows == 1, a.shape)] -= 60   # 10 %: two steps
    st = pair_stats([(a, b, None, K)], bins_m=np.array([2.5, 3.5]), steps=np.array([0.03]),
                    margin_px=0)
    assert st.jump[0] == pytest.approx(0.2)
    assert st.jump2[0] == pytest.approx(0.1)
    # the 31 x 31 box mean of d is (30 - 60) / 10 = -3 mm everywhere but at the rows' ends
    assert st.lowfreq_sigma[0] < 0.001
    assert st.median[0] == 0.0


def test_landing_and_refine_pose_follow_a_known_motion():
    spec = SCENES["office_no_change"]
    pose = spec.reference_pose
    moved = pose.moved(dx=0.02, dy=-0.01, dyaw_deg=0.5)
    def mm(r):
        return np.rint(r.depth * 1000).astype(np.uint16)

    a = mm(render(spec.reference, pose, INTR))
    b = mm(render(spec.reference, moved, INTR))
    T = np.linalg.inv(moved.matrix()) @ pose.matrix()
    L = landing(a, T, K)
    zb = b.ravel()[L["dst"]] / 1000
    ok = zb > 0
    d = zb[ok] - L["z_pred"][ok]
    assert np.median(np.abs(d)) < 0.002  # lands on the same surface
    st = pair_stats([(a, b, T, K)], bins_m=np.array([1.5, 2.5, 3.5]), steps=np.zeros(2))
    assert st.sigma[0] < 0.004 and st.sigma[1] < 0.005  # nearest-pixel landing on slopes
    # a 1 cm / 0.3 deg error is found again by refine_pose
    err = np.eye(4)
    err[:3, 3] = (0.01, -0.005, 0.005)
    c, s = math.cos(math.radians(0.3)), math.sin(math.radians(0.3))
    err[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T2 = refine_pose(a, b, err @ T, K)
    assert np.abs(T2[:3, 3] - T[:3, 3]).max() < 0.002
    assert np.abs(T2[:3, :3] - T[:3, :3]).max() < 0.001


def test_quantisation_step_and_fit_on_disparity_levels():
    c = 0.003
    k = np.arange(40, 700)
    levels = np.rint(1000.0 / (c * k)).astype(np.uint16)  # 0.48 to 8.3 m
    values = np.repeat(levels, 5)
    step = quantisation_step(values, np.array([2.0, 2.5, 3.0, 3.5]))
    assert step[0] == pytest.approx(c * 2.25**2, rel=0.1)
    assert step[2] == pytest.approx(c * 3.25**2, rel=0.05)
    assert fit_quant_c(values) == pytest.approx(c, rel=0.03)


def test_edge_stats_on_a_hand_made_edge():
    img = np.full((480, 640), 4000, np.uint16)
    img[:, :320] = 2000  # a step from 2 m to 4 m between columns 319 and 320
    img[::2, 320] = 3000  # every other row: one flying pixel in between
    e = edge_stats(img)
    # rows with the flying pixel: 5 edge pixels, 1 flying; sharp rows: 6 edge pixels
    assert e.crossings == 480
    assert e.pixels == 240 * 5 + 240 * 6
    assert e.flying_share == pytest.approx(240 / (240 * 5 + 240 * 6))
    assert e.hole_share == 0.0
    np.testing.assert_allclose(e.width_hist, [0.5, 0.5, 0, 0, 0])
    assert e.mean_width == 1.0
    i = np.searchsorted(e.bins_m, 2.0, side="right") - 1
    assert e.flying_share_by_bin[i] == pytest.approx(e.flying_share)


def test_correlated_field_has_the_asked_correlation():
    f = correlated_field(np.random.default_rng(0), (480, 640), 3.5)
    assert f.std() == pytest.approx(1.0)
    c1 = np.corrcoef(f[:, :-1].ravel(), f[:, 1:].ravel())[0, 1]
    c4 = np.corrcoef(f[:, :-4].ravel(), f[:, 4:].ravel())[0, 1]
    assert c1 == pytest.approx(math.exp(-1 / 3.5), abs=0.08)
    assert c4 == pytest.approx(math.exp(-4 / 3.5), abs=0.08)


# ----------------------------------------------------------------------------- pairs


def test_harsh_pairs_are_deterministic_no_change_pairs_with_the_true_transform():
    p = harsh_pair("storage", seed=2, offset_m=0.03)
    q = harsh_pair("storage", seed=2, offset_m=0.03)
    assert len(p.reference) == 3 and len(p.current) == 3
    for x, y in zip(p.reference + p.current, q.reference + q.current, strict=True):
        assert x.dtype == np.uint16 and x.shape == (480, 640)
        np.testing.assert_array_equal(x, y)
    assert np.linalg.norm(p.T_ref_from_cur[:3, 3]) == pytest.approx(0.03, abs=1e-9)
    angle = math.degrees(math.acos((np.trace(p.T_ref_from_cur[:3, :3]) - 1) / 2))
    assert angle == pytest.approx(1.2, abs=0.1)  # yaw, pitch, roll with RSS 1.2 deg
    assert p.intrinsics == INTR
    assert not np.array_equal(p.reference[0], p.reference[1])  # independent noise
    # nothing changed: the current reprojected into the reference agrees (robustly)
    st = pair_stats([(p.current[0], p.reference[0], p.T_ref_from_cur, K)])
    ok = st.n > 5000
    sim = RealisticKinectNoise()
    z = st.centres()[ok]
    assert (st.sigma[ok] < 4 * math.sqrt(2) * sim.sigma(z)).all()
    assert zero_border(p.current[2]) == (3, 37, 12, 7)
    assert p.layout in HARSH_LAYOUTS and HARSH_LAYOUTS == (
        "office", "lounge", "lab", "storage", "meeting")
    still = harsh_pair("storage", seed=2, frames=(1, 1))
    np.testing.assert_array_equal(still.T_ref_from_cur, np.eye(4))
    assert not np.array_equal(still.reference[0], still.current[0])
    with pytest.raises(ValueError, match="layout"):
        harsh_pair("kitchen")
