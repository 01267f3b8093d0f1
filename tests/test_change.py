"""robot_change.change.detect: change detection on simulated scenes, the switches, bad input, and
the numba kernels against NumPy twins.  Kept fast: four scenes, each built once per module."""

from __future__ import annotations

import collections
import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from hw.depth import Intrinsics
from robot_change.change import free_space, greedy
from robot_change.change.baselines import (
    detect_geometric,
    detect_nn_threshold,
    detect_plain,
)
from robot_change.change.detect import detect_changes
from robot_change.change.free_space import free_space_votes
from robot_change.change.params import ChangeParams
from robot_change.change.regions import label_voxel_components
from robot_change.change.results import ChangeSet
from robot_change.change.scene import SceneParams, build_scene
from robot_change.cloud.chain import CloudParams
from robot_change.cloud.voxels import pack_keys
from robot_change.errors import EmptySceneError, InputError, SceneMismatchError
from robot_change.noise.kernels import table_sigma
from robot_change.noise.profile import DEFAULT_PROFILE, builtin_profile
from sim_fixtures import load_scene

SCENES = ("office_box_added", "office_no_change", "lounge_chair_removed", "lab_crate_moved")


@pytest.fixture(scope="module")
def models():
    out = {}
    for name in SCENES:
        sc = load_scene(name)
        ref = build_scene(sc.reference_frames(), intrinsics=sc.intrinsics)
        cur = build_scene(sc.current_frames(), intrinsics=sc.intrinsics)
        out[name] = (sc, ref, cur)
    return out


@pytest.fixture(scope="module")
def results(models):
    return {name: detect_changes(ref, cur) for name, (_, ref, cur) in models.items()}


def _near(region, centroid, tol=0.15):
    return float(np.linalg.norm(region.centroid - np.asarray(centroid))) < tol


# --------------------------------------------------------------------------- behaviour


def test_box_added_is_one_appeared_region_at_the_box(models, results):
    sc, ref, cur = models["office_box_added"]
    cs = results["office_box_added"]
    assert isinstance(cs, ChangeSet) and cs.changed
    assert len(cs.appeared) == 1 and cs.disappeared == ()
    r = cs.appeared[0]
    assert _near(r, sc.changes[0]["after"]["visible_centroid_m"])
    assert r.kind == "appeared" and r.n_points == len(r.point_index) > 50
    assert np.all(r.extent > 0.1) and np.all(r.extent < 0.8)
    assert r.components and all(c >= cs.k_reference for c in r.components)  # novelty comps
    assert cs.appeared_points.dtype == np.float32 and cs.appeared_points.shape == (r.n_points, 3)
    assert cs.appeared_mask.shape == cur.depth.shape and cs.appeared_mask.sum() == r.n_pixels
    # the pixels reported are the box's
    assert (cs.appeared_mask & sc.truth_appeared).sum() / cs.appeared_mask.sum() > 0.95
    assert cs.k_reference == ref.mixture.n_components
    assert cs.timings_ms["detect_ms"] > 0


def test_removal_is_disappeared(models, results):
    sc, ref, _ = models["lounge_chair_removed"]
    cs = results["lounge_chair_removed"]
    assert cs.changed and cs.appeared == () and cs.disappeared
    assert _near(cs.disappeared[0], sc.changes[0]["before"]["visible_centroid_m"], 0.25)
    assert cs.disappeared_mask.shape == ref.depth.shape
    assert (cs.disappeared_mask & sc.truth_disappeared).sum() / cs.disappeared_mask.sum() > 0.95


def test_moved_is_both(models, results):
    sc, _, _ = models["lab_crate_moved"]
    cs = results["lab_crate_moved"]
    assert len(cs.appeared) == 1 and len(cs.disappeared) == 1
    assert _near(cs.appeared[0], sc.changes[0]["after"]["visible_centroid_m"], 0.25)
    assert _near(cs.disappeared[0], sc.changes[0]["before"]["visible_centroid_m"], 0.25)


def test_no_change_reports_nothing(results):
    cs = results["office_no_change"]
    assert not cs.changed and cs.regions == ()
    assert cs.appeared_points.shape == (0, 3) and cs.disappeared_points.shape == (0, 3)
    assert not cs.appeared_mask.any() and not cs.disappeared_mask.any()
    s = cs.summary()
    assert s["changed"] is False and s["regions"] == []


def test_current_as_depth_array_matches_scene_model(models):
    sc, ref, cur = models["office_box_added"]
    frame = sc.current_frames()[0]
    cs = detect_changes(ref, frame, intrinsics=sc.intrinsics)
    assert len(cs.appeared) == 1 and cs.disappeared == ()
    assert "current_cloud_ms" in cs.timings_ms and "current_fit_ms" in cs.timings_ms
    assert _near(cs.appeared[0], sc.changes[0]["after"]["visible_centroid_m"])


def test_a_removed_objects_component_leaves_the_current_mixture():
    # meeting_two_changes: a removed object at 2.3 m; EM from the reference's components
    # pulled the object's onto the wall it had hidden, where it still explained the object's
    # rear third (the daemon's path, a depth array, found 626 of its 820 points).  A
    # component whose reference points the current camera sees through goes.
    sc = load_scene("meeting_two_changes")
    ref = build_scene(sc.reference_frames(), intrinsics=sc.intrinsics)
    cur = build_scene(sc.current_frames(), intrinsics=sc.intrinsics)

    def removed_points(current, params=None):
        if params is None:
            params = ChangeParams()
        cs = detect_changes(ref, current, params,
                            intrinsics=None if current is cur else sc.intrinsics)
        return max(r.n_points for r in cs.disappeared if _near(r, (0.52, -0.12, 2.27), 0.3))

    own_fit = removed_points(cur)  # the current's own split-EM fit
    as_daemon = removed_points(np.array(cur.depth))
    assert as_daemon >= 0.95 * own_fit
    # with no component taken as gone, the old loss comes back: the rule is what finds them
    assert removed_points(np.array(cur.depth), ChangeParams(gone_component_share=1.0)) \
        < 0.85 * own_fit


def test_a_point_the_background_does_not_explain_is_not_its_evidence():
    # station 8003, one object moved, the robot 10 cm / 4 deg off: the current's own fit
    # has a narrow component on the object's new place, 15 cm from its old one, and the
    # novelty component seeded on the old place spreads over 0.3 m.  On posteriors alone the
    # narrow component won the old place (0 of its 82 points found), although its density
    # there is far below what it gives its own points
    from sim_fixtures.stations import station_checks, station_scene
    from sim_fixtures.truth import point_truth

    offset = next(o for _, seed, change, o in station_checks(10, 8000, "", (10,))
                  if seed == 8003 and change == "one_moved")
    sc = station_scene(8003, "one_moved", offset)
    ref = build_scene(list(sc.reference_frames), intrinsics=sc.intrinsics)
    cur = build_scene([sc.current], intrinsics=sc.intrinsics)
    cs = detect_changes(ref, cur, ChangeParams(object_completion=False))
    truth = point_truth(ref.pixel_voxel, sc.truth_disappeared & sc.observed_reference,
                        len(ref))
    found = np.zeros(len(ref), bool)
    found[cs.disappeared_index] = True
    assert truth.sum() > 50 and (found & truth).sum() >= 0.8 * truth.sum()
    assert not (found & ~truth).any()


def test_components_seen_through_counts_each_point_once():
    from robot_change.change.detect import _components_seen_through
    from robot_change.change.epoch import Epoch
    from robot_change.mixture.model import Mixture

    rng = np.random.default_rng(3)
    centres = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.0]])
    points = np.concatenate([c + 0.02 * rng.standard_normal((200, 3)) for c in centres])
    mix = Mixture(np.full(3, 1 / 3), centres, np.tile(np.eye(3) * 4e-4, (3, 1, 1)))
    ref = Epoch(np.zeros((4, 4), np.uint16), Intrinsics(4, 4, 3.0, 3.0, 1.5, 1.5),
                points.astype(np.float32), np.arange(len(points), dtype=np.int64),
                np.full((4, 4), -1, np.int32), 0.03, mix)
    through = np.zeros(len(points), dtype=bool)
    through[:150] = True  # 3/4 of the first component
    through[200:290] = True  # 45 % of the second
    assert _components_seen_through(ref, mix, through, 0.5).tolist() == [True, False, False]
    assert _components_seen_through(ref, mix, through, 0.4).tolist() == [True, True, False]


def test_summary_is_json_ready(results):
    import json

    s = json.loads(json.dumps(results["lab_crate_moved"].summary()))
    assert {r["kind"] for r in s["regions"]} == {"appeared", "disappeared"}
    assert s["greedy_appeared"]["emd_after"]


# --------------------------------------------------------------------------- switches


def test_free_space_off_reports_uncovered_background(models, results):
    # Behind the removed chair the wall is now seen: novelty components cover it, and only the
    # free-space check knows the reference never saw through it.
    _, ref, cur = models["lounge_chair_removed"]
    assert results["lounge_chair_removed"].appeared == ()
    cs = detect_changes(ref, cur, ChangeParams(free_space=False, novelty_seed="density"))
    assert cs.appeared


def test_plain_method_uses_independent_fits(models):
    _, ref, cur = models["office_box_added"]
    cs = detect_changes(ref, cur, ChangeParams(novelty=False, free_space=False))
    assert cs.method == "plain"
    assert cs.appeared_mixture is cur.mixture
    # the reference's own fit, moved into the current camera frame by the registration
    moved = ref.mixture.transformed(cs.registration.inverse())
    np.testing.assert_array_equal(cs.disappeared_mixture.weights, ref.mixture.weights)
    np.testing.assert_allclose(cs.disappeared_mixture.means, moved.means)
    np.testing.assert_allclose(cs.disappeared_mixture.covariances, moved.covariances)
    assert cs.greedy_appeared.candidates.size == cur.mixture.n_components
    assert detect_plain(ref, cur).method == "plain"


def test_greedy_switch_uses_the_acceptance_rule(models, results):
    _, ref, cur = models["office_box_added"]
    off = results["office_box_added"].greedy_appeared
    assert np.array_equal(off.change, off.candidates)  # greedy off: every novelty component
    on = detect_changes(ref, cur, ChangeParams(greedy=True)).greedy_appeared
    assert np.array_equal(np.sort(on.order[:on.accepted]), on.change)
    strict = detect_changes(ref, cur, ChangeParams(greedy=True, accept_min_drop_m=10.0))
    assert strict.greedy_appeared.accepted == 0 and not strict.changed


def test_accept_trajectory_rule():
    p = ChangeParams(accept_min_drop_m=0.01, accept_min_drop_rel=0.1, min_region_points=5)
    w = np.array([0.5, 0.3, 0.1, 0.1])
    emd_after = np.array([1.0, 0.5, 0.45, 0.1])  # drops 0.5, 0.05 (< 0.1 * 1.0), 0.35
    assert greedy.accept_trajectory(np.array([1, 2, 3]), emd_after, w, 100, p) == 1
    assert greedy.accept_trajectory(np.array([1, 2, 3]), emd_after, w, 10, p) == 0  # 3 points


def test_ground_distance_changes_the_emd(models):
    _, ref, cur = models["office_box_added"]
    e = detect_changes(ref, cur, ChangeParams(ground_distance="euclidean"))
    w = detect_changes(ref, cur, ChangeParams(ground_distance="wasserstein2"))
    assert e.greedy_appeared.emd_after[0] < w.greedy_appeared.emd_after[0]


def test_disappeared_off_min_region_and_connectivity(models):
    _, ref, cur = models["lab_crate_moved"]
    cs = detect_changes(ref, cur, ChangeParams(disappeared=False))
    assert cs.appeared and cs.disappeared == () and cs.greedy_disappeared is None
    assert not detect_changes(ref, cur, ChangeParams(min_region_points=10**6)).changed
    loose = detect_changes(ref, cur, ChangeParams(region_connectivity=2))
    assert len(loose.appeared) == 1


def test_baselines(models):
    _, ref, cur = models["office_box_added"]
    nn = detect_nn_threshold(ref, cur)
    geo = detect_geometric(ref, cur)
    assert nn.method == "nn" and geo.method == "geometric"
    assert len(geo.appeared) == 1 and geo.appeared_mixture is None
    assert nn.appeared_points.shape[0] >= geo.appeared_points.shape[0]
    fs = detect_nn_threshold(ref, cur, ChangeParams(nn_check_m=0.0, free_space=True))
    assert fs.method == "free_space" and len(fs.appeared) == 1
    with pytest.raises(InputError):
        detect_nn_threshold(ref, cur, ChangeParams(nn_check_m=0.0, free_space=False))


# --------------------------------------------------------------------------- bad input


def test_params_are_validated():
    for bad in (dict(novelty_quantile=0.0), dict(ground_distance="l1"), dict(greedy=1),
                dict(posterior_threshold=1.5), dict(posterior_threshold=1.0),
                dict(region_connectivity=0),
                dict(free_space_sigmas=-1.0), dict(novelty_seed="x"),
                dict(gone_component_share=1.5), dict(gone_component_share="half"),
                dict(free_space_pose_m=-0.01), dict(free_space_pose_m="1 cm"),
                dict(free_space_hole_needs_far_edge="yes")):
        with pytest.raises(InputError, match="ChangeParams"):
            ChangeParams(**bad)
    with pytest.raises(InputError):
        detect_changes(None, None, params="fast")  # type: ignore[arg-type]


def test_mismatched_intrinsics_or_params_raise(models):
    sc, ref, cur = models["office_box_added"]
    frame = sc.current_frames()[0]
    other = dataclasses.replace(sc.intrinsics, fx=500.0, fy=500.0)
    with pytest.raises(SceneMismatchError, match="intrinsics"):
        detect_changes(ref, frame, intrinsics=other)
    with pytest.raises(SceneMismatchError):
        detect_changes(ref, frame[:240], intrinsics=dataclasses.replace(
            sc.intrinsics, height=240, cy=119.5))
    leaf = ref.params.cloud.leaf_m * 1.5
    coarse = build_scene([frame], SceneParams(cloud=CloudParams(leaf_m=leaf)),
                         intrinsics=sc.intrinsics)
    with pytest.raises(SceneMismatchError, match="leaf_m"):
        detect_changes(ref, coarse)


def test_intrinsics_within_the_tolerance_are_one_camera_and_another_size_is_a_mismatch(models):
    """check_compatible took fx 1e-6 px apart (INTRINSICS_TOLERANCE_PX) and detect_changes
    refused it; a frame of another size without intrinsics was a bare InputError."""
    from hw.depth import Intrinsics

    sc, ref, _ = models["office_box_added"]
    frame = sc.current_frames()[0]
    k = ref.intrinsics
    near = Intrinsics(k.width, k.height, k.fx + 1e-6, k.fy, k.cx - 1e-4, k.cy)
    same = detect_changes(ref, frame)
    nearly = detect_changes(ref, frame, intrinsics=near)
    assert nearly.outcome == same.outcome == "changed"
    assert np.array_equal(nearly.appeared_points, same.appeared_points)
    with pytest.raises(SceneMismatchError, match="does not match the reference"):
        detect_changes(ref, np.ascontiguousarray(frame[::2, ::2]))
    far = Intrinsics(k.width, k.height, k.fx + 0.01, k.fy, k.cx, k.cy)
    with pytest.raises(SceneMismatchError, match="fx"):
        detect_changes(ref, frame, intrinsics=far)


def test_a_library_users_slips_are_named(models):
    """A list of frames from a source that ended holds None; a DepthFrame passed as the
    current: each error names what is wrong (it said 'mixes DepthFrames and arrays (item 0)'
    and "'DepthFrame' object has no attribute 'points'")."""
    from hw.depth import DepthFrame

    sc, ref, _ = models["office_box_added"]
    frames = [DepthFrame(d, k, k, sc.intrinsics) for k, d in enumerate(sc.current_frames())]
    with pytest.raises(InputError, match=r"frame 3 is None \(a source that ended"):
        build_scene(frames + [None, None])
    with pytest.raises(InputError, match="current is a DepthFrame: pass its .depth"):
        detect_changes(ref, frames[0])
    with pytest.raises(InputError, match=r"np.where\(np.isfinite\(z\)"):
        detect_changes(ref, frames[0].depth.astype(np.float32) / 1000)


def test_a_reference_keeps_a_few_results_per_kind_as_parameters_vary(models):
    """A node that varies its parameters (a tunable slider) grew the reference's derived
    results by one per value (88 MiB after 40): now at most KEPT_PER_KIND of a kind, and the
    answers are those of a fresh reference."""
    from robot_change.change.epoch import KEPT_PER_KIND

    sc, _, _ = models["office_box_added"]
    ref = build_scene(sc.reference_frames(), intrinsics=sc.intrinsics)
    frame = sc.current_frames()[0]
    for i in range(8):
        got = detect_changes(ref, frame, ChangeParams(free_space_sigmas=2.5 + 0.1 * i,
                                                      object_fold_deg=20.0 + i))
    kinds = collections.Counter(k[0] for k in ref.derived)
    assert max(kinds.values()) <= KEPT_PER_KIND and kinds["segment_pixels"] == KEPT_PER_KIND
    fresh = build_scene(sc.reference_frames(), intrinsics=sc.intrinsics)
    again = detect_changes(fresh, frame, ChangeParams(free_space_sigmas=3.2, object_fold_deg=27.0))
    assert np.array_equal(got.appeared_points, again.appeared_points)


def test_camera_sees_nothing_is_a_typed_error(models):
    # Deliberately an error, not "no change": an all-zero frame may be a covered lens or
    # something closer than the sensor's minimum range.
    sc, ref, _ = models["office_box_added"]
    blank = np.zeros((480, 640), np.uint16)
    with pytest.raises(EmptySceneError, match="current"):
        detect_changes(ref, blank, intrinsics=sc.intrinsics)
    too_close = np.full((480, 640), 300, np.uint16)  # 0.3 m, below min_depth_m
    with pytest.raises(EmptySceneError):
        detect_changes(ref, too_close, intrinsics=sc.intrinsics)


def test_a_view_that_reads_little_of_the_station_is_a_typed_error_not_no_change(models):
    """A lens covered 90 % (or held up close) left a view whose last tenth registered and
    compared as unchanged: `no_change`.  Now the share of the reference's readings the view
    does not read (0.9) says it cannot tell; a view blind on a third of it still compares."""
    sc, ref, _ = models["office_no_change"]
    frame = sc.current_frames()[0]
    covered = frame.copy()
    covered[:, :576] = 0
    with pytest.raises(EmptySceneError, match=r"reads nothing where the reference read [89]\d%"):
        detect_changes(ref, covered, intrinsics=sc.intrinsics)
    held_close = frame.copy()
    held_close[:, :576] = 250  # a hand 25 cm away: nearer than the camera's minimum range
    with pytest.raises(EmptySceneError, match="nearer than the camera's minimum range"):
        detect_changes(ref, held_close, intrinsics=sc.intrinsics)
    third = frame.copy()
    third[:, :213] = 0
    assert detect_changes(ref, third, intrinsics=sc.intrinsics).outcome == "no_change"


# --------------------------------------------------------------------------- numba twins


def _window_twin(depth, radius, take_min):
    size = 2 * radius + 1
    if take_min:
        d = np.where(depth > 0, depth.astype(np.int64), 65535)
        out = ndimage.minimum_filter(d, size=size, mode="nearest")
        return np.where(out == 65535, 0, out).astype(np.uint16)
    return ndimage.maximum_filter(depth, size=size, mode="nearest").astype(np.uint16)


@pytest.mark.parametrize("radius", [1, 3])
def test_window_filter_matches_numpy(radius):
    rng = np.random.default_rng(radius)
    depth = rng.integers(500, 4000, size=(37, 53)).astype(np.uint16)
    depth[rng.random(depth.shape) < 0.3] = 0
    depth[5:20, 10:30] = 0  # a hole wider than the window
    for take_min in (True, False):
        np.testing.assert_array_equal(free_space._window_filter(depth, radius, take_min),
                                      _window_twin(depth, radius, take_min))


def _warp_twin(own, T, intr, depth_range, window=None, pv=None):
    """NumPy twin of free_space._warp_kernel: (target (P,), z_other (P,)); pixels without a
    point (``pv`` < 0) are not warped."""
    h, w = own.shape
    rows, cols = np.mgrid[0:h, 0:w]
    z = own.astype(np.float64).ravel() * 0.001
    x = (cols.ravel() - intr.cx) * z / intr.fx
    y = (rows.ravel() - intr.cy) * z / intr.fy
    p = np.stack([x, y, z], axis=1) @ T[:3, :3].T + T[:3, 3]
    pz = p[:, 2]
    ok = (own.ravel() > 0) & (pz >= depth_range[0]) & (pz <= depth_range[1])
    zsafe = np.where(ok, pz, 1.0)
    u = np.floor(intr.fx * p[:, 0] / zsafe + intr.cx + 0.5).astype(np.int64)
    v = np.floor(intr.fy * p[:, 1] / zsafe + intr.cy + 0.5).astype(np.int64)
    r0, r1, c0, c1 = window if window is not None else (0, h - 1, 0, w - 1)
    ok &= (u >= c0) & (v >= r0) & (u <= c1) & (v <= r1)
    has = own.ravel() > 0
    if pv is not None:
        has &= pv.ravel() >= 0
    ok &= has
    target = np.where(has, -2, -1)
    target[ok] = v[ok] * w + u[ok]
    return target, np.where(ok, pz, 0.0)


def _row_neighbours_twin(depth):
    """(left_mm, left_px, right_mm, right_px): the first reading left / right of each pixel
    along its row, and how far; 0 where none."""
    h, w = depth.shape
    out = [np.zeros((h, w), np.uint16), np.zeros((h, w), np.int32),
           np.zeros((h, w), np.uint16), np.zeros((h, w), np.int32)]
    for r in range(h):
        cols = np.flatnonzero(depth[r] > 0)
        for c in range(w):
            left, right = cols[cols < c], cols[cols > c]
            if left.size:
                out[0][r, c], out[1][r, c] = depth[r, left[-1]], c - left[-1]
            if right.size:
                out[2][r, c], out[3][r, c] = depth[r, right[0]], right[0] - c
    return out


#: The default profile's sigma table (robot_change.noise.kernels.sigma_at reads it).
NOISE = builtin_profile(DEFAULT_PROFILE).kernel_table()


def _margin(z, sigmas, pose_m):
    """robot_change.noise.kernels.margin_at in NumPy."""
    s = table_sigma(NOISE, z)
    return sigmas * np.sqrt(2.0 * s * s + pose_m * pose_m)


def _unexplained_holes_twin(depth, dropout_px, shadow_bf, sigmas, pose_m):
    """(H, W) bool: pixels with no reading whose run along the row is wider than
    ``dropout_px``, meets the border, or is no projector shadow of the nearer reading beside
    it on the farther one."""
    left_mm, left_px, right_mm, right_px = _row_neighbours_twin(depth)
    width = left_px + right_px - 1
    both = (left_mm > 0) & (right_mm > 0)
    z_near = np.minimum(left_mm, right_mm) * 1e-3
    z_far = np.maximum(left_mm, right_mm) * 1e-3
    with np.errstate(divide="ignore"):
        shadow = (shadow_bf > 0) & (z_near < z_far - _margin(z_far, sigmas, pose_m)) & \
            (width <= shadow_bf * (1 / np.where(both, z_near, 1.0) - 1 / np.where(both, z_far, 1.0))
             + 1)
    return (depth == 0) & ~(both & ((width <= dropout_px) | shadow))


def _near_ray_clear_twin(q, own, back, intr, sensor_min_m, sigmas, pose_m, holes):
    """(len(q),) bool: this camera (image ``own``) reads beyond every sample of the other
    camera's ray through its pixels ``q`` (flat) at 0.4, 0.6, 0.8 and 1.0 x ``sensor_min_m``
    that lands in its image in front of it (``back``: other frame -> this frame), none lands
    in its unexplained ``holes`` (H, W) bool, and at least one lands in its image."""
    h, w = own.shape
    rays = np.stack([(q % w - intr.cx) / intr.fx, (q // w - intr.cy) / intr.fy,
                     np.ones(q.shape)], axis=1)
    clear = np.ones(q.shape, bool)
    seen = np.zeros(q.shape, bool)
    for frac in (0.4, 0.6, 0.8, 1.0):
        p = rays * (sensor_min_m * frac) @ back[:3, :3].T + back[:3, 3]
        front = p[:, 2] > 0.05
        z = np.where(front, p[:, 2], 1.0)
        c = np.floor(intr.fx * p[:, 0] / z + intr.cx + 0.5).astype(np.int64)
        r = np.floor(intr.fy * p[:, 1] / z + intr.cy + 0.5).astype(np.int64)
        inside = front & (c >= 0) & (c < w) & (r >= 0) & (r < h)
        rr, cc = np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)
        d = own[rr, cc] * 1e-3
        clear &= ~inside | np.where(d > 0, d > z + _margin(z, sigmas, pose_m), ~holes[rr, cc])
        seen |= inside
    return clear & seen


def _free_space_twin(pv, own, other, n, sigmas, pose_m, pose_r, hole_r, free_zero,
                     target=None, z_other=None, shadow_bf=0.0, sensor_min_m=0.0,
                     far_edge=False, back=None, intr=None):
    near = (_window_twin(other, pose_r, True) if pose_r else other).ravel()
    far = (_window_twin(other, hole_r, False) if hole_r else other).ravel()
    if target is None:
        target = np.where(own.ravel() > 0, np.arange(own.size), -1)
        z_other = own.astype(np.float64).ravel() * 1e-3
    pv = pv.ravel()
    valid = target >= 0
    q = np.where(valid, target, 0)
    d1 = np.where(near[q] > 0, near[q], far[q]).astype(np.float64) * 1e-3
    z = z_other
    margin = _margin(z, sigmas, pose_m)
    shadowed = np.zeros(q.shape, bool)
    opens = np.zeros(q.shape, bool)  # a first reading beside the hole lies beyond the point
    for mm, px in np.reshape(_row_neighbours_twin(other), (2, 2) + other.shape):
        zn = mm.ravel()[q] * 1e-3
        with np.errstate(divide="ignore"):
            reach = shadow_bf * (1.0 / np.where(zn > 0, zn, 1.0) - 1.0 / np.maximum(z, 1e-9))
        shadowed |= (zn > 0) & (shadow_bf > 0) & (zn < z - margin) & \
            (px.ravel()[q] <= reach + 1.0)
        opens |= zn > z + margin
    too_near = valid & (other.ravel()[q] == 0) & (z < sensor_min_m + margin)
    if sensor_min_m > 0:  # the near stretch of the other camera's ray, as this one saw it
        intr = intr or Intrinsics(own.shape[1], own.shape[0], 525.0, 525.0,
                                  (own.shape[1] - 1) / 2, (own.shape[0] - 1) / 2)
        holes = _unexplained_holes_twin(own, 2 * hole_r, shadow_bf, sigmas, pose_m)
        clear = _near_ray_clear_twin(q, own, np.eye(4) if back is None else back, intr,
                                     sensor_min_m, sigmas, pose_m, holes)
    else:
        clear = np.ones(q.shape, bool)
    read = valid & ~too_near & (d1 > 0) & (d1 > z + margin)
    seen = read | (valid & ~too_near & (d1 == 0) & free_zero & ~shadowed & (opens | ~far_edge)
                   & clear)
    ok = pv >= 0
    votes = np.bincount(pv[ok], weights=seen[ok], minlength=n).astype(np.int32)
    total = np.bincount(pv[ok], minlength=n).astype(np.int32)
    unseen = np.bincount(pv[ok], weights=(~valid | too_near)[ok], minlength=n).astype(np.int32)
    core = np.bincount(pv[ok], weights=read[ok], minlength=n).astype(np.int32)
    return votes, total, unseen, core


@pytest.mark.parametrize("pose_r,hole_r,free_zero,baseline,sensor_min,far_edge",
                         [(0, 0, True, 0.0, 0.0, False), (2, 4, False, 0.0, 0.0, False),
                          (3, 0, True, 0.0, 0.0, False), (1, 2, True, 0.075, 0.0, False),
                          (1, 2, True, 0.075, 1.5, True), (0, 0, True, 0.0, 1.0, True)])
def test_free_space_matches_numpy(pose_r, hole_r, free_zero, baseline, sensor_min, far_edge):
    rng = np.random.default_rng(7)
    h, w, n = 30, 40, 50
    own = rng.integers(800, 3000, size=(h, w)).astype(np.uint16)
    other = (own.astype(np.int64) + rng.integers(-600, 400, size=(h, w))).astype(np.uint16)
    other[rng.random((h, w)) < 0.3] = 0
    other[10:22, 5:30] = 0
    pv = rng.integers(-1, n, size=(h, w)).astype(np.int32)
    got = free_space_votes(pv, own, other, n, NOISE, 3.0, 0.01, pose_r, hole_r, free_zero,
                           shadow_baseline_m=baseline, sensor_min_m=sensor_min,
                           hole_needs_far_edge=far_edge)
    want = _free_space_twin(pv, own, other, n, 3.0, 0.01, pose_r, hole_r, free_zero,
                            shadow_bf=baseline * 525, sensor_min_m=sensor_min,
                            far_edge=far_edge)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    if sensor_min:  # points too near for the other camera on its holes: not observed
        assert got[2].any()
        if far_edge:  # and some holes lie in rows with no reading beyond the point
            plain = free_space_votes(pv, own, other, n, NOISE, 3.0, 0.01, pose_r, hole_r,
                                     free_zero, shadow_baseline_m=baseline,
                                     sensor_min_m=sensor_min)
            assert plain[0].sum() > got[0].sum()
        return
    assert not got[2].any()  # the shared pixel grid: everything is observed
    if baseline:  # some holes are shadows: fewer pixels seen through
        flat = other.ravel()
        rows = [np.empty(flat.size, np.uint16), np.empty(flat.size, np.int32),
                np.empty(flat.size, np.uint16), np.empty(flat.size, np.int32)]
        for r in range(h):
            free_space._fill_row(flat, w, r, *rows)
        for got_a, want_a in zip(rows, _row_neighbours_twin(other), strict=True):
            np.testing.assert_array_equal(got_a, want_a.ravel())
        plain = free_space_votes(pv, own, other, n, NOISE, 3.0, 0.01, pose_r, hole_r, free_zero)
        assert plain[0].sum() > got[0].sum()


def test_a_projector_shadow_is_not_seen_through():
    """A surface 2 m away beside a box 1 m away, both seen at first; then the surface has no
    reading over 15 pixels next to the box, as the projector's shadow of the box would leave
    it (7.5 cm x 525 px x (1/1 m - 1/2 m) = 19.7 pixels wide at most): not seen through.  The
    same hole 40 pixels from the box, or with no box beside it, is."""
    h, w = 20, 120
    own = np.full((h, w), 2000, np.uint16)
    own[:, 10:30] = 1000  # the box
    pv = np.full((h, w), -1, np.int32)
    pv[:, 30:45] = 0  # the surface beside the box
    pv[:, 70:85] = 1  # the surface far from it
    other = own.copy()
    other[:, 30:45] = 0
    other[:, 70:85] = 0
    votes, total, *_ = free_space_votes(pv, own, other, 2, NOISE, 3.0, 0.01, 0, 0, True,
                                        shadow_baseline_m=0.075)
    assert votes[0] == 0 and votes[1] == total[1]
    no_shadows = free_space_votes(pv, own, other, 2, NOISE, 3.0, 0.01, 0, 0, True)[0]
    assert no_shadows[0] == total[0]


def test_a_hole_is_seen_through_only_where_it_opens_beyond_the_point():
    """Holes the other camera left: over a table edge 0.45 m away (too near to read), a point
    there was not observed; a hole in a wall 2 m away, bordered by that wall, says nothing of
    a point of the wall (a dropout, or a surface too near to read, as an object 0.4 m before
    the lens leaves it); the same hole with a room 4 m away beside it opens beyond the point,
    which is seen through.  Without the two rules every one of them was seen through."""
    h, w = 10, 100
    own = np.full((h, w), 2000, np.uint16)
    own[:, 0:20] = 450  # the table edge, read by this camera
    pv = np.full((h, w), -1, np.int32)
    pv[:, 5:15] = 0  # on the table edge
    pv[:, 40:50] = 1  # on the wall, its hole bordered by the wall
    pv[:, 80:90] = 2  # on the wall, its hole beside a view 4 m deep
    other = np.full((h, w), 2000, np.uint16)
    other[:, 0:20] = 0  # too near for the other camera
    other[:, 35:55] = 0
    other[:, 75:92] = 0
    other[:, 92:] = 4000
    votes, total, unseen, *_ = free_space_votes(pv, own, other, 3, NOISE, 3.0, 0.01, 0, 0,
                                                True, sensor_min_m=0.5,
                                                hole_needs_far_edge=True)
    assert unseen[0] == total[0] and votes[0] == 0
    assert unseen[1] == 0 and votes[1] == 0
    assert unseen[2] == 0 and votes[2] == total[2]
    before = free_space_votes(pv, own, other, 3, NOISE, 3.0, 0.01, 0, 0, True)
    np.testing.assert_array_equal(before[0], total)


@pytest.mark.parametrize("dropout_px,baseline", [(0, 0.0), (10, 0.0), (4, 0.075), (10, 0.075)])
def test_holes_explained_match_numpy(dropout_px, baseline):
    rng = np.random.default_rng(dropout_px)
    depth = rng.integers(500, 4000, size=(40, 120)).astype(np.uint16)
    for _ in range(60):  # holes of every width, some at the border
        r, c, n = rng.integers(0, 40), rng.integers(0, 120), rng.integers(1, 40)
        depth[r, c:c + n] = 0
    depth[5, :] = 0  # a row with no reading
    flat = depth.ravel()
    got = np.zeros(depth.shape, bool)
    for i in np.flatnonzero(flat == 0):
        got.flat[i] = not free_space._hole_explained(flat, depth.shape[1], i, dropout_px,
                                                     baseline * 525.0, NOISE, 3.0, 0.01)
    want = _unexplained_holes_twin(depth, dropout_px, baseline * 525.0, 3.0, 0.01)
    np.testing.assert_array_equal(got, want)
    assert got[5].all()  # no reading in the row: nothing explains it
    if dropout_px or baseline:  # some holes are dropouts or shadows
        assert got.sum() < (depth == 0).sum()


def _plates_depth(plates, camera_z, intr):
    """(H, W) uint16 mm: what a camera at (0, 0, ``camera_z``) looking along +z reads of
    ``plates``, (x0, x1, z) strips square to its axis and as tall as the image, with a wall
    4 m away behind them; nothing nearer than 0.5 m is read."""
    x = (np.arange(intr.width) - intr.cx) / intr.fx  # each column's ray, x / z
    depth = np.full(intr.width, 4.0 - camera_z)
    for x0, x1, z in plates:
        d = z - camera_z
        on = (x * d >= x0) & (x * d <= x1) & (d < depth)
        depth[on] = d
    depth[depth < 0.5] = 0.0
    return np.tile(np.round(depth * 1000).astype(np.uint16), (intr.height, 1))


@pytest.mark.parametrize("plate_in_view", [True, False, "too near for both"])
def test_a_hole_left_by_a_surface_too_near_to_read_is_not_seen_through(plate_in_view):
    """A box 1.2 m away behind a plate 0.6 m away, seen by a camera that then stands 15 cm
    nearer: there the plate is too near to read (a hole wider than the plate hides the whole
    box), and beside the hole lies the wall 4 m away, so the hole opens beyond the box and,
    by the other rules, the box's edges this camera saw past the plate would be seen through.
    This camera saw the plate on the other camera's ray through the hole: the box is not
    seen through.  Where the plate is too near for this camera as well, its hole, bordered by
    the box on both sides, is neither a dropout nor a shadow: it may hold the plate, and the
    box is not seen through either.  Where this camera saw nothing on that ray (no plate
    before it: the hole is then no return), the box is."""
    intr = Intrinsics(400, 4, 200.0, 200.0, 199.5, 1.5)
    # a plate 0.45 m away is a hole for this camera too; the box is then wider, to show past it
    plate_z, box = (0.45, (-0.17, 0.17, 1.2)) if plate_in_view == "too near for both" \
        else (0.6, (-0.11, 0.11, 1.2))
    own = _plates_depth([box, (-0.05, 0.05, plate_z)] if plate_in_view else [box], 0.0, intr)
    other = _plates_depth([box, (-0.05, 0.05, plate_z)], 0.15, intr)
    pv = np.where(np.abs(own.astype(np.int64) - 1200) <= 1, 0, -1).astype(np.int32)
    assert (pv == 0).any() and (other == 0).any()
    T = np.eye(4)
    T[2, 3] = -0.15  # other_from_own: the other camera 15 cm ahead
    kwargs = dict(intrinsics=intr, other_from_own=T, hole_needs_far_edge=True)
    votes, total, unseen, *_ = free_space_votes(pv, own, other, 1, NOISE, 3.0, 0.01, 0, 0,
                                                True, sensor_min_m=0.5, **kwargs)
    assert total[0] > 0 and unseen[0] == 0
    assert votes[0] == (0 if plate_in_view else total[0])
    without = free_space_votes(pv, own, other, 1, NOISE, 3.0, 0.01, 0, 0, True, **kwargs)
    assert without[0][0] == total[0]  # the rules before this one see it through
    want = _free_space_twin(pv, own, other, 1, 3.0, 0.01, 0, 0, True,
                            *free_space._warp_kernel(own, pv, T[:3, :3].copy(), T[:3, 3].copy(),
                                                     intr.fx, intr.fy, intr.cx, intr.cy,
                                                     intr.width, np.array(
                                                         free_space.sensing_window(other)),
                                                     0.0, 65.535),
                            sensor_min_m=0.5, far_edge=True, back=np.linalg.inv(T), intr=intr)
    np.testing.assert_array_equal(votes, want[0])


def test_a_hole_whose_near_stretch_this_camera_never_saw_is_not_seen_through():
    """The other camera stands 30 cm to the side: the stretch of its ray within 0.5 m of it
    lies outside this camera's narrow view, so a hole there may hide a surface too near for
    it, and a wall point landing on the hole is not seen through (it is without the rule)."""
    intr = Intrinsics(40, 4, 200.0, 200.0, 19.5, 1.5)
    own = np.full((4, 40), 4000, np.uint16)
    other = own.copy()
    other[:, 5:20] = 0
    pv = np.zeros((4, 40), np.int32)
    T = np.eye(4)
    T[0, 3] = -0.3  # other_from_own: the other camera 30 cm along +x
    kwargs = dict(intrinsics=intr, other_from_own=T)
    votes, total, *_ = free_space_votes(pv, own, other, 1, NOISE, 3.0, 0.01, 0, 0, True,
                                        sensor_min_m=0.5, **kwargs)
    without = free_space_votes(pv, own, other, 1, NOISE, 3.0, 0.01, 0, 0, True, **kwargs)
    assert without[0][0] > 0 and votes[0] == 0
    target, z_other = free_space._warp_kernel(own, pv, T[:3, :3].copy(), T[:3, 3].copy(),
                                              intr.fx, intr.fy, intr.cx, intr.cy, intr.width,
                                              np.array(free_space.sensing_window(other)),
                                              0.0, 65.535)
    want = _free_space_twin(pv, own, other, 1, 3.0, 0.01, 0, 0, True, target, z_other,
                            sensor_min_m=0.5, back=np.linalg.inv(T), intr=intr)
    np.testing.assert_array_equal(votes, want[0])


@pytest.mark.parametrize("shift", [(0.0, 0.0, 0.0), (0.03, -0.02, 0.05), (0.4, 0.0, 0.0)])
def test_free_space_through_a_transform_matches_numpy(shift):
    from robot_change.change.registration import rpy_deg_to_rotation

    rng = np.random.default_rng(11)
    h, w, n = 30, 40, 60
    intr = Intrinsics(w, h, 35.0, 35.0, 19.5, 14.5)
    own = rng.integers(800, 3000, size=(h, w)).astype(np.uint16)
    own[rng.random((h, w)) < 0.1] = 0
    other = (own.astype(np.int64) + rng.integers(-200, 400, size=(h, w))).astype(np.uint16)
    other[rng.random((h, w)) < 0.2] = 0
    other[:, -3:] = 0  # a dead strip at the border, as a Kinect has
    pv = rng.integers(-1, n, size=(h, w)).astype(np.int32)
    T = np.eye(4)
    T[:3, :3] = rpy_deg_to_rotation(1.0, -2.0, 3.0)
    T[:3, 3] = shift
    window = free_space.sensing_window(other)
    assert window == (0, h - 1, 0, w - 4)
    got_t, got_z = free_space._warp_kernel(own, pv, T[:3, :3].copy(), T[:3, 3].copy(), intr.fx,
                                           intr.fy, intr.cx, intr.cy, w, np.array(window), 0.4,
                                           2.9)
    want_t, want_z = _warp_twin(own, T, intr, (0.4, 2.9), window, pv)
    assert (got_t[pv.ravel() < 0] == -1).all()  # pixels without a point are not warped
    np.testing.assert_array_equal(got_t, want_t)
    np.testing.assert_allclose(got_z, want_z, rtol=1e-12)
    got = free_space_votes(pv, own, other, n, NOISE, 3.0, 0.01, 2, 3, True, intrinsics=intr,
                           other_from_own=T, depth_range_m=(0.4, 2.9), shadow_baseline_m=0.075,
                           sensor_min_m=1.2, hole_needs_far_edge=True)
    want = _free_space_twin(pv, own, other, n, 3.0, 0.01, 2, 3, True, want_t, want_z,
                            shadow_bf=0.075 * intr.fx, sensor_min_m=1.2, far_edge=True,
                            back=np.linalg.inv(T), intr=intr)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    assert got[2].sum() > 0  # the depth range and the image border leave some unseen


@pytest.mark.parametrize("radius", [1, 2])
def test_voxel_components_match_ndimage_label(radius):
    rng = np.random.default_rng(radius)
    grid = rng.random((14, 12, 10)) < 0.25
    idx = np.argwhere(grid) - 5  # negative indices too
    keys = pack_keys(idx)
    perm = rng.permutation(len(keys))
    labels = label_voxel_components(keys[perm], radius)
    structure = np.ones((2 * radius + 1,) * 3, dtype=bool)
    if radius == 1:
        ref_lab, _ = ndimage.label(grid, structure=structure)
    else:  # radius 2: dilate-free check by brute force union of pairs within 2
        pts = idx.astype(np.int64)
        parent = list(range(len(pts)))

        def find(i):
            while parent[i] != i:
                i = parent[i]
            return i

        for i in range(len(pts)):
            near = np.flatnonzero(np.abs(pts - pts[i]).max(axis=1) <= radius)
            for j in near:
                a, b = find(i), find(int(j))
                if a != b:
                    parent[b] = a
        ref_lab = np.zeros(grid.shape, np.int64)
        for i, p in enumerate(pts + 5):
            ref_lab[tuple(p)] = find(i) + 1
    want = ref_lab[tuple((idx + 5).T)][perm]
    # same partition: a bijection between label sets
    pairs = set(zip(labels.tolist(), want.tolist(), strict=True))
    assert len(pairs) == len(set(labels.tolist())) == len(set(want.tolist()))


def test_voxel_components_reject_duplicates():
    with pytest.raises(InputError, match="unique"):
        label_voxel_components(np.array([5, 5], dtype=np.int64))


def test_posteriors_over_a_background_match_the_full_mixture():
    from robot_change.change.greedy import posteriors
    from robot_change.mixture.model import Mixture

    rng = np.random.default_rng(5)
    means = rng.normal(size=(5, 3))
    covs = np.stack([np.eye(3) * s for s in (0.2, 0.3, 0.25, 0.1, 0.4)])
    weights = np.array([0.3, 0.2, 0.1, 0.25, 0.15])
    mix = Mixture(weights, means, covs)
    background = Mixture(weights[:3] / weights[:3].sum(), means[:3], covs[:3])
    points = rng.normal(size=(200, 3))
    rows = np.flatnonzero(rng.random(200) < 0.6)
    full = posteriors(mix, points, rows)
    fast = posteriors(mix, points, rows, (3, background.score_samples(points)))
    np.testing.assert_allclose(fast[:, 3:], full[:, 3:], rtol=1e-10, atol=1e-14)
    assert not fast[:, :3].any()
    assert not fast[np.setdiff1d(np.arange(200), rows)].any()


def _read_through_twin(own, pixels, poses, intr, depth_range, window, views, other, sensor_min_m):
    """NumPy twin of free_space._read_through_kernel: (K, N) bool."""
    near, far = views[0].ravel(), views[1].ravel()
    out = np.zeros((len(poses), len(pixels)), bool)
    for k, T in enumerate(poses):
        target, z = _warp_twin(own, T, intr, depth_range, window)
        t, zz = target[pixels], z[pixels]
        ok = t >= 0
        q = np.where(ok, t, 0)
        margin = _margin(zz, 3.0, 0.01)
        near_cam = (other.ravel()[q] == 0) & (zz < sensor_min_m + margin)
        d1 = np.where(near[q] > 0, near[q], far[q]).astype(np.float64)
        out[k] = ok & ~near_cam & (d1 > 0) & (d1 * 0.001 > zz + margin)
    return out


def test_core_votes_at_several_poses_are_those_of_one_call_per_pose():
    """free_space.core_votes_at_poses (one pass, every pose) gives, pose by pose, the core
    counts of free_space_votes at that pose; its kernel matches a NumPy twin."""
    from robot_change.change.registration import rpy_deg_to_rotation

    rng = np.random.default_rng(3)
    h, w, n = 40, 48, 50
    intr = Intrinsics(w, h, 45.0, 45.0, 23.5, 19.5)
    own = np.full((h, w), 2000, np.uint16)
    own[10:30, 12:36] = 1500  # a box before a wall: blocks of pixels to be seen through
    own = (own.astype(np.int64) + rng.integers(-20, 20, size=(h, w))).astype(np.uint16)
    own[rng.random((h, w)) < 0.05] = 0
    other = np.full((h, w), 2600, np.uint16)  # the other image sees the wall behind it
    other[:, :6] = 1400
    other[rng.random((h, w)) < 0.1] = 0
    pv = np.where(rng.random((h, w)) < 0.98, rng.integers(0, n, size=(h, w)), -1).astype(np.int32)
    pv[:4] = -1  # rows without a point
    poses = []
    for rpy, t in (((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), ((0.5, 0.0, 0.0), (0.01, 0.0, 0.0)),
                   ((0.0, -0.5, 1.0), (0.0, 0.02, -0.03)), ((2.0, 1.0, 0.0), (0.1, 0.0, 0.0))):
        T = np.eye(4)
        T[:3, :3] = rpy_deg_to_rotation(*rpy)
        T[:3, 3] = t
        poses.append(T)
    views = free_space.other_views(other, 2, 3)
    kw = dict(intrinsics=intr, depth_range_m=(0.4, 4.0), sensor_min_m=0.5)
    for edge_px in (0, 1, 2):
        got = free_space.core_votes_at_poses(pv, own, other, n, NOISE, 3.0, 0.01,
                                             np.array(poses), views=views, edge_px=edge_px,
                                             **kw)
        for k, T in enumerate(poses):
            one = free_space_votes(pv, own, other, n, NOISE, 3.0, 0.01, 2, 3, True,
                                   other_from_own=T, views=views, edge_px=edge_px, **kw)
            np.testing.assert_array_equal(got[k], one.core)
        assert got.sum() > 0 and (got[0] != got[3]).any()  # seen through, and the poses differ
    pixels = np.flatnonzero(pv.ravel() >= 0)
    kernel = free_space._read_through_kernel(
        own.ravel(), pixels, np.ascontiguousarray(np.array(poses)[:, :3, :3]),
        np.ascontiguousarray(np.array(poses)[:, :3, 3]), intr.fx, intr.fy, intr.cx, intr.cy, w,
        views[2], 0.4, 4.0, views[0].ravel(), views[1].ravel(), other.ravel(), NOISE, 3.0, 0.01,
        0.5)
    want = _read_through_twin(own, pixels, poses, intr, (0.4, 4.0), tuple(views[2]), views,
                              other, 0.5)
    np.testing.assert_array_equal(kernel, want)
    assert want.any()
    empty = free_space.core_votes_at_poses(np.full((h, w), -1, np.int32), own, other, n, NOISE,
                                           3.0, 0.01, np.array(poses), views=views, **kw)
    assert empty.shape == (4, n) and not empty.any()
