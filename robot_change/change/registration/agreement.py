"""How well the two views agree at a pose: inlier pairs, the cells either view sees through
or puts on no reading of the other, the scores that rank candidate poses (the search along
weak directions, the table-top tracks), and the fitness, seen-through and behind shares of the
final estimate (docs/algorithm.md, "Registration", steps 6 and 8).  Kernels are
``@njit(cache=True, nogil=True)`` with NumPy twins in ``tests/test_registration.py``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from robot_change.noise.kernels import floored_margin_at, sigma_at

from .icp import land, pair
from .params import RegistrationParams
from .pyramid import Level
from .rigid import exp_so3, invert, rigid


@numba.njit(cache=True, nogil=True)
def cell_states(cur_v, cur_n, ref_v, ref_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos,
                noise, sigmas, through_sigmas, margin_m, margin_per_m2, facing, min_facing):
    """What the reference says of each current cell (``cur_v``, ``cur_n`` (h, w, 3)) moved by
    (rot, trans) and projected into it: 2 (contradicts) when it sees through the cell (its
    reading farther by more than the margin: ``margin_m + margin_per_m2 z^2``, or
    ``through_sigmas`` sigmas of the difference of two readings where wider,
    robot_change.noise.kernels.floored_margin_at with the sigma table ``noise``) or pairs
    it (:func:`~.icp.pair`) with a residual beyond ``sigmas`` sigmas of the noise of one
    reading; 1 (fits) when it pairs it within them; 0 otherwise (outside its image, on no
    reading, hidden behind a nearer reading, or not paired).  Only the cells whose normal has
    |n . ``facing``| >= ``min_facing`` (``facing`` (3,), current frame) are judged; the
    others are 0 (``min_facing`` 0: every cell).  Returns (h, w) int8."""
    h, w = cur_v.shape[0], cur_v.shape[1]
    out = np.zeros((h, w), dtype=np.int8)
    md2 = max_dist * max_dist
    for i in range(h):
        for j in range(w):
            if cur_v[i, j, 2] <= 0.0:
                continue
            if min_facing > 0.0 and abs(cur_n[i, j, 0] * facing[0] + cur_n[i, j, 1] * facing[1]
                                        + cur_n[i, j, 2] * facing[2]) < min_facing:
                continue
            px, py, pz, u, v = land(cur_v[i, j, 0], cur_v[i, j, 1], cur_v[i, j, 2], rot, trans,
                                    fx, fy, cx, cy, ref_v.shape[0], ref_v.shape[1])
            if u < 0:
                continue
            rz = ref_v[v, u, 2]
            if rz <= 0.0:
                continue
            margin = floored_margin_at(noise, pz, through_sigmas, margin_m, margin_per_m2)
            if rz > pz + margin:
                out[i, j] = 2
                continue
            if rz < pz - margin:
                continue
            paired, r, _, _, _ = pair(cur_n[i, j], ref_v, ref_n, v, u, px, py, pz, rot, md2,
                                      min_cos)
            if not paired:
                continue
            out[i, j] = 1 if abs(r) <= sigmas * sigma_at(noise, pz) else 2
    return out


@numba.njit(cache=True, nogil=True)
def _counts_until(own_v, own_n, other_v, other_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos,
                  noise, sigmas, through_sigmas, margin_m, margin_per_m2, count_pairs,
                  stop_below, pairable_after):
    """:func:`agreement_counts`, given up after a row ``i`` where the inliers less the cells
    seen through, plus ``pairable_after[i]`` (the view's cells with a normal in the rows
    after it: the most inliers still to come), fall below ``stop_below`` (-inf: never).
    Returns agreement_counts' tuple and whether the pass went to the end."""
    inliers = 0
    sq_sum = 0.0
    through = 0
    compared = 0
    holes = 0
    behind = 0
    md2 = max_dist * max_dist
    h = other_v.shape[0]
    w = other_v.shape[1]
    for i in range(own_v.shape[0]):
        for j in range(own_v.shape[1]):
            if own_v[i, j, 2] <= 0.0:
                continue
            px, py, pz, u, v = land(own_v[i, j, 0], own_v[i, j, 1], own_v[i, j, 2], rot, trans,
                                    fx, fy, cx, cy, h, w)
            if u < 0:
                continue
            rz = other_v[v, u, 2]
            if rz <= 0.0:
                holes += 1
                continue
            compared += 1
            margin = floored_margin_at(noise, pz, through_sigmas, margin_m, margin_per_m2)
            if rz > pz + margin:
                through += 1
            elif rz < pz - margin:
                behind += 1
            if not count_pairs:
                continue
            paired, r, _, _, _ = pair(own_n[i, j], other_v, other_n, v, u, px, py, pz, rot,
                                      md2, min_cos)
            if paired and abs(r) <= sigmas * sigma_at(noise, pz):
                inliers += 1
                sq_sum += r * r
        if inliers - through + pairable_after[i] < stop_below:
            return inliers, sq_sum, through, compared, holes, behind, False
    return inliers, sq_sum, through, compared, holes, behind, True


@numba.njit(cache=True, nogil=True)
def agreement_counts(own_v, own_n, other_v, other_n, rot, trans, fx, fy, cx, cy, max_dist,
                     min_cos, noise, sigmas, through_sigmas, margin_m, margin_per_m2,
                     count_pairs):
    """What the other view says of one view's cells (``own_v``, ``own_n`` (h, w, 3)) moved
    by (``rot`` (3, 3), ``trans`` (3,) m) into its image (intrinsics fx, fy, cx, cy of
    ``other_v``, ``other_n``), in one pass.  Of the cells that land inside its image: those
    that land on no reading (holes); those that land on one (compared), of them those it sees
    *through* (its reading farther than the point by more than the margin, ``margin_m +
    margin_per_m2 z^2`` or ``through_sigmas`` sigmas of the difference of two readings where
    wider: robot_change.noise.kernels.floored_margin_at with the sigma table ``noise``) and
    those that lie *behind* it (its reading nearer by as much: hidden from it).  When
    ``count_pairs``: the inliers, the pairs (:func:`~.icp.pair`: within ``max_dist``, normals
    within acos ``min_cos``) whose residual is within ``sigmas`` sigmas of one reading's
    noise, and the sum of their squared residuals (m^2); else both 0.
    Returns (inliers, squared residuals, through, compared, holes, behind)."""
    inliers, sq_sum, through, compared, holes, behind, _ = _counts_until(
        own_v, own_n, other_v, other_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos, noise,
        sigmas, through_sigmas, margin_m, margin_per_m2, count_pairs, -np.inf,
        np.zeros(own_v.shape[0], np.int64))
    return inliers, sq_sum, through, compared, holes, behind


@numba.njit(cache=True, nogil=True)
def through_counts(own_v, other_v, rots, transs, fx, fy, cx, cy, noise, through_sigmas,
                   margin_m, margin_per_m2):
    """For each pose (``rots`` (n, 3, 3), ``transs`` (n, 3) m: other-from-own), the cells of
    ``own_v`` (h, w, 3) m (z = 0: none) that ``other_v`` (intrinsics fx, fy, cx, cy) sees
    through: :func:`agreement_counts`' through, for many poses in one call (no pairs counted,
    so no normals are read).  Returns (n,) int64."""
    out = np.zeros(rots.shape[0], dtype=np.int64)
    never = np.zeros(own_v.shape[0], np.int64)
    no_pairs = np.bool_(False)  # a bool, not the literal False: the kernel compiles once
    for m in range(rots.shape[0]):
        out[m] = _counts_until(own_v, own_v, other_v, other_v, rots[m], transs[m], fx, fy, cx,
                               cy, 0.0, 1.0, noise, 0.0, through_sigmas, margin_m,
                               margin_per_m2, no_pairs, -np.inf, never)[2]
    return out


@numba.njit(cache=True, nogil=True)
def _pose_scores(cur_v, cur_n, ref_v, ref_n, rots, transs, fx, fy, cx, cy, max_dist, min_cos,
                 noise, sigmas, through_sigmas, margin_m, margin_per_m2, both_ways, hole_weight,
                 prune):
    """Scores of candidate poses ``T_ref_from_cur`` (``rots`` (n, 3, 3), ``transs`` (n, 3)
    metres): per pose, the current's inlier pairs (:func:`agreement_counts`; with ``both_ways``
    those of the reference's cells moved into the current view too) minus the cells of either
    view the other sees through, minus ``hole_weight`` times the cells of either view that
    land on no reading of the other inside its image.  A wrong slide along a room fits floor
    and walls (inliers) but puts surfaces where the other camera saw free space; a wrong turn
    on a table top puts the table where the other saw none.

    With ``prune`` (and not ``both_ways``), for a caller that wants the best pose alone: the
    reference's side only subtracts, so a pose whose current side, with every cell still to
    come counted as an inlier, already scores below the best so far is not counted further
    and scores -inf (the first best pose is the same).
    Returns (n,) float64."""
    out = np.empty(rots.shape[0])
    back = np.empty(3)
    best = -np.inf
    prune = prune and not both_ways
    pairs = np.bool_(True)  # a bool, not the literal True: the kernel compiles once
    pairable_after = np.zeros(cur_v.shape[0], np.int64)  # cells with a normal below row i
    for i in range(cur_v.shape[0] - 2, -1, -1):
        pairable_after[i] = pairable_after[i + 1]
        for j in range(cur_v.shape[1]):
            if cur_n[i + 1, j, 0] != 0.0 or cur_n[i + 1, j, 1] != 0.0 or cur_n[i + 1, j, 2] != 0.0:
                pairable_after[i] += 1
    for m in range(rots.shape[0]):
        rot = rots[m]
        t = transs[m]
        inliers_cur, _, through_cur, _, holes_cur, _, whole = _counts_until(
            cur_v, cur_n, ref_v, ref_n, rot, t, fx, fy, cx, cy, max_dist, min_cos, noise, sigmas,
            through_sigmas, margin_m, margin_per_m2, pairs, best if prune else -np.inf,
            pairable_after)
        if prune and (not whole or inliers_cur - through_cur - hole_weight * holes_cur < best):
            out[m] = -np.inf
            continue
        rot_t = np.ascontiguousarray(rot.T)
        for a in range(3):
            back[a] = -(rot_t[a, 0] * t[0] + rot_t[a, 1] * t[1] + rot_t[a, 2] * t[2])
        inliers_ref, _, through_ref, _, holes_ref, _ = agreement_counts(
            ref_v, ref_n, cur_v, cur_n, rot_t, back, fx, fy, cx, cy, max_dist, min_cos, noise,
            sigmas, through_sigmas, margin_m, margin_per_m2, both_ways)
        out[m] = (inliers_cur + inliers_ref - through_cur - through_ref
                  - hole_weight * (holes_cur + holes_ref))
        best = max(best, out[m])
    return out


def score_poses(rl: Level, cl: Level, poses: list[np.ndarray], params: RegistrationParams,
                min_cos: float, both_ways: bool = False, hole_weight: float = 0.0, *,
                prune: bool = False) -> np.ndarray:
    """(n,) :func:`_pose_scores` of the (4, 4) ``poses`` at one level: inliers within one
    search step (of the current's cells; ``both_ways``: of both views' cells), less the cells
    either view sees through and ``hole_weight`` times those landing on no reading
    (``prune``: -inf for poses that cannot be the best)."""
    rots = np.array([T[:3, :3] for T in poses])
    transs = np.array([T[:3, 3] for T in poses])
    return _pose_scores(cl.vertex, cl.normal, rl.vertex, rl.normal, rots, transs, rl.fx, rl.fy,
                        rl.cx, rl.cy, params.search_step_m, min_cos, *params.noise_args(),
                        bool(both_ways), float(hole_weight), bool(prune))


def best_pose(rl: Level, cl: Level, poses: list[np.ndarray], params: RegistrationParams,
              min_cos: float) -> int:
    """The index of the first best-scoring of ``poses`` (:func:`score_poses`, one way)."""
    return int(np.argmax(score_poses(rl, cl, poses, params, min_cos, prune=True)))


def better_end(rl: Level, cl: Level, T: np.ndarray, ends: list[np.ndarray],
               params: RegistrationParams, min_cos: float) -> int | None:
    """The index of the best of the (4, 4) ``ends`` on the score taken both ways
    (:func:`score_poses` with ``table_hole_weight``) when it scores higher than ``T`` by more
    than ``final_search_margin`` of the two views' cells with a normal; None otherwise."""
    scores = score_poses(rl, cl, [T] + ends, params, min_cos, True, params.table_hole_weight)
    best = int(np.argmax(scores[1:]))
    margin = params.final_search_margin * (rl.n_normals + cl.n_normals)
    return best if scores[1 + best] > scores[0] + margin else None


def slides_along(T: np.ndarray, A: np.ndarray, step_m: float, reach_m: float, n_dirs: int
                 ) -> list[np.ndarray]:
    """``T`` (4, 4) moved along the ``n_dirs`` least constrained directions of the translation
    block of the normal matrix ``A`` (6, 6), ``step_m`` apart out to ``reach_m`` each way (m)."""
    _lam, vecs = np.linalg.eigh(A[3:, 3:])
    k = int(math.floor(reach_m / step_m + 1e-9))
    poses = []
    for d in vecs[:, :n_dirs].T:
        poses += line_poses(T, d, step_m, -k, -1) + line_poses(T, d, step_m, 1, k)
    return poses


def line_poses(T: np.ndarray, direction: np.ndarray, step_m: float, lo: int, hi: int
               ) -> list[np.ndarray]:
    """``T`` (4, 4) moved by ``i * step_m`` along ``direction`` (3,), a unit translation in
    the reference frame, for i = lo ... hi, in that order."""
    poses = []
    for i in range(lo, hi + 1):
        pose = T.copy()
        pose[:3, 3] += i * step_m * direction
        poses.append(pose)
    return poses


def weak_search(rl: Level, cl: Level, T: np.ndarray, A: np.ndarray,
                params: RegistrationParams, min_cos: float) -> np.ndarray | None:
    """The best-scoring (:func:`score_poses`) of ``T`` moved along the least constrained
    directions of the normal matrix ``A`` (6, 6): translation offsets along the two weakest
    directions of its translation block, and screw motions along the two weakest directions
    of the whole, rotations scaled by the radius (root median squared depth) of the current
    level; None when ``T`` itself scores best."""
    poses = [T] + slides_along(T, A, params.search_step_m, params.search_reach_m, 2)
    if params.search_screw_steps:
        z = cl.vertex[:, :, 2]
        radius = math.sqrt(float(np.median(np.square(z[z > 0], dtype=np.float64))))
        s = np.array([radius, radius, radius, 1.0, 1.0, 1.0])
        _lam6, vecs6 = np.linalg.eigh(A / np.outer(s, s))
        screw = params.search_step_m * np.arange(1, params.search_screw_steps + 1)
        for d in (vecs6[:, 0] / s, vecs6[:, 1] / s):
            for st in np.concatenate([-screw[::-1], screw]):
                poses.append(rigid(exp_so3(st * d[:3]), st * d[3:]) @ T)
    best = best_pose(rl, cl, poses, params, min_cos)
    return None if best == 0 else poses[best]  # the first of equal scores: T wins ties


def fine_search(rl: Level, cl: Level, T: np.ndarray, A: np.ndarray,
                params: RegistrationParams, min_cos: float) -> np.ndarray | None:
    """The best-scoring (:func:`score_poses`) of ``T`` slid along the least constrained
    direction of the translation block of ``A`` (6, 6), ``fine_search_step_m`` apart out to
    ``fine_search_reach_m`` each way; None when ``T`` itself scores best, or when that
    direction is not a slide (its eigenvalue not below ``fine_search_ratio`` of the next
    one's).  What pins a slide may be a few centimetres wide (a table's legs, the sides of
    the objects on it): ICP's basin there is about that wide, narrower than the coarse
    search's step."""
    lam = np.linalg.eigvalsh(A[3:, 3:])
    if params.fine_search_reach_m <= 0 or not lam[0] < params.fine_search_ratio * lam[1]:
        return None
    poses = [T] + slides_along(T, A, params.fine_search_step_m, params.fine_search_reach_m, 1)
    best = best_pose(rl, cl, poses, params, min_cos)
    return None if best == 0 else poses[best]  # the first of equal scores: T wins ties


def slide_peaks(rl: Level, cl: Level, T: np.ndarray, A: np.ndarray,
                params: RegistrationParams, min_cos: float,
                start: np.ndarray | None = None) -> list[np.ndarray]:
    """Up to ``final_search_starts`` poses of ``T`` (4, 4) slid along the least constrained
    translation of ``A`` (6, 6), ``final_search_step_m`` apart out to ``final_search_reach_m``
    each way, and as far round where ``start`` (4, 4, the initial pose) stands along that
    line: the local peaks of the score taken both ways (:func:`score_poses`, with
    ``table_hole_weight``) at this level, best first, none of them ``T`` itself.  ICP does
    not move an estimate along a slide, and the searches before may have carried it farther
    from the initial pose than the robot can stand from it."""
    step, reach = params.final_search_step_m, params.final_search_reach_m
    d = np.linalg.eigh(A[3:, 3:])[1][:, 0]
    k = int(math.floor(reach / step + 1e-9))
    lo, hi = -k, k
    if start is not None:
        s0 = int(round(float(d @ (start[:3, 3] - T[:3, 3])) / step))
        lo, hi = min(lo, s0 - k), max(hi, s0 + k)
    poses = line_poses(T, d, step, lo, hi)  # in order along the line, T at -lo
    line = score_poses(rl, cl, poses, params, min_cos, True, params.table_hole_weight)
    peaks = [i for i in range(len(line)) if i != -lo
             and (i == 0 or line[i] >= line[i - 1])
             and (i == len(line) - 1 or line[i] >= line[i + 1])]
    peaks.sort(key=lambda i: -line[i])
    return [poses[i] for i in peaks[:params.final_search_starts]]


def slide_support(rl: Level, cl: Level, T: np.ndarray, direction: np.ndarray,
                  params: RegistrationParams, min_cos: float) -> tuple[int, int]:
    """The cells of both views (one level: reference ``rl``, current ``cl``) whose normal lies
    within 60 degrees of ``direction`` (3,), a translation in the reference camera frame, that
    fit the other view at ``T`` (T_ref_from_cur) and that contradict it
    (:func:`cell_states`): the surfaces that pin the estimate along that direction, and
    those that argue against it.  A wall's or a table's normals are nearly square to a slide
    along them, and their many cells can give the normal equations a little information
    along it; the surfaces facing along it are what decides it.  Returns (fit, contradict)."""
    fit = contradict = 0
    direction = np.ascontiguousarray(direction)  # as every caller's: one compile
    for own, other, M, d in ((cl, rl, T, T[:3, :3].T @ direction),
                             (rl, cl, invert(T), direction)):
        states = cell_states(*own.onto(other, M), params.max_distance_m[-1], min_cos,
                             *params.noise_args(), d, 0.5)
        fit += int(np.count_nonzero(states == 1))
        contradict += int(np.count_nonzero(states == 2))
    return fit, contradict


def fitness_pairing(cl: Level, params: RegistrationParams, min_cos: float
                    ) -> tuple[float, float]:
    """How far apart (m) and how far turned (the cosine) two cells may be to pair when the
    fitness is counted: the finest level's ``max_distance_m`` and ``min_cos``, or, where the
    camera's noise at the view's median depth makes two cells' means differ more or their
    normals scatter more (``inlier_sigmas`` sigmas of the difference of two cells' means, and
    of their normals' angle: each cell a mean of ``factor^2`` readings, its normal taken across
    two cells), that.  With a Kinect at 1-3 m these are the level's own (at 4 m normals 40
    degrees apart pair); with the paper's 100 mm noise no normal is trusted and means 11 cm
    apart still pair."""
    z = cl.vertex[:, :, 2]
    z = z[z > 0]
    if not z.size:
        return params.max_distance_m[-1], min_cos
    depth = float(np.median(z))
    cell = float(params.noise.sigma(depth)) / cl.factor  # a cell's mean of factor^2 readings
    spread = params.inlier_sigmas * math.sqrt(2.0) * cell
    across = 2.0 * depth / cl.fx  # a normal is taken across two cells (m)
    turned = params.inlier_sigmas * math.sqrt(2.0) * math.atan(math.sqrt(2.0) * cell / across)
    return max(params.max_distance_m[-1], spread), min(min_cos, math.cos(min(turned, math.pi)))


def final_agreement(rl: Level, cl: Level, T: np.ndarray, params: RegistrationParams,
                    min_cos: float) -> tuple[float, float, int, int, float, float]:
    """What the finest levels (``rl``, ``cl``) say of the estimate ``T`` (4, 4): (fitness, the
    share of the current's cells with a normal that have an inlier pair (within
    ``max_distance_m`` of the level and ``inlier_sigmas`` noise sigmas); the inliers' rmse, m;
    the inliers; the current's cells with a normal; the larger of the fractions of each view
    that the other sees through; the fraction of the current's cells that lie behind a nearer
    reading of the reference)."""
    n_cells = cl.n_normals
    max_dist, min_cos = fitness_pairing(cl, params, min_cos)

    k, sq_sum, through, compared, _, behind = agreement_counts(
        *cl.onto(rl, T), max_dist, min_cos, *params.noise_args(), True)
    _, _, back, back_compared, _, _ = agreement_counts(  # the reference's cells
        *rl.onto(cl, invert(T)), max_dist, min_cos, *params.noise_args(), False)
    cells = int(np.count_nonzero(cl.vertex[:, :, 2] > 0))
    return (k / n_cells if n_cells else 0.0, math.sqrt(sq_sum / k) if k else 0.0, k, n_cells,
            max(through / compared if compared else 0.0,
                back / back_compared if back_compared else 0.0),
            behind / cells if cells else 0.0)
