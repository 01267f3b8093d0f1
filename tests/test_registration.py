"""Registration of the current view to the reference (robot_change.change.registration): the kernels
against plain NumPy twins, accuracy against the revisit fixtures' true transforms (with the
change in view), weak directions of a bare wall, and the not-at-station outcome."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hw.depth import Intrinsics
from robot_change.change.detect import detect_changes
from robot_change.change.params import ChangeParams
from robot_change.change.registration import (
    RegistrationParams,
    agreement,
    icp,
    invert,
    pyramid,
    register,
    register_depth,
    rotation_angle_deg,
    rotation_to_rpy_deg,
    rpy_deg_to_rotation,
    table_station,
    table_top,
)
from robot_change.change.registration.rigid import exp_so3
from robot_change.change.scene import build_scene
from robot_change.errors import InputError
from robot_change.noise.kernels import table_sigma
from robot_change.noise.profile import NoiseProfile
from sim_fixtures import load_scene, scene_names

INTR = Intrinsics.openni_default()
#: The default profile's sigma table, as the registration's kernels read it.
NOISE = RegistrationParams().noise_args()[0]


def _margin_twin(z, sigmas, floor_m, floor_per_m2, noise=NOISE):
    """robot_change.noise.kernels.floored_margin_at in NumPy."""
    return np.maximum(floor_m + floor_per_m2 * z * z, sigmas * np.sqrt(2.0) *
                      table_sigma(noise, z))


def _fused(frames):
    return np.median(np.stack(frames), axis=0).astype(np.uint16)


# --------------------------------------------------------------------------- numba twins


def _vertex_twin(depth, f, intr, min_mm, max_mm, band_m, band_slope):
    h, w = depth.shape[0] // f, depth.shape[1] // f
    out = np.zeros((h, w, 3), np.float32)
    count = np.zeros((h, w), np.int32)
    half = f // 2
    lo = max(half - 1, 0)
    for i in range(h):
        for j in range(w):
            block = depth[i * f:(i + 1) * f, j * f:(j + 1) * f].astype(np.int64)
            centre = block[lo:half + 1, lo:half + 1]
            centre = centre[(centre >= min_mm) & (centre <= max_mm)]
            if centre.size == 0:
                continue
            za = (centre * 0.001).sum() / centre.size
            band = band_m + band_slope * f * za / intr.fx
            r, c = np.nonzero((block >= min_mm) & (block <= max_mm)
                              & (np.abs(block * 0.001 - za) <= band))
            if r.size < max(1, f * f // 4):
                continue
            z = block[r, c] * 0.001
            x = (c + j * f - intr.cx) * z / intr.fx
            y = (r + i * f - intr.cy) * z / intr.fy
            out[i, j] = (x.sum() / r.size, y.sum() / r.size, z.sum() / r.size)
            count[i, j] = r.size
    return out, count


def _merge_twin(vertex, count, band_m, slope):
    h, w = vertex.shape[0] // 2, vertex.shape[1] // 2
    out = np.zeros((h, w, 3), np.float32)
    out_count = np.zeros((h, w), np.int32)
    for i in range(h):
        for j in range(w):
            v = vertex[2 * i:2 * i + 2, 2 * j:2 * j + 2].reshape(4, 3).astype(np.float64)
            k = count[2 * i:2 * i + 2, 2 * j:2 * j + 2].reshape(4)
            ok = k > 0
            if not ok.any():
                continue
            za = v[ok, 2].sum() / ok.sum()
            sel = ok & (np.abs(v[:, 2] - za) <= band_m + slope * za)
            n = k[sel].sum()
            if n > 0 and 4 * n >= k.sum():
                out[i, j] = (k[sel, None] * v[sel]).sum(axis=0) / n
                out_count[i, j] = n
    return out, out_count


def _normal_twin(vertex, max_step):
    v = vertex.astype(np.float64)
    h, w, _ = v.shape
    out = np.zeros((h, w, 3), np.float32)
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            nb = [v[i, j], v[i, j - 1], v[i, j + 1], v[i - 1, j], v[i + 1, j]]
            if any(p[2] <= 0 for p in nb):
                continue
            a = v[i, j + 1] - v[i, j - 1]
            b = v[i + 1, j] - v[i - 1, j]
            lim = max_step * v[i, j, 2]
            if a @ a > lim * lim or b @ b > lim * lim:
                continue
            n = np.cross(a, b)
            norm = np.linalg.norm(n)
            if norm <= 0:
                continue
            out[i, j] = -n / norm if n @ v[i, j] > 0 else n / norm
    return out


def _project_twin(point, R, t, fx, fy, cx, cy, shape):
    """(p, u, v): ``point`` moved by (R, t) and the pixel it lands on, or None when it lands
    behind the camera or outside an image of ``shape`` (h, w)."""
    p = R @ point.astype(np.float64) + t
    if p[2] <= 0:
        return None
    u = int(math.floor(fx * p[0] / p[2] + cx + 0.5))
    v = int(math.floor(fy * p[1] / p[2] + cy + 0.5))
    if not (0 <= u < shape[1] and 0 <= v < shape[0]):
        return None
    return p, u, v


def _associate_twin(cur_v, cur_n, ref_v, ref_n, R, t, fx, fy, cx, cy, max_dist, min_cos):
    res, jac, zs = [], [], []
    for i in range(cur_v.shape[0]):
        for j in range(cur_v.shape[1]):
            n0 = cur_n[i, j].astype(np.float64)
            if not n0.any():
                continue
            hit = _project_twin(cur_v[i, j], R, t, fx, fy, cx, cy, ref_v.shape)
            if hit is None:
                continue
            p, u, v = hit
            m = ref_n[v, u].astype(np.float64)
            if not m.any():
                continue
            d = p - ref_v[v, u]
            if d @ d > max_dist ** 2 or (R @ n0) @ m < min_cos:
                continue
            res.append(m @ d)
            jac.append(np.concatenate([np.cross(p, m), m]))
            zs.append(p[2])
    return np.array(res), np.array(jac).reshape(-1, 6), np.array(zs)


@pytest.fixture(scope="module")
def office_pair():
    sc = load_scene("office_box_added_pose_5cm")
    return _fused(sc.reference_frames()), sc.current_frames()[0], sc


def test_vertex_and_merge_levels_match_numpy(office_pair):
    ref, _, _ = office_pair
    crop = np.ascontiguousarray(ref[100:196, 200:328])  # (96, 128), edges and the floor
    intr = Intrinsics(128, 96, 525.0, 525.0, 319.5 - 200, 239.5 - 100)
    for f in (4, 8):
        got_v, got_c = pyramid._vertex_level(crop, f, intr.fx, intr.fy, intr.cx, intr.cy, 400,
                                             5000, 0.03, 2.0)
        want_v, want_c = _vertex_twin(crop, f, intr, 400, 5000, 0.03, 2.0)
        np.testing.assert_array_equal(got_c, want_c)
        np.testing.assert_allclose(got_v, want_v, rtol=1e-6, atol=1e-7)
    got = pyramid._merge_level(got_v, got_c, 0.03, 2.0 * 16 / 525.0)
    want = _merge_twin(got_v, got_c, 0.03, 2.0 * 16 / 525.0)
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_allclose(got[0], want[0], rtol=1e-6, atol=1e-7)
    assert (got_c > 0).mean() > 0.5


def test_normal_map_and_association_match_numpy(office_pair):
    ref, cur, sc = office_pair
    params = RegistrationParams()
    rl = pyramid.levels(ref, INTR, params)[1]
    cl = pyramid.levels(cur, INTR, params)[1]
    np.testing.assert_allclose(pyramid._normal_map(rl.vertex, 8.0 * 8 / INTR.fx),
                               _normal_twin(rl.vertex, 8.0 * 8 / INTR.fx), atol=1e-6)
    T = sc.T_ref_from_cur
    n_cells = cl.vertex.shape[0] * cl.vertex.shape[1]
    res, jac, zs = np.empty(n_cells), np.empty((n_cells, 6)), np.empty(n_cells)
    n = icp._associate(cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3].copy(),
                           T[:3, 3].copy(), rl.fx, rl.fy, rl.cx, rl.cy, 0.1, 0.8, res, jac, zs)
    w_res, w_jac, w_zs = _associate_twin(cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3],
                                         T[:3, 3], rl.fx, rl.fy, rl.cx, rl.cy, 0.1, 0.8)
    assert n == len(w_res) > 1000
    np.testing.assert_allclose(res[:n], w_res, atol=1e-6)
    np.testing.assert_allclose(jac[:n], w_jac, atol=1e-6)
    np.testing.assert_allclose(zs[:n], w_zs, atol=1e-6)
    inliers, sq_sum, *_ = agreement.agreement_counts(
        cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3].copy(), T[:3, 3].copy(), rl.fx,
        rl.fy, rl.cx, rl.cy, 0.1, 0.8, NOISE, 3.0, 3.0, 0.03, 0.004, True)
    inl = np.abs(w_res) <= 3.0 * table_sigma(NOISE, w_zs)
    assert inliers == int(inl.sum())
    assert sq_sum == pytest.approx(float(np.square(w_res[inl]).sum()), rel=1e-9)
    # the default profile's table is the Kinect's noise (Nguyen et al. 2012 with the
    # disparity step, Khoshelham & Oude Elberink 2012)
    sig = 0.0012 + 0.0019 * (w_zs - 0.4) ** 2
    quant = 2.85e-3 * w_zs ** 2 / math.sqrt(12.0)
    np.testing.assert_allclose(table_sigma(NOISE, w_zs), np.hypot(sig, quant), rtol=1e-3)


def _weighted_system_twin(res, jac, zs, c, min_cut_m):
    sig = table_sigma(NOISE, zs)
    e = res / sig
    scale = max(1.4826 * float(np.median(np.abs(e))), 0.5)
    u = res / np.maximum(c * scale * sig, min_cut_m)
    wts = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0) / sig ** 2
    jw = jac * wts[:, None]
    return jw.T @ jac, jw.T @ res, wts.sum(), math.sqrt(float(np.median(zs ** 2)))


@pytest.mark.parametrize("tukey_c,min_cut_m", [(1.0, 0.0), (4.685, 0.0), (4.685, 0.05)])
def test_weighted_normal_equations_match_numpy(office_pair, tukey_c, min_cut_m):
    ref, cur, sc = office_pair
    params = RegistrationParams()
    rl = pyramid.levels(ref, INTR, params)[-1]
    cl = pyramid.levels(cur, INTR, params)[-1]
    pairs = icp.Pairs(cl)
    n = icp._associate(cl.vertex, cl.normal, rl.vertex, rl.normal, np.eye(3), np.zeros(3),
                       rl.fx, rl.fy, rl.cx, rl.cy, 0.1, 0.8, pairs.res, pairs.jac,
                       pairs.zs)  # identity: many large residuals
    A, b, wsum, radius = icp._weighted_system(pairs.res, pairs.jac, pairs.zs, n, tukey_c,
                                              min_cut_m, NOISE)
    wA, wb, wwsum, wradius = _weighted_system_twin(pairs.res[:n], pairs.jac[:n], pairs.zs[:n],
                                                   tukey_c, min_cut_m)
    assert n > 1000
    np.testing.assert_allclose(A, wA, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(b, wb, rtol=1e-9, atol=1e-9)
    assert wsum == pytest.approx(wwsum, rel=1e-12)
    assert radius == pytest.approx(wradius, rel=1e-12)


def _exp_so3_twin(w):
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


def test_exp_so3_matches_numpy_and_scipy():
    from scipy.spatial.transform import Rotation

    for w in (np.zeros(3), np.array([1e-13, 0.0, 0.0]), np.array([0.1, -0.2, 0.3]),
              np.array([0.0, 0.0, math.pi - 1e-3])):
        got = exp_so3(w)
        np.testing.assert_allclose(got, _exp_so3_twin(w), atol=1e-14)
        np.testing.assert_allclose(got, Rotation.from_rotvec(w).as_matrix(), atol=1e-12)


def _icp_twin(cur_v, cur_n, ref_v, ref_n, T, fx, fy, cx, cy, max_dist, min_cos, tukey_c,
              min_cut_m, weak_eigenvalue, iterations, tol_m):
    """The Gauss-Newton iterations of one level, in NumPy (icp._icp_iterations' twin)."""
    lam_n, vec, A = np.zeros(6), np.eye(6), None
    for it in range(iterations):
        res, jac, zs = _associate_twin(cur_v, cur_n, ref_v, ref_n, T[:3, :3], T[:3, 3], fx, fy,
                                       cx, cy, max_dist, min_cos)
        if len(res) < 6:
            return T, it, False, lam_n, vec, A
        A, b, wsum, radius = _weighted_system_twin(res, jac, zs, tukey_c, min_cut_m)
        s = np.array([radius] * 3 + [1.0] * 3)
        lam, vec = np.linalg.eigh(A / np.outer(s, s))
        lam_n = lam / max(wsum, 1e-300)
        strong = lam_n >= weak_eigenvalue
        step = -(vec[:, strong] @ ((vec[:, strong].T @ (b / s)) / lam[strong])) / s
        length = math.sqrt(float(step[:3] @ step[:3]) * radius ** 2 + float(step[3:] @ step[3:]))
        if length > 0.5 * max_dist:
            step, length = step * (0.5 * max_dist / length), 0.5 * max_dist
        inc = np.eye(4)
        inc[:3, :3], inc[:3, 3] = _exp_so3_twin(step[:3]), step[3:]
        T = inc @ T
        if length < tol_m:
            return T, it + 1, True, lam_n, vec, A
    return T, iterations, False, lam_n, vec, A


@pytest.mark.parametrize("level,min_cut_m", [(0, 0.0), (0, 0.2), (1, 0.0), (2, 0.0)])
def test_icp_iterations_match_numpy(office_pair, level, min_cut_m):
    """From within each level's basin (4 cm and 2 degrees off at the coarsest level, a
    quarter of that at the finest), the iterations of each level (with and without a wide
    cut) end where the NumPy twin's do, after as many steps, with the same system, nearer the
    truth."""
    ref, cur, sc = office_pair
    params = RegistrationParams()
    rl = pyramid.levels(ref, INTR, params)[level]
    cl = pyramid.levels(cur, INTR, params)[level]
    start = np.eye(4)
    start[:3, :3] = rpy_deg_to_rotation(*np.array([1.0, -1.0, 1.0]) / 2 ** level)
    start[:3, 3] = np.array([0.02, -0.03, 0.01]) / 2 ** level
    start = start @ sc.T_ref_from_cur
    min_cos = math.cos(math.radians(params.max_normal_angle_deg))
    args = (rl.fx, rl.fy, rl.cx, rl.cy, params.max_distance_m[level], min_cos, params.tukey_c,
            min_cut_m, params.weak_eigenvalue, params.iterations[level], params.tol_m)
    pairs = icp.Pairs(cl)
    T, n_it, converged, lam_n, _vec, A, has_system = icp._icp_iterations(
        cl.vertex, cl.normal, rl.vertex, rl.normal, start, *args, pairs.res, pairs.jac, pairs.zs,
        NOISE)
    wT, w_it, w_converged, w_lam_n, _w_vec, wA = _icp_twin(cl.vertex, cl.normal, rl.vertex,
                                                          rl.normal, start, *args)
    assert (n_it, converged, has_system) == (w_it, w_converged, wA is not None) and n_it > 0
    np.testing.assert_allclose(T, wT, atol=1e-7)
    np.testing.assert_allclose(lam_n, w_lam_n, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(A, wA, rtol=1e-6, atol=1e-6)
    # and it went towards the truth
    err = np.linalg.norm((T @ np.linalg.inv(sc.T_ref_from_cur))[:3, 3])
    assert err < np.linalg.norm((start @ np.linalg.inv(sc.T_ref_from_cur))[:3, 3])


def _seen_through_twin(cur_v, ref_v, R, t, fx, fy, cx, cy, sigmas, floor_m, floor_per_m2):
    v = cur_v.reshape(-1, 3).astype(np.float64)
    v = v[v[:, 2] > 0]
    p = v @ R.T + t
    p = p[p[:, 2] > 0]
    u = np.floor(fx * p[:, 0] / p[:, 2] + cx + 0.5).astype(np.int64)
    w = np.floor(fy * p[:, 1] / p[:, 2] + cy + 0.5).astype(np.int64)
    inside = (u >= 0) & (w >= 0) & (u < ref_v.shape[1]) & (w < ref_v.shape[0])
    rz = ref_v[w[inside], u[inside], 2].astype(np.float64)
    pz = p[inside, 2]
    ok = rz > 0
    m = _margin_twin(pz[ok], sigmas, floor_m, floor_per_m2)
    return (int((rz[ok] > pz[ok] + m).sum()), int(ok.sum()), int((~ok).sum()),
            int((rz[ok] < pz[ok] - m).sum()))


def test_agreement_counts_match_numpy(office_pair):
    """Seen through, compared, on no reading, behind; and, counting pairs, the inliers of
    the association and their squared residuals."""
    ref, cur, sc = office_pair
    params = RegistrationParams()
    rl = pyramid.levels(ref, INTR, params)[-1]
    cl = pyramid.levels(cur, INTR, params)[-1]
    T = sc.T_ref_from_cur
    for count_pairs in (False, True):
        inliers, sq_sum, *got = agreement.agreement_counts(
            cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3].copy(), T[:3, 3].copy(),
            rl.fx, rl.fy, rl.cx, rl.cy, 0.06, 0.8, NOISE, 3.0, 3.0, 0.03, 0.004, count_pairs)
        through, compared, holes, behind = _seen_through_twin(
            cl.vertex, rl.vertex, T[:3, :3], T[:3, 3], rl.fx, rl.fy, rl.cx, rl.cy, 3.0, 0.03, 0.004)
        assert tuple(got) == (through, compared, holes, behind)
        res, _jac, zs = _associate_twin(cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3],
                                        T[:3, 3], rl.fx, rl.fy, rl.cx, rl.cy, 0.06, 0.8)
        inl = np.abs(res) <= 3.0 * table_sigma(NOISE, zs)
        assert inliers == (int(inl.sum()) if count_pairs else 0)
        assert sq_sum == pytest.approx(float(np.square(res[inl]).sum()) if count_pairs else 0.0,
                                       rel=1e-9)
    assert inliers > 0.7 * compared  # at the true pose most cells pair
    assert 0 < through < 0.1 * compared  # the added box, and little else
    assert 0 < holes < 0.2 * compared  # cells landing on no reading: few at the true pose
    assert 0 < behind < 0.1 * compared  # behind what the reference saw nearer: few as well


def test_through_counts_match_numpy(office_pair):
    """The cells seen through at each of many poses, in one pass: the twin's count, pose by
    pose (the truth, and poses slid and turned off it, where more is seen through)."""
    ref, cur, sc = office_pair
    params = RegistrationParams()
    rl = pyramid.levels(ref, INTR, params)[1]
    cl = pyramid.levels(cur, INTR, params)[1]
    poses = []
    for k in range(5):
        T = sc.T_ref_from_cur.copy()
        T[:3, :3] = T[:3, :3] @ rpy_deg_to_rotation(0.0, 0.0, 2.0 * k)
        T[:3, 3] += [0.04 * k, 0.0, -0.03 * k]
        poses.append(T)
    rots = np.array([T[:3, :3] for T in poses])
    transs = np.array([T[:3, 3] for T in poses])
    got = agreement.through_counts(cl.vertex, rl.vertex, rots, transs, rl.fx, rl.fy, rl.cx,
                                   rl.cy, NOISE, 3.0, 0.03, 0.004)
    want = [_seen_through_twin(cl.vertex, rl.vertex, T[:3, :3], T[:3, 3], rl.fx, rl.fy, rl.cx,
                               rl.cy, 3.0, 0.03, 0.004)[0] for T in poses]
    assert got.tolist() == want
    assert want[0] < want[-1]
    empty = agreement.through_counts(cl.vertex, rl.vertex, rots[:0], transs[:0], rl.fx, rl.fy,
                                     rl.cx, rl.cy, NOISE, 3.0, 0.03, 0.004)
    assert empty.shape == (0,)


@pytest.mark.parametrize("both_ways,hole_weight", [(False, 0.0), (True, 0.0), (True, 1.0),
                                                   (False, 0.5)])
def test_pose_scores_match_numpy(office_pair, both_ways, hole_weight):
    """Each pose's score: inliers within the step (of the current's cells, or of both views'
    cells), less the cells either view sees through and hole_weight times those of either
    view that land on no reading of the other."""
    ref, cur, sc = office_pair
    params = RegistrationParams()
    rl = pyramid.levels(ref, INTR, params)[1]
    cl = pyramid.levels(cur, INTR, params)[1]
    T = sc.T_ref_from_cur
    tilt = rpy_deg_to_rotation(1.0, -2.0, 3.0)
    rots = np.array([T[:3, :3], T[:3, :3], tilt @ T[:3, :3], T[:3, :3]])
    transs = T[:3, 3] + np.array([[0, 0, 0], [0.1, 0, 0], [-0.2, 0, 0.05], [0, 0.1, -0.1]])
    args = (cl.vertex, cl.normal, rl.vertex, rl.normal, rots, transs, rl.fx, rl.fy, rl.cx,
            rl.cy, 0.1, 0.8, NOISE, 3.0, 3.0, 0.03, 0.004, both_ways, hole_weight)
    got = agreement._pose_scores(*args, False)
    # pruned (for the best alone): the same first best; a pose is either scored as it was
    # or -inf, and then below the best
    pruned = agreement._pose_scores(*args, True)
    assert np.argmax(pruned) == np.argmax(got)
    kept = np.isfinite(pruned)
    np.testing.assert_array_equal(pruned[kept], got[kept])
    assert (got[~kept] < got.max()).all() and (kept.all() if both_ways else not kept.all())
    for score, rot, t in zip(got, rots, transs, strict=True):
        inliers = 0
        for own, other, R, tt in ((cl, rl, rot, t), (rl, cl, rot.T, -rot.T @ t))[:1 + both_ways]:
            res, _jac, zs = _associate_twin(own.vertex, own.normal, other.vertex, other.normal,
                                            R, tt, other.fx, other.fy, other.cx, other.cy, 0.1,
                                            0.8)
            inliers += int((np.abs(res) <= 3.0 * table_sigma(NOISE, zs)).sum())
        through_cur, _, holes_cur, _ = _seen_through_twin(cl.vertex, rl.vertex, rot, t, rl.fx,
                                                          rl.fy, rl.cx, rl.cy, 3.0, 0.03, 0.004)
        through_ref, _, holes_ref, _ = _seen_through_twin(rl.vertex, cl.vertex, rot.T,
                                                          -rot.T @ t, cl.fx, cl.fy, cl.cx,
                                                          cl.cy, 3.0, 0.03, 0.004)
        assert score == pytest.approx(inliers - through_cur - through_ref
                                      - hole_weight * (holes_cur + holes_ref), abs=1e-9)
    assert got[0] == got.max()  # the true pose scores best


def _cell_states_twin(cur_v, cur_n, ref_v, ref_n, R, t, fx, fy, cx, cy, max_dist, min_cos,
                      noise, sigmas, through_sigmas, floor_m, floor_per_m2, facing, min_facing):
    out = np.zeros(cur_v.shape[:2], np.int8)
    for i in range(cur_v.shape[0]):
        for j in range(cur_v.shape[1]):
            if min_facing > 0 and abs(float(cur_n[i, j] @ facing)) < min_facing:
                continue
            hit = _project_twin(cur_v[i, j], R, t, fx, fy, cx, cy, ref_v.shape)
            if cur_v[i, j, 2] <= 0 or hit is None or ref_v[hit[2], hit[1], 2] <= 0:
                continue
            p, u, v = hit
            gap = float(ref_v[v, u, 2]) - p[2]
            margin_z = _margin_twin(p[2], through_sigmas, floor_m, floor_per_m2, noise)
            if gap > margin_z:
                out[i, j] = 2  # seen through
                continue
            n0 = cur_n[i, j].astype(np.float64)
            m = ref_n[v, u].astype(np.float64)
            d = p - ref_v[v, u]
            if gap < -margin_z or not n0.any() or not m.any() or d @ d > max_dist ** 2 \
                    or (R @ n0) @ m < min_cos:
                continue
            out[i, j] = 1 if abs(m @ d) <= sigmas * table_sigma(noise, p[2]) else 2
    return out


@pytest.mark.parametrize("level", [1, 2])
def test_cell_states_match_numpy(office_pair, level):
    """Per cell: 2 seen through or paired beyond 3 sigmas, 1 paired within, 0 otherwise; with
    a facing direction, only the cells whose normal lies along it are judged."""
    ref, cur, sc = office_pair
    params = RegistrationParams()
    rl = pyramid.levels(ref, INTR, params)[level]
    cl = pyramid.levels(cur, INTR, params)[level]
    for T in (sc.T_ref_from_cur, np.eye(4)):
        args = (cl.vertex, cl.normal, rl.vertex, rl.normal, T[:3, :3].copy(), T[:3, 3].copy(),
                rl.fx, rl.fy, rl.cx, rl.cy, 0.06, 0.8, NOISE, 3.0, 3.0, 0.03, 0.004)
        every = agreement.cell_states(*args, np.zeros(3), 0.0)
        np.testing.assert_array_equal(every, _cell_states_twin(*args, np.zeros(3), 0.0))
        assert (every == 1).sum() > 100 and (every == 2).sum() > 10
        along_x = agreement.cell_states(*args, np.array([1.0, 0.0, 0.0]), 0.5)
        np.testing.assert_array_equal(
            along_x, _cell_states_twin(*args, np.array([1.0, 0.0, 0.0]), 0.5))
        facing = np.abs(cl.normal[:, :, 0]) >= 0.5
        assert 0 < (along_x > 0).sum() < (every > 0).sum()
        np.testing.assert_array_equal(along_x[facing], every[facing])


def test_rotation_helpers_round_trip():
    R = rpy_deg_to_rotation(3.0, -4.0, 10.0)
    np.testing.assert_allclose(rotation_to_rpy_deg(R), (3.0, -4.0, 10.0), atol=1e-9)
    assert rotation_angle_deg(R) == pytest.approx(
        math.degrees(math.acos((np.trace(R) - 1) / 2)))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, (0.1, -0.2, 0.3)
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)


# --------------------------------------------------------------------------- behaviour


REVISITS = [n for n in scene_names() if "_pose_" in n]


@pytest.mark.parametrize("name", REVISITS)
def test_registration_recovers_the_true_offset_with_the_change_in_view(name):
    sc = load_scene(name)
    got = register_depth(_fused(sc.reference_frames()), sc.current_frames()[0], sc.intrinsics)
    err = invert(sc.T_ref_from_cur) @ got.T_ref_from_cur
    assert np.linalg.norm(err[:3, 3]) < 0.01, got.to_dict()
    assert rotation_angle_deg(err[:3, :3]) < 0.5
    assert got.fitness > 0.6 and got.weak == ()


def test_a_bare_wall_leaves_sliding_along_it_weak_and_unmoved():
    depth = np.full((480, 640), 2000, np.uint16)  # a wall 2 m ahead, square to the camera
    got = register_depth(depth, depth, INTR)
    assert {"x", "y"} <= set(got.weak)
    np.testing.assert_allclose(got.T_ref_from_cur, np.eye(4), atol=1e-6)
    assert got.to_dict()["weak_directions"] == list(got.weak)


# Table stations (sim_fixtures.stations) from the bench's dev seeds: (seed, change, offset
# (translation m, rotation deg, draw)); the draws are the bench's for those pairs.
_STATION_SLID = (1, "one_removed", (0.10, 4.0, 20663))  # one object taken off the table
_STATION_LINED_UP = (0, "all_moved", (0.15, 6.0, 78249))  # every object on the table moved
_STATION_CONTESTED = (3003, "all_moved", (0.05, 2.0, 30935))  # the same, another table


def _station_error(station, params=None):
    from sim_fixtures.stations import station_pair

    if params is None:
        params = RegistrationParams()

    ref, cur, truth, intrinsics = station_pair(*station)
    got = register_depth(ref, cur, intrinsics, params)
    err = invert(truth) @ got.T_ref_from_cur
    return float(np.linalg.norm(err[:3, 3])), rotation_angle_deg(err[:3, :3]), got


def test_a_table_station_does_not_slide_along_its_wall():
    """A table before a wall pins the slide along the wall only by the table's legs and the
    sides of the objects on it, a few centimetres wide: the fine search finds it where the
    10 cm search steps over it (57 mm off without it, and without the final search, which
    finds it too). The slide stays said (step 7e): without the objects on the table 7 cells
    facing along it fit, under slide_support_share of the view."""
    metres, degrees, got = _station_error(_STATION_SLID)
    assert metres < 0.005 and degrees < 0.1 and got.weak == ("x",)
    metres, _degrees, _got = _station_error(_STATION_SLID,
                                            RegistrationParams(fine_search_reach_m=0.0))
    assert metres < 0.005
    metres, _degrees, _got = _station_error(
        _STATION_SLID, RegistrationParams(fine_search_reach_m=0.0, final_search_reach_m=0.0))
    assert metres > 0.03


# One object moved 8-20 cm, the revisit 15 cm away (the bench's 9000 set, one of the checks
# the final search was chosen on).
_STATION_ONE_MOVED = (9007, "one_moved", (0.15, 6.0, 71648))


def test_a_weak_slide_is_searched_again_at_the_end():
    """The estimate ends 15 cm off along the wall, weak there, where the moved object and the
    objects beside it line up; scored both ways the pose where the table's legs and edges fit
    wins by about 4 % of the cells, and the final search (agreement.slide_peaks, then ICP at
    the finest level) takes it. It does not without the search, nor when the margin asked
    is more than that lead. Where along the wall it stands the search's score chose, not the
    geometry, so `x` stays said (at its new pose the geometry alone would say nothing)."""
    metres, degrees, got = _station_error(_STATION_ONE_MOVED)
    assert metres < 0.005 and degrees < 0.1 and got.weak == ("x",)
    for params in (RegistrationParams(final_search_reach_m=0.0),
                   RegistrationParams(final_search_margin=0.05)):
        metres, _degrees, got = _station_error(_STATION_ONE_MOVED, params)
        assert metres > 0.1 and "x" in got.weak


_STATION_FELL_OFF = (10003, "one_moved", (0.15, 6.0, 79566))
_STATION_ALL_MOVED_UNFIT = (10008, "all_moved", (0.1, 4.0, 94017))


def test_a_station_that_slid_off_is_found_again_from_the_restarts():
    """From the initial pose, 15 cm / 6 deg from the truth, ICP turns right but slides 27 cm
    off, where much of a view is seen through by the other. Step 7d's passes from the initial
    pose moved 10 cm along / turned 5 deg about each axis reach the truth; without them the
    check ends `not_at_station`. (The coarsest level's own restarts, step 5b until 2026-12-07,
    changed no check of any set: removed.)"""
    metres, degrees, got = _station_error(_STATION_FELL_OFF)
    assert metres < 0.005 and degrees < 0.1 and got.fitness > 0.5
    params = RegistrationParams(restart_step_m=0.0, restart_step_deg=0.0)
    metres, _degrees, got = _station_error(_STATION_FELL_OFF, params)
    assert metres > 0.2 and got.fitness < params.min_fitness
    # a right end never starts again; where every object moved the estimate stays as ICP
    # left it (27 cm off, weak x), whence, since the objects' feet are told from the
    # structure, step 7c's search takes it to the truth
    no = RegistrationParams(restart_step_m=0.0, restart_step_deg=0.0)
    for station in (_STATION_ALL_MOVED_UNFIT, _STATION_ONE_MOVED):
        _, _, with_ = _station_error(station)
        _, _, without = _station_error(station, no)
        np.testing.assert_array_equal(with_.T_ref_from_cur, without.T_ref_from_cur)
    metres, _degrees, got = _station_error(_STATION_ALL_MOVED_UNFIT)
    assert metres < 0.005 and "x" in got.weak
    metres, _degrees, got = _station_error(_STATION_ALL_MOVED_UNFIT,
                                           RegistrationParams(station_through_ratio=0.0))
    assert metres > 0.2 and "x" in got.weak


# One object taken off the table, the revisit 15 cm / 6 deg away (the bench's 9000 set).
_STATION_TURNED_OFF = (9001, "one_removed", (0.15, 6.0, 94178))


def test_an_end_that_contradicts_the_views_starts_again():
    """ICP and every search after it end 27 cm / 8 deg off, where a fifth of a view is seen
    through by the other (more than restart_end_through); the coarse-to-fine passes from the
    12 restarts around the initial pose reach the truth from 4 of them, and it scores highest
    both ways and is seen through much less (step 7d).  An end seen through less (a revisit
    with nothing changed) is left as it is, not a pass more; nor is one where the best pass
    is not seen through in less than restart_end_ratio of its share."""
    no_restart = RegistrationParams(restart_end_through=0.0)
    metres, degrees, got = _station_error(_STATION_TURNED_OFF)
    assert metres < 0.005 and degrees < 0.1 and got.seen_through < 0.05
    metres, degrees, without = _station_error(_STATION_TURNED_OFF, no_restart)
    assert metres > 0.2 and degrees > 5 and without.seen_through > 0.15
    assert got.iterations > without.iterations
    _, _, strict = _station_error(_STATION_TURNED_OFF, RegistrationParams(restart_end_ratio=0.1))
    np.testing.assert_array_equal(strict.T_ref_from_cur, without.T_ref_from_cur)
    assert strict.iterations > without.iterations  # the passes ran, and were not taken
    quiet = (9000, "none", (0.10, 4.0, 62388))
    _, _, got = _station_error(quiet)
    _, _, without = _station_error(quiet, no_restart)
    assert got.seen_through < RegistrationParams().restart_end_through
    np.testing.assert_array_equal(got.T_ref_from_cur, without.T_ref_from_cur)
    assert got.iterations == without.iterations


def test_a_pass_whose_coarsest_end_was_seen_is_given_up():
    """Step 7d's passes share their coarsest ends: a pass that ends the coarsest level where
    an earlier one did (within 2 mm / 0.1 deg) stops there, T None, its iterations counted;
    one that ends elsewhere goes on and adds its end."""
    from sim_fixtures.stations import station_pair

    params = RegistrationParams()
    min_cos = math.cos(math.radians(params.max_normal_angle_deg))
    ref, cur, _truth, intrinsics = station_pair(*_STATION_TURNED_OFF)
    rls, cls = (pyramid.levels(d, intrinsics, params) for d in (ref, cur))
    seen: list[np.ndarray] = []
    first = register._coarse_to_fine(rls, cls, np.eye(4), params, min_cos, seen)
    assert first[0] is not None and len(seen) == 1
    again = register._coarse_to_fine(rls, cls, np.eye(4), params, min_cos, seen)
    assert again[0] is None and again[1] > 0 and len(seen) == 1
    start = register._restart_starts(np.eye(4), params)[2]  # 10 cm along x: another basin
    other = register._coarse_to_fine(rls, cls, start, params, min_cos, seen)
    assert other[0] is not None and len(seen) == 2
    assert not register._same_pose(seen[0], seen[1])
    np.testing.assert_array_equal(
        register._coarse_to_fine(rls, cls, np.eye(4), params, min_cos)[0], first[0])

def test_slide_peaks_lie_on_the_weak_line_best_first():
    """From that wrong estimate, the starts slide_peaks gives lie on the line of its least
    constrained translation, 1 cm steps from it, not at it, best first; the best is within a
    step or two of the true pose along the line."""
    from sim_fixtures.stations import station_pair

    params = RegistrationParams(final_search_reach_m=0.0)
    ref, cur, truth, intrinsics = station_pair(*_STATION_ONE_MOVED)
    T = register_depth(ref, cur, intrinsics, params).T_ref_from_cur
    params = RegistrationParams()
    min_cos = math.cos(math.radians(params.max_normal_angle_deg))
    rl, cl = (pyramid.levels(d, intrinsics, params)[params.search_level] for d in (ref, cur))
    A = icp.icp_level(rl, cl, T, params, params.search_level, min_cos, icp.Pairs(cl))[5]
    direction = np.linalg.eigh(A[3:, 3:])[1][:, 0]
    starts = agreement.slide_peaks(rl, cl, T, A, params, min_cos)
    assert 1 <= len(starts) <= params.final_search_starts
    for st in starts:
        np.testing.assert_allclose(st[:3, :3], T[:3, :3])
        step = (st[:3, 3] - T[:3, 3]) @ direction / params.final_search_step_m
        assert abs(step - round(step)) < 1e-6 and round(step) != 0
        np.testing.assert_allclose(st[:3, 3], T[:3, 3] + step * params.final_search_step_m
                                   * direction, atol=1e-9)
    scores = agreement.score_poses(rl, cl, starts, params, min_cos, True,
                                   params.table_hole_weight)
    assert list(scores) == sorted(scores, reverse=True)
    assert abs((truth[:3, 3] - starts[0][:3, 3]) @ direction) < 0.025


# One object moved, the revisit 15 cm away (the fresh 16000 set of stop 40): the coarsest
# level slides 23 cm off along the wall and the middle level's 10 cm search steps 20 cm
# farther, where the table lines up with the view 41 cm from the truth.
_STATION_CARRIED_OFF = (16005, "one_moved", (0.15, 6.0, 11472))


def test_the_final_search_looks_round_the_initial_pose_too():
    """ICP does not move an estimate along a slide, and the searches before the final one
    carried this one 41 cm from the truth, farther than the robot stands from its station
    pose (15 cm). The final search's line covers its reach round the initial pose as well as
    round the estimate: one of its peaks lies at the truth, which wins at the finest level;
    without the initial pose the line ends 30 cm from the estimate, short of the truth."""
    from sim_fixtures.stations import station_pair

    metres, degrees, got = _station_error(_STATION_CARRIED_OFF)
    assert metres < 0.005 and degrees < 0.1 and "x" in got.weak
    ref, cur, truth, intrinsics = station_pair(*_STATION_CARRIED_OFF)
    params = RegistrationParams()
    min_cos = math.cos(math.radians(params.max_normal_angle_deg))
    T = register_depth(ref, cur, intrinsics, RegistrationParams(final_search_reach_m=0.0)
                       ).T_ref_from_cur
    assert np.linalg.norm((invert(truth) @ T)[:3, 3]) > 0.3
    rl, cl = (pyramid.levels(d, intrinsics, params)[params.search_level] for d in (ref, cur))
    A = icp.icp_level(rl, cl, T, params, params.search_level, min_cos, icp.Pairs(cl))[5]
    direction = np.linalg.eigh(A[3:, 3:])[1][:, 0]
    along = lambda pose: float((pose[:3, 3] - truth[:3, 3]) @ direction)  # noqa: E731
    near = agreement.slide_peaks(rl, cl, T, A, params, min_cos)
    assert all(abs(along(st)) > 0.05 for st in near)
    wide = agreement.slide_peaks(rl, cl, T, A, params, min_cos, np.eye(4))
    assert any(abs(along(st)) < 0.025 for st in wide)


def test_a_slide_nothing_pins_is_said_weak():
    """Every object on the table moved, and they line up 28 cm along the wall better than the
    table's legs do at the truth: without the structure's search (step 7c, which takes this
    one to the truth and keeps `x` said) the estimate is wrong, and no surface facing along
    the slide fits there, so the slide is said weak by that count alone (without the checks,
    nothing was said)."""
    metres, _degrees, got = _station_error(_STATION_LINED_UP)
    assert metres < 0.005 and "x" in got.weak
    no_search = RegistrationParams(station_through_ratio=0.0)
    metres, _degrees, got = _station_error(_STATION_LINED_UP, no_search)
    assert metres > 0.05 and "x" in got.weak
    _metres, _degrees, support_only = _station_error(
        _STATION_LINED_UP, no_search.replace(slide_contested_share=1.0))
    assert "x" in support_only.weak
    _metres, _degrees, unchecked = _station_error(
        _STATION_LINED_UP, no_search.replace(slide_support_share=0.0, slide_contested_share=1.0))
    assert unchecked.weak == ()


def test_a_contested_slide_is_said_weak():
    """Every object on the table moved; some line up 45 mm along the wall, where their sides
    fit, but most of what faces along the slide (the legs, the other objects) contradicts
    that pose: the slide is contested and said weak (without that check, nothing was until
    step 7e, whose structure alone does not pin it either). The structure's search (step
    7c) takes it to the truth, `x` kept said."""
    metres, _degrees, got = _station_error(_STATION_CONTESTED)
    assert metres < 0.005 and "x" in got.weak
    no_search = RegistrationParams(station_through_ratio=0.0)
    metres, _degrees, got = _station_error(_STATION_CONTESTED, no_search)
    assert metres > 0.03 and "x" in got.weak
    _metres, _degrees, contest_only = _station_error(
        _STATION_CONTESTED, no_search.replace(slide_support_share=0.0))
    assert "x" in contest_only.weak
    # without the contest the structure alone (step 7e) does not pin it: said all the same
    _metres, _degrees, uncontested = _station_error(
        _STATION_CONTESTED, no_search.replace(slide_contested_share=1.0))
    assert "x" in uncontested.weak
    _metres, _degrees, unchecked = _station_error(
        _STATION_CONTESTED, no_search.replace(slide_support_share=0.0, slide_contested_share=1.0))
    assert unchecked.weak == ()


@pytest.mark.parametrize("name", ["office_far_offset", "storage_other_room"])
def test_another_place_is_not_at_station_not_a_change(name):
    sc = load_scene(name)
    ref = build_scene(sc.reference_frames(), intrinsics=sc.intrinsics)
    cs = detect_changes(ref, sc.current_frames()[0], intrinsics=sc.intrinsics)
    assert cs.outcome == "not_at_station" and not cs.changed and cs.regions == ()
    assert cs.not_at_station_reason
    summary = cs.summary()
    assert summary["outcome"] == "not_at_station"
    assert set(summary["registration"]) >= {"T_ref_from_cur", "translation_m", "rotation_deg",
                                             "fitness", "rmse_m", "weak_directions", "ms"}


def test_what_lies_behind_the_reference_counts_for_the_station():
    """A table station revisited from 15 cm away, one object moved 8-20 cm: the pose is right,
    but a quarter of the current's cells fall outside the reference's image and a fifth lie
    behind what the reference saw nearer (the object's old place), so fewer than half fit.
    Hidden, not contradicted: the check compares and reports the move.  The rule itself:
    fitness plus that share against min_fitness."""
    from robot_change.change.registration.result import Registration
    from sim_fixtures.stations import station_checks, station_scene

    check = next(c for c in station_checks(1, 9009, "", (15,)) if c[2] == "one_moved")
    sc = station_scene(*check[1:])
    ref = build_scene(list(sc.reference_frames), intrinsics=sc.intrinsics)
    cs = detect_changes(ref, sc.current, intrinsics=sc.intrinsics)
    reg = cs.registration
    err = invert(sc.T_ref_from_cur) @ reg.T_ref_from_cur
    assert np.linalg.norm(err[:3, 3]) < 0.002 and reg.seen_through < 0.1
    assert reg.fitness < 0.5 <= reg.fitness + reg.behind
    assert cs.outcome == "changed" and cs.not_at_station_reason == ""
    params = RegistrationParams()
    for fitness, behind, at_station in ((0.45, 0.1, True), (0.45, 0.0, False),
                                        (0.3, 0.15, False)):
        got = Registration(np.eye(4), fitness, 0.0, (), np.ones(6), 0, 0, 0, True, 0.0,
                           0.0, behind).not_at_station(params)
        assert (got == "") == at_station
        assert at_station or "behind what the reference saw nearer" in got


def test_the_station_tolerance_covers_the_range_the_checks_are_measured_in():
    """Every revisit of the station sets (15 cm; 6 deg drawn as yaw / pitch / roll steps, which
    with the camera pitched down at a table compose to single turns of up to 7.8 deg) is within
    the tolerance with an estimate 1 cm / 0.5 deg off; 17 cm or 9 degrees is not."""
    from robot_change.change.registration.result import Registration
    from sim_fixtures.scenes import true_transform
    from sim_fixtures.stations import station_checks, station_spec

    params = RegistrationParams()
    off = np.eye(4)
    off[:3, :3] = rpy_deg_to_rotation(0.3, 0.3, 0.2)
    angles = []
    for base in range(8000, 18000, 1000):
        for _name, seed, change, offset in station_checks(10, base, levels=(15,)):
            T = true_transform(station_spec(seed, change, offset)) @ off
            T[:3, 3] *= 1.0 + 0.009 / 0.15  # an estimate 9 mm farther
            reg = Registration(T, 0.9, 0.0, (), np.ones(6), 0, 0, 0, True, 0.0)
            assert reg.not_at_station(params) == "", (seed, change)
            angles.append(reg.rotation_deg)
    assert max(angles) > 7.5
    beyond = np.eye(4)
    beyond[:3, 3] = (0.17, 0.0, 0.0)
    turned = np.eye(4)
    turned[:3, :3] = rpy_deg_to_rotation(0.0, 0.0, 9.0)
    for T, why in ((beyond, "offset"), (turned, "rotation")):
        reg = Registration(T, 0.9, 0.0, (), np.ones(6), 0, 0, 0, True, 0.0)
        assert reg.not_at_station(params).startswith(why)


def test_the_station_test_leaves_out_what_the_views_do_not_pin():
    """Along a weak direction the estimate is a search's pick, not measured: every object on a
    table moved, at the station itself, a slide 18 cm along x (weak x, 17000) must not read as
    the robot standing elsewhere.  The rotation vector is exp_so3's inverse."""
    from robot_change.change.registration.result import Registration
    from robot_change.change.registration.rigid import rotation_vector

    for w in ([0.1, -0.05, 0.02], [0.0, 0.0, 0.0], [0.0, 2.0, 0.5]):
        np.testing.assert_allclose(rotation_vector(exp_so3(np.array(w))), w, atol=1e-12)
    half_turn = rotation_vector(exp_so3(np.array([0.0, 0.6, 0.8]) * math.pi))
    assert np.linalg.norm(half_turn) == pytest.approx(math.pi)  # never read as a small turn
    np.testing.assert_allclose(np.abs(half_turn), np.array([0.0, 0.6, 0.8]) * math.pi,
                               atol=1e-6)
    params = RegistrationParams()
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.radians([0.0, 12.0, 2.0]))
    T[:3, 3] = (0.18, 0.02, 0.01)
    slid = Registration(T, 0.7, 0.0, ("x", "rot_y"), np.ones(6), 0, 0, 0, True, 0.0)
    moved, turned = slid.pinned_offset()
    assert moved == pytest.approx(math.hypot(0.02, 0.01)) and turned == pytest.approx(2.0)
    assert slid.not_at_station(params) == ""
    pinned = dataclasses.replace(slid, weak=())
    assert pinned.not_at_station(params).startswith("offset 0.18 m")
    assert dataclasses.replace(slid, weak=("x",)).not_at_station(params).startswith("rotation")


def test_offset_beyond_the_station_tolerance_is_not_at_station():
    sc = load_scene("office_no_change_pose_10cm")
    ref = build_scene(sc.reference_frames(), intrinsics=sc.intrinsics)
    tight = ChangeParams(registration=RegistrationParams(max_translation_m=0.05))
    cs = detect_changes(ref, sc.current_frames()[0], tight, intrinsics=sc.intrinsics)
    assert cs.outcome == "not_at_station" and "offset" in cs.not_at_station_reason
    assert detect_changes(ref, sc.current_frames()[0], intrinsics=sc.intrinsics).outcome == \
        "no_change"


def test_registration_switched_off_is_the_identity(office_pair):
    ref, cur, _ = office_pair
    got = register_depth(ref, cur, INTR, RegistrationParams(enabled=False))
    assert got.is_identity and got.fitness == 1.0
    given = np.eye(4)
    given[:3, 3] = (0.01, 0.02, 0.03)
    taken = register_depth(ref, cur, INTR, RegistrationParams(enabled=False), initial=given)
    np.testing.assert_array_equal(taken.T_ref_from_cur, given)
    # a start that is no rigid transform was taken as it was (a scale of 2: no_change with
    # fitness 0; a mirror: 65 false regions)
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    for bad in (np.diag([2.0, 2.0, 2.0, 1.0]), mirror, np.ones((4, 4))):
        with pytest.raises(InputError, match="rigid transform"):
            register_depth(ref, cur, INTR, initial=bad)


def test_a_kept_reference_pyramid_gives_the_same_registration(office_pair):
    """keep=: the reference's pyramid is built once and reused; the estimate is the same."""
    ref, cur, _ = office_pair
    fresh = register_depth(ref, cur, INTR)
    kept: dict = {}
    first = register_depth(ref, cur, INTR, keep=kept)
    assert len(kept) == 1
    second = register_depth(ref, cur, INTR, keep=kept, initial=np.eye(4))
    for got in (first, second):
        np.testing.assert_array_equal(got.T_ref_from_cur, fresh.T_ref_from_cur)
        assert (got.fitness, got.rmse_m, got.weak) == (fresh.fitness, fresh.rmse_m, fresh.weak)
    coarse = RegistrationParams(levels=(32, 16, 8))
    register_depth(ref, cur, INTR, coarse, keep=kept)
    assert len(kept) == 2  # other pyramid parameters: another entry


def test_bad_input_is_refused_with_typed_errors(office_pair):
    ref, cur, _ = office_pair
    with pytest.raises(InputError, match="uint16"):
        register_depth(ref.astype(np.float32), cur, INTR)
    with pytest.raises(InputError, match="intrinsics"):
        register_depth(ref[:100], cur[:100], INTR)
    with pytest.raises(InputError, match="twice"):
        RegistrationParams(levels=(16, 4, 2))
    with pytest.raises(InputError, match="same length"):
        RegistrationParams(iterations=(1, 2))
    with pytest.raises(InputError, match="RegistrationParams"):
        ChangeParams(registration="yes")
    for name in ("table_outline_holes", "table_static_share", "fine_search_step_m",
                 "fine_search_reach_m", "fine_search_ratio", "slide_support_share",
                 "slide_contested_share", "final_search_step_m", "final_search_reach_m",
                 "final_search_margin", "restart_step_m",
                 "station_through_ratio", "station_through_min", "station_through_max",
                 "restart_end_through", "restart_end_ratio"):
        for bad in (-0.1, 1.5, "0.02", float("nan")):
            with pytest.raises(InputError, match=name):
                RegistrationParams(**{name: bad})
    for bad in (0, 21, 2.5, "2"):
        with pytest.raises(InputError, match="final_search_starts"):
            RegistrationParams(final_search_starts=bad)
    for bad in (-1.0, 46.0, "5"):
        with pytest.raises(InputError, match="restart_step_deg"):
            RegistrationParams(restart_step_deg=bad)


# --------------------------------------------------------------------------- table stations


# Every object on the table moved, the revisit 10 cm / 4 deg away (the bench's 9000 set, one
# of the checks the structure's say was looked at on): the estimate slid 77 mm along the wall,
# where the moved objects line up.
_STATION_EVERY_MOVED = (9000, "all_moved", (0.10, 4.0, 20364))


def _station_views(station):
    """(reference levels, the reference's rendered object ids, the station's name -> id) of a
    station (sim_fixtures.stations)."""
    from sim_fixtures.scenes import object_ids, render_pair
    from sim_fixtures.stations import station_pair, station_spec

    ref, _cur, _truth, intrinsics = station_pair(*station)
    spec = station_spec(*station)
    rendered, _ = render_pair(spec)
    return pyramid.levels(ref, intrinsics, RegistrationParams()), rendered.ids, object_ids(spec)


def _cells_of(level, ids, wanted):
    """(h, w) bool: the cells of ``level`` with a reading whose pixels are all of the
    rendered objects ``wanted``, and those with none of them."""
    f = level.factor
    h, w = level.vertex.shape[:2]
    share = np.isin(ids[:h * f, :w * f], wanted).reshape(h, f, w, f).mean(axis=(1, 3))
    seen = level.vertex[:, :, 2] > 0
    return seen & (share == 1.0), seen & (share == 0.0)


def test_a_table_station_has_a_table_over_the_floor(office_pair):
    """Of the station reference's planes the table is the one with the floor parallel beneath
    it: the rendered table's cells that face up lie on it. A room view (floor and walls, no
    plane parallel to the floor above it) has none."""
    ref_levels, ids, names = _station_views(_STATION_EVERY_MOVED)
    level = ref_levels[RegistrationParams().search_level]
    plane = table_station.support_plane(level)
    assert plane is not None
    n, d = plane
    table, _ = _cells_of(level, ids, [names["table"]])
    up = table & (np.abs(level.normal @ n) > 0.95)
    assert up.sum() > 500
    assert (np.abs(level.vertex[up] @ n + d) < 0.01).mean() > 0.8
    room = pyramid.levels(office_pair[0], INTR, RegistrationParams())
    assert table_station.support_plane(room[RegistrationParams().search_level]) is None


def test_objects_on_a_table_are_what_stands_on_it():
    """The cells the rule says stand on the table are the rendered objects': nearly all of
    them, and nearly nothing of the table, its legs, the floor or the walls."""
    ref_levels, ids, names = _station_views(_STATION_EVERY_MOVED)
    params = RegistrationParams()
    level = ref_levels[-1]
    plane = table_station.support_plane(ref_levels[params.search_level])
    got = table_station.objects_on_table(level, plane, params)
    items, others = _cells_of(level, ids, [v for k, v in names.items() if k.startswith("item")])
    assert items.sum() > 300
    assert got[items].mean() > 0.9
    assert got[others].mean() < 0.01
    # an object's foot, lower than table_object_m, is claimed by its sideways normal
    n, d = plane
    foot = items & (level.vertex @ n + d < params.table_object_m) \
        & (np.abs(level.normal @ n) < 0.5)
    assert foot.sum() > 10 and got[foot].mean() > 0.9


def test_where_every_object_moved_the_table_and_its_legs_decide_the_slide():
    """Every object on the table moved and the estimate slid 77 mm along the wall, where the
    moved objects line up and outnumber the table's legs and ends that pin the slide (the
    both-ways score of the final search prefers it too). Left out, the objects on the table
    say nothing, and the rest is seen through at 0.2 % of the cells there against under
    0.03 % at the truth: the structure's search takes the estimate to within 5 mm. Without it
    (ratio 0) the estimate stays where the objects line up; `x` stays said either way."""
    metres, degrees, got = _station_error(_STATION_EVERY_MOVED)
    assert metres < 0.005 and degrees < 0.1 and "x" in got.weak
    metres, _degrees, got = _station_error(_STATION_EVERY_MOVED,
                                           RegistrationParams(station_through_ratio=0.0))
    assert metres > 0.05 and "x" in got.weak
    # a station's reference keeps its pyramid, its table and what stands on it between checks:
    # the same estimate, check after check
    from sim_fixtures.stations import station_pair

    ref, cur, _truth, intrinsics = station_pair(*_STATION_EVERY_MOVED)
    keep: dict = {}
    first, again = (register_depth(ref, cur, intrinsics, keep=keep) for _ in range(2))
    np.testing.assert_array_equal(first.T_ref_from_cur, again.T_ref_from_cur)
    unkept = _station_error(_STATION_EVERY_MOVED)[2]
    np.testing.assert_allclose(first.T_ref_from_cur, unkept.T_ref_from_cur, atol=1e-9)


# Every object on the table moved, the revisit 15 cm / 6 deg away (the bench's 12000 set): the
# moved objects line up 24 cm along the wall, and the structure, the table's ends and legs out
# of view, does not tell that pose from the truth.
_STATION_UNPINNED = (12006, "all_moved", (0.15, 6.0, 65550))


def test_a_slide_only_what_stands_on_the_table_pins_is_said_weak(monkeypatch):
    """Where every object moved and lined up 24 cm along the wall, the objects' sides pin the
    slide and the whole view has nothing against it: without step 7e nothing is said. The
    structure alone (what stands on the table without normals) pins it in none of its cells,
    so `x` is said weak, the estimate left where it is. One object moved at another station
    whose structure does not pin the slide either: `x` is said there too, and the right
    estimate is not searched away from (a search there went 29 cm off). The same station
    with nothing changed, its structure pinning the slide, says nothing."""
    params = RegistrationParams()
    metres, _degrees, got = _station_error(_STATION_UNPINNED)
    assert "x" in got.weak and metres > 0.2
    with monkeypatch.context() as m:
        m.setattr(register, "_structure_slide", lambda *args: ())
        _metres, _degrees, unsaid = _station_error(_STATION_UNPINNED)
    assert unsaid.weak == ()
    np.testing.assert_array_equal(unsaid.T_ref_from_cur, got.T_ref_from_cur)
    from sim_fixtures.stations import station_pair

    ref, cur, _truth, intrinsics = station_pair(*_STATION_UNPINNED)
    rls, cls = (pyramid.levels(d, intrinsics, params) for d in (ref, cur))
    rn, cn = table_station.structure_levels(rls, cls, got.T_ref_from_cur, params)
    objects = table_station.station_objects(rls, cls, got.T_ref_from_cur, params)
    for level, structure, on_table in ((rls[-1], rn, objects[0]), (cls[-1], cn, objects[1])):
        assert on_table.sum() > 300
        assert not structure.normal[on_table].any()
        np.testing.assert_array_equal(structure.normal[~on_table], level.normal[~on_table])
        np.testing.assert_array_equal(structure.vertex, level.vertex)
    metres, degrees, got = _station_error((14002, "one_moved", (0.05, 2.0, 88886)))
    assert "x" in got.weak and metres < 0.002 and degrees < 0.05
    metres, _degrees, got = _station_error((12006, "none", (0.15, 6.0, 3885)))
    assert metres < 0.002 and got.weak == ()


def test_the_structure_keeps_a_right_estimate():
    """A station where nothing changed, 10 cm away: the estimate is right, the structure
    agrees with it, and it is kept to the micrometre with and without the search."""
    station = (9000, "none", (0.10, 4.0, 62388))
    with_search = _station_error(station)[2].T_ref_from_cur
    without = _station_error(station, RegistrationParams(station_through_ratio=0.0))[2]
    assert np.abs(with_search - without.T_ref_from_cur).max() < 1e-6
    assert _station_error(station)[0] < 0.002


# --------------------------------------------------------------------------- table-plane starts


def _plane_grid_twin(vertex, rot, trans, cell_m, lo_x, lo_y, rows, cols, object_m, below_m):
    p = vertex.reshape(-1, 3)
    p = p[p[:, 2] > 0]
    q = p @ rot.T + trans
    q = q[q[:, 2] > -below_m]
    r = np.floor((q[:, 0] - lo_x) / cell_m).astype(np.int64)
    c = np.floor((q[:, 1] - lo_y) / cell_m).astype(np.int64)
    ok = (r >= 0) & (c >= 0) & (r < rows) & (c < cols)
    out = np.zeros((rows, cols))
    out[r[ok], c[ok]] = -1.0
    obj = ok & (q[:, 2] > object_m)
    out[r[obj], c[obj]] = 1.0
    return out


_BOXES = ((-0.2, 0.1, 0.12, 0.08, 0.10), (0.15, -0.15, 0.08, 0.08, 0.2),
          (0.25, 0.2, 0.2, 0.1, 0.05))


def _table_scene(T_world_from_cam, table=(-0.5, 0.5, -0.4, 0.4), boxes=_BOXES):
    """(480, 640) uint16 mm: a table top (z = 0 in the world; ``table`` its x0, x1, y0, y1 m,
    1.0 x 0.8 m centred at the origin by default) with ``boxes`` (centre x, y, size x, y, z m;
    three by default) on it, seen by a camera at ``T_world_from_cam`` (4, 4); points sampled
    every 2 mm, splatted into a z-buffer; nothing beyond the table."""
    g = np.arange(table[0], table[1], 0.002)
    h = np.arange(table[2], table[3], 0.002)
    X, Y = np.meshgrid(g, h)
    pts = [np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)]
    for (cx, cy, sx, sy, sz) in boxes:
        a = np.arange(-sx / 2, sx / 2, 0.002)
        b = np.arange(-sy / 2, sy / 2, 0.002)
        c = np.arange(0, sz, 0.002)
        A, B = np.meshgrid(a, b)
        pts.append(np.stack([cx + A.ravel(), cy + B.ravel(), np.full(A.size, sz)], axis=1))
        for fixed, (u, w) in ((0, (b, c)), (1, (a, c))):
            U, W = np.meshgrid(u, w)
            for side in (-1, 1):
                q = np.empty((U.size, 3))
                q[:, fixed] = (cx, cy)[fixed] + side * (sx, sy)[fixed] / 2
                q[:, 1 - fixed] = (cx, cy)[1 - fixed] + U.ravel()
                q[:, 2] = W.ravel()
                pts.append(q)
    p = np.concatenate(pts)
    T = invert(T_world_from_cam)
    p = p @ T[:3, :3].T + T[:3, 3]
    p = p[p[:, 2] > 0.1]
    u = np.floor(INTR.fx * p[:, 0] / p[:, 2] + INTR.cx + 0.5).astype(np.int64)
    v = np.floor(INTR.fy * p[:, 1] / p[:, 2] + INTR.cy + 0.5).astype(np.int64)
    inside = (u >= 0) & (v >= 0) & (u < 640) & (v < 480)
    out = np.full((480, 640), np.iinfo(np.int64).max)
    np.minimum.at(out, (v[inside], u[inside]), np.round(p[inside, 2] * 1000).astype(np.int64))
    out[out == np.iinfo(np.int64).max] = 0
    return out.astype(np.uint16)


def _camera_over_table(x, y, yaw_deg):
    """(4, 4) world-from-camera: 0.6 m above the table, 0.6 m back from its centre, looking
    down at 45 degrees, turned by ``yaw_deg`` about the table's normal, moved by (x, y) m."""
    down = rpy_deg_to_rotation(-135.0, 0.0, 0.0)  # optical z forward-down, y down the view
    T = np.eye(4)
    T[:3, :3] = rpy_deg_to_rotation(0.0, 0.0, yaw_deg) @ down
    T[:3, 3] = (x, y - 0.6, 0.6)
    return T


def test_plane_grid_matches_numpy(office_pair):
    ref, _, _ = office_pair
    lv = pyramid.levels(ref, INTR, RegistrationParams())[2]
    n, d, frac = table_top._dominant_plane(pyramid.levels(ref, INTR, RegistrationParams())[0])
    to_plane = invert(table_top.plane_frame(n, d))
    args = (0.05, -3.0, -1.0, 96, 120, 0.015, 0.03)
    got = table_top._plane_grid(lv.vertex, to_plane[:3, :3].copy(), to_plane[:3, 3].copy(), *args)
    want = _plane_grid_twin(lv.vertex, to_plane[:3, :3], to_plane[:3, 3], *args)
    np.testing.assert_array_equal(got, want)
    assert (got == 1).sum() > 100 and (got == -1).sum() > 100  # floor and things on it
    assert abs(n @ np.array([0.0, -1.0, 0.0])) > 0.9 and 0.3 < frac < 0.8  # the floor


def test_table_top_starts_put_one_start_near_the_truth():
    W_ref = _camera_over_table(0.0, 0.0, 0.0)
    W_cur = _camera_over_table(0.06, -0.05, 4.0)
    ref, cur = _table_scene(W_ref), _table_scene(W_cur)
    truth = invert(W_ref) @ W_cur  # T_ref_from_cur
    params = RegistrationParams()
    rl, cl = pyramid.levels(ref, INTR, params), pyramid.levels(cur, INTR, params)
    n, d, frac = table_top._dominant_plane(rl[0])
    assert frac > params.table_plane_fraction and d == pytest.approx(0.6, abs=0.01)
    planes = table_top.table_planes(rl, cl, params)
    assert planes is not None
    starts = table_top.table_starts(rl, cl, planes, params)
    assert 1 <= len(starts) <= params.table_starts
    errs = [(np.linalg.norm(e[:3, 3]), rotation_angle_deg(e[:3, :3]))
            for e in (invert(truth) @ s for s in starts)]
    assert any(e_t < 0.03 and e_r < 2.0 for e_t, e_r in errs), errs
    got = register_depth(ref, cur, INTR)
    err = invert(truth) @ got.T_ref_from_cur
    assert np.linalg.norm(err[:3, 3]) < 0.01 and rotation_angle_deg(err[:3, :3]) < 0.5


def test_tables_that_do_not_overlap_leave_the_table_plane_directions_weak():
    """Every box moved and the two views cut the table differently (a narrower and deeper
    one against a wider one, as a crop that changed): whatever pose is estimated,
    each view's table lands on the other's no reading, so the slides in the table's plane and
    the turn about its normal are reported weak, never guessed.  The same views with the
    same table leave nothing weak."""
    W_ref = _camera_over_table(0.0, 0.0, 0.0)
    W_cur = _camera_over_table(0.04, -0.03, 2.0)
    params = RegistrationParams()
    ref = _table_scene(W_ref)
    cur = _table_scene(W_cur, table=(-0.3, 0.3, -0.4, 0.6), boxes=((0.0, 0.4, 0.1, 0.1, 0.1),))
    got = register_depth(ref, cur, INTR)
    rl, cl = pyramid.levels(ref, INTR, params), pyramid.levels(cur, INTR, params)
    planes = table_top.table_planes(rl, cl, params)
    assert planes is not None
    T = got.T_ref_from_cur
    holes = (table_top._table_holes(rl[-1], cl[-1], invert(T), planes[0], params),
             table_top._table_holes(cl[-1], rl[-1], T, planes[1], params))
    assert min(holes) > params.table_outline_holes, holes
    in_plane = table_top.in_plane_names(planes[1])
    assert len(in_plane) == 3 and "x" in in_plane  # the table's width runs along camera x
    assert set(in_plane) <= set(got.weak)
    # the outline check alone says it (every box moved too: the next test's check is off)
    min_cos = np.cos(np.radians(params.max_normal_angle_deg))
    assert table_top.table_pose_weak(rl[-1], cl[-1], T, planes, (), params.replace(
        table_static_share=0.0), min_cos)
    assert not table_top.table_pose_weak(rl[-1], cl[-1], T, planes, (), params.replace(
        table_static_share=0.0, table_outline_holes=0.0), min_cos)
    same_cur = _table_scene(W_cur)
    assert register_depth(ref, same_cur, INTR).weak == ()
    truth = invert(W_ref) @ W_cur
    same_cl = pyramid.levels(same_cur, INTR, params)
    same_planes = table_top.table_planes(rl, same_cl, params)
    assert max(table_top._table_holes(rl[-1], same_cl[-1], invert(truth), same_planes[0], params),
               table_top._table_holes(same_cl[-1], rl[-1], truth, same_planes[1], params)) < 0.02


def test_a_table_where_no_object_stayed_put_leaves_the_table_plane_directions_weak():
    """Every box moved (the same table, the same outline): no object cell fits the other view
    at the estimate, so the pose in the table's plane rests on the outline alone and is
    reported weak, as on a bare table.  With two boxes left where they were (one moved, one
    taken away), their cells fit and nothing is weak; ``table_static_share=0`` turns the
    check off."""
    W_ref = _camera_over_table(0.0, 0.0, 0.0)
    W_cur = _camera_over_table(0.03, -0.02, 1.5)
    truth = invert(W_ref) @ W_cur
    params = RegistrationParams()
    ref = _table_scene(W_ref)
    moved = ((0.05, 0.3, 0.12, 0.08, 0.10), (-0.3, -0.2, 0.08, 0.08, 0.2),
             (0.3, -0.1, 0.2, 0.1, 0.05))
    rl = pyramid.levels(ref, INTR, params)
    min_cos = np.cos(np.radians(params.max_normal_angle_deg))
    for boxes, stayed in ((moved, False), (_BOXES[:2] + moved[:1], True)):
        cur = _table_scene(W_cur, boxes=boxes)
        got = register_depth(ref, cur, INTR)
        err = invert(truth) @ got.T_ref_from_cur
        cl = pyramid.levels(cur, INTR, params)
        planes = table_top.table_planes(rl, cl, params)
        assert planes is not None
        share = table_top._static_object_share(rl[-1], cl[-1], got.T_ref_from_cur, planes,
                                             params, min_cos)
        in_plane = set(table_top.in_plane_names(planes[1]))
        if stayed:
            assert np.linalg.norm(err[:3, 3]) < 0.01 and rotation_angle_deg(err[:3, :3]) < 0.5
            assert share > params.table_static_share and got.weak == (), (share, got.weak)
        else:
            assert share < params.table_static_share, share
            assert in_plane <= set(got.weak), got.weak
            alone = params.replace(table_outline_holes=0.0)  # this check alone says it
            assert table_top.table_pose_weak(rl[-1], cl[-1], got.T_ref_from_cur, planes, (),
                                            alone, min_cos)
            assert not table_top.table_pose_weak(rl[-1], cl[-1], got.T_ref_from_cur, planes,
                                                (), alone.replace(table_static_share=0.0),
                                                min_cos)
    # nothing changed at all: the object cells fit (but for edges and occlusions)
    same = _table_scene(W_cur)
    same_cl = pyramid.levels(same, INTR, params)
    assert table_top._static_object_share(rl[-1], same_cl[-1], truth, table_top.table_planes(
        rl, same_cl, params), params, min_cos) > 10 * params.table_static_share


def test_one_low_box_on_a_table_names_every_table_plane_direction_weak():
    """Nothing changed, but the one low box (20 x 10 x 5 cm) barely pins the slides along the
    table: the normal equations flag the weakest direction, which mixes a slide with the
    turn about the table's normal, so all three motions in the table's plane are named --
    the estimate there is not measured (here it is centimetres off)."""
    W_ref = _camera_over_table(0.0, 0.0, 0.0)
    W_cur = _camera_over_table(0.03, -0.02, 1.5)
    params = RegistrationParams()
    ref, cur = (_table_scene(W, boxes=_BOXES[2:]) for W in (W_ref, W_cur))
    got = register_depth(ref, cur, INTR)
    rl, cl = pyramid.levels(ref, INTR, params), pyramid.levels(cur, INTR, params)
    planes = table_top.table_planes(rl, cl, params)
    assert planes is not None and got.eigenvalues[0] < params.weak_eigenvalue
    assert set(table_top.in_plane_names(planes[1])) <= set(got.weak), got.weak
    min_cos = np.cos(np.radians(params.max_normal_angle_deg))
    assert table_top._static_object_share(rl[-1], cl[-1], got.T_ref_from_cur, planes, params,
                                        min_cos) > params.table_static_share  # not that check


def test_the_reference_says_whether_the_station_is_a_table_top():
    """A big box (60 x 50 x 30 cm) put on the table leaves the table under
    ``table_plane_fraction`` of the current's cells; the station is still a table top (the
    reference says so) and the current's dominant plane is that table.  A current whose
    dominant plane is turned further than ``table_max_tilt_deg`` from the reference's is not
    the table seen again."""
    W_ref = _camera_over_table(0.0, 0.0, 0.0)
    W_cur = _camera_over_table(0.04, -0.03, 2.0)
    params = RegistrationParams()
    ref = _table_scene(W_ref)
    cur = _table_scene(W_cur, boxes=_BOXES + ((0.0, 0.0, 0.6, 0.5, 0.3),))
    rl, cl = pyramid.levels(ref, INTR, params), pyramid.levels(cur, INTR, params)
    assert table_top._dominant_plane(rl[0])[2] > params.table_plane_fraction
    _n, d, frac = table_top._dominant_plane(cl[0])
    assert frac < params.table_plane_fraction and d == pytest.approx(0.6, abs=0.01)
    planes = table_top.table_planes(rl, cl, params)
    assert planes is not None
    got = register_depth(ref, cur, INTR)  # the box hides two of the three boxes that stayed
    assert set(table_top.in_plane_names(planes[1])) <= set(got.weak), got.weak
    tilted = W_cur.copy()
    tilted[:3, :3] = W_cur[:3, :3] @ rpy_deg_to_rotation(params.table_max_tilt_deg + 5.0, 0, 0)
    assert table_top.table_planes(rl, pyramid.levels(_table_scene(tilted), INTR, params),
                                 params) is None


def test_room_views_are_not_table_tops(office_pair):
    """A room's floor is larger than a table top (table_max_extent_m): no table planes, so no
    starts and no trimming of objects."""
    ref, cur, _ = office_pair
    params = RegistrationParams()
    rl, cl = pyramid.levels(ref, INTR, params), pyramid.levels(cur, INTR, params)
    assert table_top.table_planes(rl, cl, params) is None
    loose = params.replace(table_plane_fraction=0.0, table_max_extent_m=100.0)
    planes = table_top.table_planes(rl, cl, loose)
    assert planes is not None and table_top.table_starts(rl, cl, planes, loose) != []


def test_the_plane_frame_is_a_rotation_for_any_plane_normal():
    """A plane facing the camera's x axis (a camera rolled by 90 degrees over a table) too."""

    for n in ([0.0, -0.8, -0.6], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]):
        n = np.array(n) / np.linalg.norm(n)
        F = table_top.plane_frame(n, 1.2)
        R = F[:3, :3]
        assert np.all(np.isfinite(F))
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R[:, 2], n) and np.isclose(n @ F[:3, 3] + 1.2, 0.0)


# --------------------------------------------------------------------------- trimming the change


@pytest.fixture(scope="module")
def tabletop(shared_data):
    from sim_fixtures.tabletop import load_tabletop_pair

    folder = shared_data / "osd-tabletop"
    if not folder.is_dir():
        pytest.skip(f"osd-tabletop not found in {shared_data}")
    return lambda name: load_tabletop_pair(name, folder)


@pytest.mark.parametrize("name", ["test36-test37", "learn40-learn41"])
def test_changed_objects_are_the_objects_that_moved(tabletop, name):
    """At the station (the camera did not move), the objects judged changed cover the truth's
    changed pixels both ways; nothing is judged changed against the view itself."""
    pair = tabletop(name)
    params = RegistrationParams()
    rl = pyramid.levels(pair.reference, pair.intrinsics, params)
    cl = pyramid.levels(pair.current, pair.intrinsics, params)
    planes = table_top.table_planes(rl, cl, params)
    assert planes is not None
    min_cos = math.cos(math.radians(params.max_normal_angle_deg))
    for own, other, plane, truth in ((cl[2], rl[2], planes[1], pair.truth_appeared),
                                     (rl[2], cl[2], planes[0], pair.truth_disappeared)):
        got = table_top._changed_objects(own, other, np.eye(4), plane, params, 0.06, min_cos)
        blocks = truth.reshape(120, 4, 160, 4).any(axis=(1, 3))  # the finest level's cells
        assert (got & blocks).sum() >= 0.9 * blocks.sum()
        assert (got & blocks).sum() >= 0.5 * got.sum()  # whole objects, most of them truth
        assert not table_top._changed_objects(own, own, np.eye(4), plane, params, 0.06,
                                            min_cos).any()


@pytest.mark.parametrize("name", ["test10-test11", "test13-test14"])
def test_a_moved_object_does_not_drag_the_estimate(tabletop, name):
    """Real table tops at the station (a camera that did not move) where a moved box pulled
    ICP 1.7-3.2 mm / 0.16-0.38 deg off before the change was trimmed."""
    pair = tabletop(name)
    got = register_depth(pair.reference, pair.current, pair.intrinsics)
    assert np.linalg.norm(got.translation_m) < 0.001 and got.rotation_deg < 0.1
    assert got.weak == ()


@pytest.mark.parametrize("offset_m, turn_deg, seed", [(0.05, 2.0, 99231), (0.10, 4.0, 99326),
                                                      (0.15, 6.0, 99174)])
def test_moved_objects_do_not_slide_a_displaced_table_top(tabletop, offset_m, turn_deg,
                                                          seed):
    """test36-test37 (all three objects moved) seen from a camera 5-15 cm away (the held3
    sample of bench_registration.py ``--tabletop``): the final search (step 7b), scoring the
    views whole, found the moved objects lined up 11-32 mm along the table and took a right
    estimate there.  A table top's in-plane pose has starts of its own (step 6b); the final
    search is not run on it."""
    from sim_fixtures.scenes import Pose, pose_offset
    from sim_fixtures.tabletop import seen_from

    pair = tabletop("test36-test37")
    station = Pose((0.0, 0.0, 0.0))
    truth = invert(station.matrix()) @ pose_offset(station, offset_m, turn_deg, seed).matrix()
    current = seen_from(pair.current, pair.intrinsics, invert(truth))
    got = register_depth(pair.reference, current, pair.intrinsics)
    D = invert(truth) @ got.T_ref_from_cur
    assert np.linalg.norm(D[:3, 3]) < 0.005 and rotation_angle_deg(D[:3, :3]) < 0.2


def test_seen_from_keeps_what_the_camera_saw():
    """sim_fixtures.tabletop.seen_from: at the identity the image itself; moved, a reading lands
    where the pinhole model puts it, and of two readings on one ray of the new camera the
    nearer is kept."""
    from sim_fixtures.tabletop import seen_from

    K = Intrinsics.openni_default()
    depth = np.zeros((480, 640), dtype=np.uint16)
    depth[100:140, 200:260] = 1500
    np.testing.assert_array_equal(seen_from(depth, K, np.eye(4)), depth)

    def pixel(p):  # (u, v) of a point in a camera's frame
        return (int(np.floor(K.fx * p[0] / p[2] + K.cx + 0.5)),
                int(np.floor(K.fy * p[1] / p[2] + K.cy + 0.5)))

    # the new camera 0.5 m to the right of the old one: two points straight ahead of it, at 1
    # and 2 m, are two pixels of the old image
    T = np.eye(4)
    T[0, 3] = -0.5
    depth = np.zeros((480, 640), dtype=np.uint16)
    for z in (1.0, 2.0):
        u, v = pixel((0.5, 0.0, z))
        depth[v, u] = round(z * 1000)
    moved = seen_from(depth, K, T)
    landed = {pixel(((u - K.cx) * d / 1000 / K.fx - 0.5, (v - K.cy) * d / 1000 / K.fy, d / 1000))
              for v, u in zip(*np.nonzero(depth), strict=True) for d in [int(depth[v, u])]}
    assert len(landed) == 1  # both on one pixel of the new image
    (u, v), = landed
    assert moved[v, u] == 1000 and np.count_nonzero(moved) == 1


def _level_at(depth_m: float, factor: int = 4) -> pyramid.Level:
    """A flat wall ``depth_m`` ahead as one pyramid level (cells ``factor`` pixels wide)."""
    h, w = 480 // factor, 640 // factor
    vertex = np.zeros((h, w, 3), np.float32)
    vertex[:, :, 2] = depth_m
    normal = np.zeros((h, w, 3), np.float32)
    normal[:, :, 2] = -1.0
    return pyramid.Level(factor, vertex, normal, INTR.fx / factor, INTR.fy / factor,
                         INTR.cx / factor, INTR.cy / factor)


def test_fitness_pairing_widens_only_where_the_noise_outgrows_the_level():
    params = RegistrationParams()
    min_cos = math.cos(math.radians(30.0))
    # A Kinect room at 1-3 m: the finest level's own distance and angle.
    for depth in (1.0, 2.0, 3.0):
        assert agreement.fitness_pairing(_level_at(depth), params, min_cos) == (
            params.max_distance_m[-1], min_cos)
    # At 4 m (29 mm a reading) the normals scatter past 30 degrees; the distance holds.
    dist, cos = agreement.fitness_pairing(_level_at(4.0), params, min_cos)
    assert dist == params.max_distance_m[-1] and 35.0 < math.degrees(math.acos(cos)) < 45.0
    # The paper's protocol: 100 mm of noise on every reading.  A cell is a mean of 16
    # readings (25 mm); two such means differ by 3 sqrt(2) 25 mm = 10.6 cm at 3 sigmas, and
    # the normals, taken across two cells 4.6 cm wide, say nothing (normals facing more than
    # 90 degrees apart pair).
    noisy = dataclasses.replace(params, noise=NoiseProfile(
        "paper_100mm", "simulated", (0.1, 0.0, 0.0), 0.0, 0.3, 10.0, 0.0))
    dist, cos = agreement.fitness_pairing(_level_at(3.0), noisy, min_cos)
    assert dist == pytest.approx(3.0 * math.sqrt(2.0) * 0.1 / 4, rel=1e-6)
    assert cos < 0.0
    # An empty level pairs as the level says.
    empty = _level_at(0.0)
    assert agreement.fitness_pairing(empty, noisy, min_cos) == (params.max_distance_m[-1], min_cos)
