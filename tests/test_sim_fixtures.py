"""sim_fixtures: the renderer against analytic depth, the noise models' statistics, the truth
masks, and the checked-in scenes against their scene.json (and against a regeneration)."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest

from hw.depth import Intrinsics, open_depth
from hw.imagefile import read_image
from hw.oni import read_oni_frames, read_oni_header
from sim_fixtures import DEMO_FRAME, SCENES_DIR, UnknownScene, load_scene, scene_names
from sim_fixtures import FORMAT_VERSION as LOADER_FORMAT_VERSION
from sim_fixtures import ROOT as FIXTURES_ROOT
from sim_fixtures import render as render_mod
from sim_fixtures.make_fixtures import (
    FORMAT_VERSION,
    best_codec,
    noisy_frames,
    write_oni_recording,
)
from sim_fixtures.noise import (
    PAPER_SIGMAS_M,
    GaussianNoise,
    KinectNoise,
    kinect_axial_sigma,
    quantise_depth,
)
from sim_fixtures.render import Box, Cylinder, Obj, Plane, Pose, cast_rays, render
from sim_fixtures.scenes import (
    SCENES,
    SceneSpec,
    box,
    diff_layouts,
    object_ids,
    render_pair,
    room,
    truth_masks,
)

INTR = Intrinsics.openni_default()
FX = INTR.fx


def wall(x: float) -> Obj:
    """A wall facing the camera at world x (the camera at the origin looks along +x)."""
    return Obj("wall", (Plane((x, 0.0, 0.0), (1.0, 0.0, 0.0)),))


FLAT = Pose((0.0, 0.0, 1.0))  # 1 m up, looking along world +x, level


# ----------------------------------------------------------------------------- renderer


def test_pose_convention():
    rot = Pose((0, 0, 0)).rotation()
    np.testing.assert_allclose(rot[:, 2], [1, 0, 0], atol=1e-12)  # optical z = world +x
    np.testing.assert_allclose(rot[:, 0], [0, -1, 0], atol=1e-12)  # image right = world -y
    np.testing.assert_allclose(rot[:, 1], [0, 0, -1], atol=1e-12)  # image down = world down
    tilted = Pose((0, 0, 0), yaw_deg=30, pitch_deg=20, roll_deg=5).rotation()
    np.testing.assert_allclose(tilted.T @ tilted, np.eye(3), atol=1e-12)
    assert np.linalg.det(tilted) == pytest.approx(1.0)
    assert tilted[2, 2] == pytest.approx(-math.sin(math.radians(20)))  # looks down
    assert math.degrees(math.atan2(tilted[1, 2], tilted[0, 2])) == pytest.approx(30)


def test_fronto_parallel_wall_is_2m_everywhere():
    r = render([wall(2.0)], FLAT, INTR)
    assert r.depth.shape == (480, 640) and r.depth.dtype == np.float64
    np.testing.assert_allclose(r.depth, 2.0, rtol=0, atol=1e-12)
    assert (r.ids == 1).all()
    np.testing.assert_allclose(r.normals[240, 320], [0, 0, -1], atol=1e-12)
    # incidence: cos = 1 / |((u - cx)/fx, (v - cy)/fy, 1)|
    u, v = 0, 0
    d = np.array([(u - INTR.cx) / FX, (v - INTR.cy) / FX, 1.0])
    assert r.cos_incidence[v, u] == pytest.approx(1 / np.linalg.norm(d))
    # back-projected points lie on the wall
    np.testing.assert_allclose(r.points[..., 2], 2.0, atol=1e-12)
    assert r.points[0, 0, 0] == pytest.approx((0 - INTR.cx) / FX * 2.0)


@pytest.mark.parametrize("height,pitch_deg,yaw_deg", [(1.0, 20.0, 0.0), (0.6, 8.0, 137.0)])
def test_floor_depth_per_row(height, pitch_deg, yaw_deg):
    floor = Obj("floor", (Plane((0, 0, 0), (0, 0, 1)),))
    r = render([floor], Pose((1.0, 2.0, height), yaw_deg, pitch_deg), INTR)
    th = math.radians(pitch_deg)
    yc = (np.arange(480) - INTR.cy) / INTR.fy
    denom = math.sin(th) + yc * math.cos(th)
    expected = np.where(denom > 0, height / np.where(denom > 0, denom, 1), 0.0)
    for col in (0, 320, 639):  # the same in every column
        np.testing.assert_allclose(r.depth[:, col], expected, rtol=1e-10, atol=1e-12)
    assert (r.ids[denom <= 0] == 0).all() and (r.ids[denom > 0] == 1).all()


def test_box_cylinder_and_rotated_box_against_analytic_depth():
    cube = Obj("cube", (Box((3.0, 0.0, 1.0), (1.0, 1.0, 1.0)),))
    r = render([wall(6.0), cube], FLAT, INTR)
    assert r.depth[240, 320] == pytest.approx(2.5)  # front face at x = 2.5
    cols = np.flatnonzero(r.ids[240] == 2)
    assert abs(cols.min() - (INTR.cx - FX * 0.5 / 2.5)) <= 1  # 105 px either side
    assert abs(cols.max() - (INTR.cx + FX * 0.5 / 2.5)) <= 1

    turned = Obj("turned", (Box((3.0, 0.0, 1.0), (1.0, 1.0, 1.0),
                                tuple(map(tuple, render_mod.rot_z(math.radians(45))))),))
    r = render([wall(6.0), turned], FLAT, INTR)
    # the nearest vertical edge points at the camera: 3 - sqrt(2)/2 (pixel 319.5 is between
    # columns, so the centre columns see the edge 0.5 px off: allow that slope)
    assert r.depth[240, 320] == pytest.approx(3 - math.sqrt(0.5), abs=0.5 / FX * 2.3 + 1e-9)

    can = Obj("can", (Cylinder((3.0, 0.0, 0.0), 0.4, 2.0),))
    r = render([wall(6.0), can], FLAT, INTR)
    x = (np.arange(640) - INTR.cx) / FX  # ray slope in the row through the optical axis
    # ray (t, -x t) in world (x, y) hits the circle |p - (3, 0)| = 0.4 at the smaller root
    a, b, c = 1 + x**2, -6.0, 9 - 0.16
    disc = b * b - 4 * a * c
    hit = disc >= 0
    t = (-b - np.sqrt(np.where(hit, disc, 0))) / (2 * a)
    row = r.depth[int(INTR.cy)]  # row 239: 0.5 px above the axis, still within the can
    np.testing.assert_allclose(row[hit], t[hit], atol=1e-9)
    assert (row[~hit] == pytest.approx(6.0))


def test_culling_gives_the_same_hits_as_testing_every_ray(monkeypatch):
    spec = SCENES["lab_two_changes"]
    objs, pose = spec.current, spec.current_pose
    ids = list(range(1, len(objs) + 1))
    rays = render_mod.camera_rays(INTR)[::7]
    culled = cast_rays(objs, np.array(pose.position), pose.rotation(), rays, ids)
    monkeypatch.setattr(render_mod, "_candidates", lambda *args: None)
    brute = cast_rays(objs, np.array(pose.position), pose.rotation(), rays, ids)
    np.testing.assert_array_equal(culled[1], brute[1])
    np.testing.assert_array_equal(culled[0], brute[0])
    np.testing.assert_array_equal(culled[2], brute[2])
    assert len(np.unique(culled[1])) >= 8  # the test saw furniture, not only walls


def test_renders_vga_well_under_a_second():
    spec = SCENES["meeting_two_changes"]
    render(spec.current, spec.current_pose, INTR)  # warm caches
    start = time.perf_counter()
    render(spec.current, spec.current_pose, INTR)
    assert time.perf_counter() - start < 1.0


# ----------------------------------------------------------------------------- noise


@pytest.mark.parametrize("z", [1.0, 2.0, 3.0])
def test_kinect_axial_std_matches_nguyen(z):
    r = render([wall(z)], FLAT, INTR)
    noise = KinectNoise()
    frames = np.stack([noise.apply(r, np.random.default_rng([5, k])) for k in range(3)])
    patch = frames[:, 100:380, 100:540].astype(np.float64) / 1000.0
    assert (patch > 0).all()
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    assert patch.std() == pytest.approx(sigma, rel=0.08)  # without the q^2/12 share: +10-14 %
    assert abs(patch.mean() - z) < 0.2 * sigma + 0.001  # unbiased, up to the quantisation


def test_quantisation_steps_grow_with_z_squared():
    c = KinectNoise().quant_c_per_m
    steps = {}
    for z in (1.0, 2.0, 3.0, 4.0):
        levels = np.unique(quantise_depth(np.linspace(z - 0.1, z + 0.1, 20001), c))
        steps[z] = np.median(np.diff(levels))
        assert steps[z] == pytest.approx(c * z * z, rel=0.05)
    assert steps[2.0] / steps[1.0] == pytest.approx(4, rel=0.05)
    assert steps[3.0] / steps[1.0] == pytest.approx(9, rel=0.05)
    # the noisy output lands on those levels too: at 3 m its values are ~25.6 mm apart
    r = render([wall(3.0)], FLAT, INTR)
    values = np.unique(KinectNoise().apply(r, np.random.default_rng(1)))
    values = values[values > 0]
    assert np.median(np.diff(values)) == pytest.approx(1000 * c * 9, abs=1.5)


def test_nguyen_angle_term_only_above_60_degrees():
    assert kinect_axial_sigma(2.0, math.radians(50)) == pytest.approx(0.0012 + 0.0019 * 1.6**2)
    steep = kinect_axial_sigma(2.0, math.radians(80))
    assert steep == pytest.approx(0.0012 + 0.0019 * 1.6**2 + 0.0001 / math.sqrt(2)
                                  * math.radians(80) ** 2 / math.radians(10) ** 2)


@pytest.mark.parametrize("sigma", PAPER_SIGMAS_M)
def test_paper_protocol_is_plain_gaussian(sigma):
    r = render([wall(3.0)], FLAT, INTR)
    frame = GaussianNoise(sigma).apply(r, np.random.default_rng(3))
    assert frame.dtype == np.uint16 and (frame > 0).all()  # no dropouts, no range limit
    z = frame.astype(np.float64) / 1000.0
    expected = math.sqrt(sigma**2 + 1e-6 / 12)  # + rounding to whole millimetres
    assert z.std() == pytest.approx(expected, rel=0.05)
    assert abs(z.mean() - 3.0) < 4 * expected / math.sqrt(z.size) + 1e-4
    if sigma >= 0.01:  # no disparity quantisation: every millimetre value occurs
        assert np.median(np.diff(np.unique(frame))) == 1
    assert PAPER_SIGMAS_M == (0.001, 0.01, 0.1)


def test_beyond_range_is_invalid():
    noise = KinectNoise()
    for z, valid in ((0.3, 0.0), (2.0, 1.0), (5.5, 0.0)):
        frame = noise.apply(render([wall(z)], FLAT, INTR), np.random.default_rng(0))
        assert (frame > 0).mean() == pytest.approx(valid, abs=1e-9)


def test_grazing_incidence_is_invalid():
    floor = Obj("floor", (Plane((0, 0, 0), (0, 0, 1)),))
    r = render([floor], Pose((0, 0, 0.3), 0, 14.0), INTR)
    frame = KinectNoise(near_m=0.0, far_m=100.0).apply(r, np.random.default_rng(0))
    theta = np.degrees(np.arccos(r.cos_incidence))
    inner = np.zeros_like(r.depth, dtype=bool)
    inner[2:-2, 2:-2] = True  # away from the image border and the horizon edge
    hit = (r.depth > 0) & inner
    assert (frame[hit & (theta < 77)] > 0).all()
    assert (frame[hit & (theta > 88)] == 0).all()
    middle = (frame[hit & (theta > 82) & (theta < 84)] > 0).mean()
    assert 0.2 < middle < 0.6  # linear ramp 78 -> 88 degrees: ~40 % survive at 83
    assert (hit & (theta > 88)).sum() > 1000


def box_before_wall(baseline):
    """A thin board at 1.5 m in front of a wall at 3 m, projector at ``baseline``."""
    board = Obj("board", (Box((1.5, 0.0, 1.0), (0.02, 0.6, 0.6)),))
    return render([wall(3.0), board], FLAT, INTR, projector_baseline_m=baseline)


@pytest.mark.parametrize("baseline,side", [(0.075, "left"), (-0.075, "right")])
def test_projector_shadow_falls_beside_the_object_away_from_the_projector(baseline, side):
    r = box_before_wall(baseline)
    row = r.shadow[240]
    board = np.flatnonzero(r.ids[240] == 2)
    shadow_cols = np.flatnonzero(row)
    assert len(shadow_cols) and not r.shadow[r.ids == 2].any()
    if side == "left":
        assert shadow_cols.max() < board.min() and shadow_cols.min() > board.min() - 20
    else:
        assert shadow_cols.min() > board.max() and shadow_cols.max() < board.max() + 20
    # width on the wall: b (z_wall / z_board - 1) m at 3 m -> fx * 0.075 / 3 ~ 13 px
    z_board = 1.5 - 0.01
    expected = FX * abs(baseline) * (3.0 / z_board - 1) / 3.0
    assert len(shadow_cols) == pytest.approx(expected, abs=1.5)
    frame = KinectNoise(projector_baseline_m=baseline).apply(r, np.random.default_rng(0))
    assert (frame[r.shadow] == 0).all()
    assert not box_before_wall(None).shadow.any()  # no projector, no shadow


def test_depth_edges_drop_about_half_and_nothing_else():
    r = box_before_wall(None)
    noise = KinectNoise(projector_baseline_m=0.0)
    frames = np.stack([noise.apply(r, np.random.default_rng(k)) for k in range(4)])
    jump_cols = np.flatnonzero(np.abs(np.diff(r.depth[240])) > 0.5)
    edge = np.zeros(640, dtype=bool)
    edge[jump_cols] = edge[jump_cols + 1] = True
    dropped = frames[:, 240, :] == 0
    assert dropped[:, edge].mean() == pytest.approx(0.5, abs=0.25)
    assert not dropped[:, ~edge].any()


def test_lateral_noise_blurs_edges_only():
    r = box_before_wall(None)
    noise = KinectNoise(projector_baseline_m=0.0, lateral_sigma_px=0.8, edge_drop_prob=0.0)
    frame = noise.apply(r, np.random.default_rng(0)).astype(np.float64) / 1000
    board = r.ids == 2
    interior = board.copy()
    for axis in (0, 1):
        for shift in (-3, 3):
            interior &= np.roll(board, shift, axis=axis)
    assert (np.abs(frame[interior] - 1.49) < 0.05).all()
    wall_near = np.roll(board, 2, axis=1) & ~board  # 1-2 px right of the board
    assert (np.abs(frame[wall_near] - 1.49) < 0.05).any()  # some read the board


def test_frames_are_reproducible_and_independent():
    spec = SCENES["office_box_added"]
    ref, _ = render_pair(spec)
    a = noisy_frames(spec, ref, 0, 2)
    b = noisy_frames(spec, ref, 0, 2)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert (a[0] != a[1]).mean() > 0.3


# ----------------------------------------------------------------------------- truth


def test_diff_layouts_and_truth_masks_follow_object_ids():
    base = room(4, 4, 2.5) + [box("stays", 3.0, 2.0, (0.5, 0.5, 0.5)),
                             box("goes", 3.0, 1.0, (0.4, 0.4, 0.4)),
                             box("moves", 3.0, 3.0, (0.4, 0.4, 0.4))]
    cur = [o for o in base if o.name != "goes"]
    cur = [o.moved(-0.5, 0.3) if o.name == "moves" else o for o in cur]
    cur += [box("arrives", 2.0, 1.6, (0.3, 0.3, 0.3))]
    changes = diff_layouts(base, cur)
    assert [(c.kind, c.name) for c in changes] == [
        ("removed", "goes"), ("moved", "moves"), ("added", "arrives")]
    pose = Pose((0.3, 2.0, 1.0), 0.0, 15.0)
    spec = SceneSpec("t", "dev", "", "two", (4, 4, 2.5), tuple(base), tuple(cur), pose, pose,
                     KinectNoise(), 1)
    ref, now = render_pair(spec)
    appeared, disappeared = truth_masks(spec, ref, now)
    ids = object_ids(spec)
    np.testing.assert_array_equal(appeared, np.isin(now.ids, [ids["moves"], ids["arrives"]]))
    np.testing.assert_array_equal(disappeared, np.isin(ref.ids, [ids["goes"], ids["moves"]]))
    assert appeared.sum() > 500 and disappeared.sum() > 500
    assert not (appeared & (now.ids == ids["stays"])).any()


@pytest.mark.parametrize("seed", [0, 7])
def test_table_stations_change_what_they_name_and_keep_the_room(seed):
    """sim_fixtures.stations: every kind of change touches only the things on the table, as
    named (all_moved: every one of them), each on the table top; the table, the room and the
    camera stay; the camera looks down at the table and sees it, the wall and the floor."""
    from sim_fixtures.stations import CHANGES, station_spec

    kinds = {"none": set(), "one_moved": {"moved"}, "one_removed": {"removed"},
             "one_added": {"added"}, "all_moved": {"moved"}}
    for change in CHANGES:
        spec = station_spec(seed, change)
        found = diff_layouts(spec.reference, spec.current)
        assert {c.kind for c in found} == kinds[change]
        assert all(c.name.startswith(("item", "new")) for c in found)
        items = [o for o in spec.reference if o.name.startswith("item")]
        if change == "all_moved":
            assert len(found) == len(items) >= 3
        elif change != "none":
            assert len(found) == 1
        table = next(o for o in spec.reference if o.name == "table")
        top = table.parts[0]
        lo = np.asarray(top.center) - np.asarray(top.size) / 2
        hi = np.asarray(top.center) + np.asarray(top.size) / 2
        for obj in spec.current:
            if obj.name.startswith(("item", "new")):
                corners = obj.corners()
                assert corners[:, 2].min() == pytest.approx(hi[2])  # stands on the top
                assert (corners[:, :2] >= lo[:2] - 0.05).all()  # a turned box's corners
                assert (corners[:, :2] <= hi[:2] + 0.05).all()  # stay near it
        assert spec.reference_pose == spec.current_pose
        ref, _cur = render_pair(spec)
        ids = object_ids(spec)
        for name in ("table", "floor", "wall_north"):
            assert (ref.ids == ids[name]).mean() > 0.05, name
        assert spec.reference_pose.pitch_deg > 20.0
    moved = station_spec(seed, "none", offset=(0.10, 4.0, 3)).current_pose
    shift = np.subtract(moved.position, station_spec(seed, "none").reference_pose.position)
    assert np.linalg.norm(shift) == pytest.approx(0.10)
    with pytest.raises(ValueError, match="change must be one of"):
        station_spec(seed, "everything_gone")


def test_a_station_check_carries_its_truth():
    """sim_fixtures.stations.station_scene: 3 reference frames and 1 current frame, each its
    own noise; the truth says only what changed (nothing for none, appeared for added,
    disappeared for removed, both for moved), on surfaces the frames read; with no change at
    the station each camera observes every surface the other read, 10 cm away not quite;
    station_pair fuses the same
    frames; station_checks names every change at every level."""
    from sim_fixtures.stations import CHANGES, station_checks, station_pair, station_scene

    expect = {"none": (False, False), "one_added": (True, False),
              "one_removed": (False, True), "one_moved": (True, True)}
    seed = 3
    for change, (app, dis) in expect.items():
        sc = station_scene(seed, change)
        assert sc.reference_frames.shape == (3, 480, 640) and sc.current.shape == (480, 640)
        assert sc.reference_frames.dtype == sc.current.dtype == np.uint16
        assert not np.array_equal(sc.reference_frames[0], sc.reference_frames[1])
        assert bool(sc.truth_appeared.any()) == app and bool(sc.truth_disappeared.any()) == dis
        if app:
            assert (sc.current[sc.truth_appeared] > 0).mean() > 0.5
        np.testing.assert_allclose(sc.T_ref_from_cur, np.eye(4), atol=1e-12)
        if change == "none":
            assert sc.observed_reference[sc.reference_frames[0] > 0].all()
            assert sc.observed_current[sc.current > 0].all()
    away = station_scene(seed, "one_moved", (0.10, 4.0, 3))
    assert 0.5 < away.observed_reference[away.reference_frames[0] > 0].mean() < 0.999
    fused, cur, truth, _ = station_pair(seed, "one_moved", (0.10, 4.0, 3))
    np.testing.assert_array_equal(fused, np.median(away.reference_frames, axis=0))
    np.testing.assert_array_equal(cur, away.current)
    np.testing.assert_array_equal(truth, away.T_ref_from_cur)
    checks = list(station_checks(2, 40, "t", (0, 10)))
    assert len(checks) == 2 * 2 * len(CHANGES) and len({c[0] for c in checks}) == len(checks)
    assert all((c[3] is None) == c[0].endswith(("_0cm_40", "_0cm_41")) for c in checks)


# ----------------------------------------------------------------------------- fixtures


def all_scenes():
    return [load_scene(n) for n in scene_names()]


def test_catalogue_matches_stored_scenes():
    stored = scene_names()
    assert sorted(SCENES) == stored
    for name in stored:
        assert load_scene(name).split == SCENES[name].split
    holdout = scene_names("holdout")
    assert set(holdout) | set(scene_names("dev")) == set(stored)
    assert 0.25 <= len(holdout) / len(stored) <= 0.45
    kinds = {load_scene(n).change for n in stored}
    assert {"added", "removed", "moved", "none", "none_jitter", "two", "small"} <= kinds
    sigmas = sorted(load_scene(n).meta["noise"].get("sigma_m", 0) for n in stored
                    if load_scene(n).meta["noise"]["model"] == "gaussian")
    assert sigmas == [0.001, 0.01, 0.1]


def test_stored_files_match_scene_json():
    total = 0
    assert FORMAT_VERSION == LOADER_FORMAT_VERSION
    for scene in all_scenes():
        meta = scene.meta
        stored = {str(p.relative_to(scene.folder)) for p in scene.folder.rglob("*") if p.is_file()}
        assert stored == set(meta["bytes"]) | {"scene.json"}  # nothing unlisted, nothing missing
        if scene.revisits is not None:  # shares the reference of the scene it revisits
            assert meta["files"]["reference"] == f"../{scene.revisits}/reference.oni"
            assert scene.recording("reference") == load_scene(scene.revisits).recording(
                "reference")
        for epoch in ("reference", "current"):
            info = read_oni_header(scene.recording(epoch))
            rec = meta["recordings"][epoch]
            assert rec["file"] == meta["files"][epoch]
            assert scene.recording(epoch).name == Path(rec["file"]).name
            assert info.frames == rec["frames"] == meta["frame_counts"][epoch] >= 2
            assert info.codec == rec["codec"] and (info.width, info.height) == (640, 480)
            assert info.intrinsics() == Intrinsics.openni_default()
        for rel, size in meta["bytes"].items():
            assert (scene.folder / rel).stat().st_size == size, rel
            total += size
        for frame in scene.reference_frames() + scene.current_frames():
            assert frame.dtype == np.uint16 and frame.shape == (480, 640)
            assert (frame > 0).mean() > 0.6
            assert frame[frame > 0].min() >= 400 and frame.max() <= 7000  # rooms up to 6 m
            if meta["noise"]["model"] == "kinect":
                assert frame.max() <= 1000 * meta["noise"]["far_m"]
        assert scene.truth_appeared.shape == scene.truth_disappeared.shape == (480, 640)
        assert scene.intrinsics == Intrinsics.openni_default()
        assert meta["truth"]["appeared_pixels"] == scene.truth_appeared.sum()
        assert meta["truth"]["disappeared_pixels"] == scene.truth_disappeared.sum()
        assert meta["noise"]["model"] in ("kinect", "gaussian") and isinstance(meta["seed"], int)
    assert total < 34e6  # the budget is 40 MB for the whole folder; keep below
    folder = sum(p.stat().st_size for p in FIXTURES_ROOT.rglob("*") if p.is_file()
                 and "__pycache__" not in p.parts)
    assert folder < 36e6


def test_kinect_scenes_are_stored_in_16zt():
    codecs = {(s.meta["noise"]["model"], s.meta["recordings"][e]["codec"])
              for s in all_scenes() for e in ("reference", "current")}
    assert {c for m, c in codecs if m == "kinect"} == {"16zT"}  # quantised: the table pays
    assert {c for m, c in codecs if m == "gaussian"} <= {"16zP", "NONE", "16zT"}


def test_stored_truth_is_consistent_with_object_ids():
    for scene in all_scenes():
        changes = scene.changes
        ids_ref, ids_cur = scene.object_ids("reference"), scene.object_ids("current")
        new = [c["id"] for c in changes if c["kind"] in ("added", "moved")]
        gone = [c["id"] for c in changes if c["kind"] in ("removed", "moved")]
        np.testing.assert_array_equal(scene.truth_appeared, np.isin(ids_cur, new))
        np.testing.assert_array_equal(scene.truth_disappeared, np.isin(ids_ref, gone))
        if scene.change.startswith("none") or scene.change == "not_at_station":
            assert not changes and not scene.truth_appeared.any()
            assert not scene.truth_disappeared.any()
        else:
            assert changes and (scene.truth_appeared.any() or scene.truth_disappeared.any())
            expected = {"two": 2}.get(scene.change, 1)
            assert len(changes) == expected, scene.name
        for c in changes:
            for side, ids in (("before", ids_ref), ("after", ids_cur)):
                if side in c:
                    assert c[side]["visible_pixels"] == (ids == c["id"]).sum() > 300
                    assert 0.5 < c[side]["centroid_m"][2] < 5.0
        if scene.change == "small":
            extent = changes[0]["after"]["extent_m"]
            assert max(extent) < 0.2 and 2.0 < changes[0]["after"]["centroid_m"][2] < 3.0
        if scene.change == "none_jitter":
            ref, cur = scene.meta["camera"]["reference"], scene.meta["camera"]["current"]
            shift = np.subtract(ref["position_m"], cur["position_m"])
            assert 0.005 < np.linalg.norm(shift) < 0.02
            assert 0.2 < abs(ref["yaw_deg"] - cur["yaw_deg"]) <= 0.6


def test_revisits_are_displaced_as_named_with_truth_the_other_camera_can_see():
    from robot_change.change.registration import rotation_angle_deg
    from sim_fixtures.scenes import POSE_LEVELS

    revisits = [n for n in scene_names() if "_pose_" in n]
    assert len(revisits) == 21 and len(scene_names("holdout")) >= 9
    for name in revisits:
        scene = load_scene(name)
        base = load_scene(scene.revisits)
        translation, rotation = POSE_LEVELS[name[name.index("pose_"):]]
        T = scene.T_ref_from_cur
        assert abs(np.linalg.norm(T[:3, 3]) - translation) < 1e-9
        assert 0.7 * rotation < rotation_angle_deg(T[:3, :3]) < 1.3 * rotation
        assert scene.split == base.split and scene.has_change == base.has_change
        # the camera moved: a part of each view is outside the other, the rest is seen
        for observed in (scene.observed_reference, scene.observed_current):
            assert 0.5 < observed.mean() < 1.0
        np.testing.assert_array_equal(base.truth_disappeared, scene.truth_disappeared)
    for name in ("office_far_offset", "storage_other_room"):
        assert load_scene(name).change == "not_at_station"


def test_regenerating_a_scene_reproduces_the_stored_files(tmp_path):
    name = "lab_crate_moved"
    spec, scene = SCENES[name], load_scene(name)
    ref, cur = render_pair(spec)
    for epoch, (r, label) in enumerate(((ref, "reference"), (cur, "current"))):
        stored = scene.frames(label)
        frames = noisy_frames(spec, r, epoch, len(stored))
        for frame, again in zip(frames, stored, strict=True):
            np.testing.assert_array_equal(frame, again)
        # the writer is deterministic: the same frames give a byte-identical file
        (tmp_path / label).mkdir()
        assert write_oni_recording(tmp_path / label, frames, spec) == [f"{label}.oni"]
        assert (tmp_path / f"{label}.oni").read_bytes() == scene.recording(label).read_bytes()
    appeared, disappeared = truth_masks(spec, ref, cur)
    np.testing.assert_array_equal(appeared, scene.truth_appeared)
    np.testing.assert_array_equal(disappeared, scene.truth_disappeared)
    np.testing.assert_array_equal(cur.ids, scene.object_ids("current"))
    assert scene.meta["seed"] == spec.seed
    assert scene.meta["noise"] == json.loads(json.dumps(spec.noise.to_json()))


def test_loader_errors_and_uri():
    with pytest.raises(UnknownScene) as info:
        load_scene("no_such_scene")
    assert "office_box_added" in str(info.value) and isinstance(info.value, KeyError)
    with pytest.raises(ValueError):
        scene_names("train")
    scene = load_scene("office_no_change")
    with pytest.raises(ValueError, match="epoch"):
        scene.uri("later")
    with pytest.raises(ValueError, match="kind"):
        scene.uri("current", "tiff")
    assert scene.uri("current") == f"oni:{SCENES_DIR / 'office_no_change' / 'current.oni'}"
    assert SCENES_DIR.is_dir()


def read_all(uri):
    frames = []
    with open_depth(uri) as source:
        while (frame := source.read(5.0)) is not None:
            frames.append(frame)
    return frames


@pytest.mark.parametrize("name", ["office_box_added", "paper_sigma_100mm"])
def test_stored_recordings_play_through_openni2_and_as_images(name, tmp_path, monkeypatch):
    import sim_fixtures

    monkeypatch.setattr(sim_fixtures, "IMAGE_CACHE", tmp_path / "cache")
    scene = load_scene(name)
    for epoch in ("reference", "current"):
        expected = scene.frames(epoch)
        played = read_all(scene.uri(epoch))  # the real libOpenNI2 player
        assert [f.index for f in played] == list(range(1, len(expected) + 1))
        assert [f.timestamp_us for f in played] == \
            [round(k * 1e6 / 30) for k in range(len(expected))]
        as_images = read_all(scene.uri(epoch, "images"))  # PNG copies in the cache
        assert len(played) == len(as_images) == len(expected) == 3
        for a, b, c in zip(played, as_images, expected, strict=True):
            np.testing.assert_array_equal(a.depth, c)
            np.testing.assert_array_equal(b.depth, c)
        assert played[0].intrinsics == scene.intrinsics
    copies = sorted((tmp_path / "cache").iterdir())
    assert len(copies) == 2 and all(len(list(c.glob("*.png"))) == 3 for c in copies)
    scene.uri("current", "images")  # reused, not written again
    assert sorted((tmp_path / "cache").iterdir()) == copies


def test_demo_frame_is_a_mostly_valid_room():
    depth = read_image(DEMO_FRAME)
    assert depth.dtype == np.uint16 and depth.shape == (480, 640)
    valid = depth > 0
    assert valid.mean() > 0.9
    assert 500 <= depth[valid].min() and depth[valid].max() <= 5000
    assert 1000 < np.median(depth[valid]) < 4000
    meta = json.loads(DEMO_FRAME.with_suffix(".json").read_text())
    assert meta["valid_fraction"] == pytest.approx(valid.mean(), abs=1e-4)


def test_oni_writer_picks_the_smallest_codec(tmp_path):
    spec = SCENES["paper_sigma_1mm"]
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:480, 0:640]
    ramp = 1000 + 4 * yy + xx  # smooth, every step small in mm: 16z
    kinect = (ramp // 25) * 25  # quantised: large steps in mm, index steps 0/1: 16zt
    noise = rng.integers(0, 30000, (480, 640))  # incompressible: raw
    big = ramp + 40000  # beyond 16z, few values: 16zt
    for frames, codec, four_cc in ((ramp, "16z", "16zP"), (kinect, "16zt", "16zT"),
                                   (noise, "none", "NONE"), (big, "16zt", "16zT")):
        frames = [frames.astype(np.uint16), frames[::-1].astype(np.uint16)]
        assert best_codec(frames) == codec
        (tmp_path / "reference").mkdir(exist_ok=True)
        assert write_oni_recording(tmp_path / "reference", frames, spec) == ["reference.oni"]
        info = read_oni_header(tmp_path / "reference.oni")
        assert (info.width, info.height, info.frames, info.codec) == (640, 480, 2, four_cc)
        for got, want in zip(read_oni_frames(tmp_path / "reference.oni"), frames, strict=True):
            np.testing.assert_array_equal(got.depth, want)
