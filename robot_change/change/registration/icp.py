"""Projective point-to-plane ICP of one pyramid level: association on the depth grid, the
robustly weighted normal equations, the Gauss-Newton step that does not move along weak
directions, and the iterations with a trust region (docs/algorithm.md, "Registration", steps
3-5 and 7).  Kernels are ``@njit(cache=True, nogil=True)`` with NumPy twins in
``tests/test_registration.py``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from robot_change.noise.kernels import sigma_at

from .params import RegistrationParams
from .pyramid import Level
from .result import AXES
from .rigid import exp_so3


@numba.njit(inline="always")
def land(x, y, z, rot, trans, fx, fy, cx, cy, h, w):
    """The point (``x``, ``y``, ``z``) m moved by (``rot`` (3, 3), ``trans`` (3,)) and the
    cell of an (``h``, ``w``) level (intrinsics fx, fy, cx, cy) it lands on: (px, py, pz, u,
    v); u = v = -1 when it lands behind the camera or outside the level.  Inlined into the
    kernels that walk the cells (a called helper returning a tuple made them five times
    slower)."""
    px = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
    py = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
    pz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
    if pz <= 0.0:
        return px, py, pz, -1, -1
    u = int(math.floor(fx * px / pz + cx + 0.5))
    v = int(math.floor(fy * py / pz + cy + 0.5))
    if u < 0 or v < 0 or u >= w or v >= h:
        return px, py, pz, -1, -1
    return px, py, pz, u, v


@numba.njit(inline="always")
def pair(own_normal, other_v, other_n, v, u, px, py, pz, rot, max_dist2, min_cos):
    """Whether a cell moved to (``px``, ``py``, ``pz``) m, of normal ``own_normal`` (3,) before
    the move by ``rot``, pairs with the other level's cell (``v``, ``u``) it lands on: both
    have a normal, the points are within sqrt(``max_dist2``) m and the normals' cosine is at
    least ``min_cos``.  Returns (paired, residual n . (p - q) m, the other's normal n)."""
    nx0 = own_normal[0]
    ny0 = own_normal[1]
    nz0 = own_normal[2]
    mx = other_n[v, u, 0]
    my = other_n[v, u, 1]
    mz = other_n[v, u, 2]
    if (nx0 == 0.0 and ny0 == 0.0 and nz0 == 0.0) or (mx == 0.0 and my == 0.0 and mz == 0.0):
        return False, 0.0, mx, my, mz
    dx = px - other_v[v, u, 0]
    dy = py - other_v[v, u, 1]
    dz = pz - other_v[v, u, 2]
    if dx * dx + dy * dy + dz * dz > max_dist2:
        return False, 0.0, mx, my, mz
    nx = rot[0, 0] * nx0 + rot[0, 1] * ny0 + rot[0, 2] * nz0
    ny = rot[1, 0] * nx0 + rot[1, 1] * ny0 + rot[1, 2] * nz0
    nz = rot[2, 0] * nx0 + rot[2, 1] * ny0 + rot[2, 2] * nz0
    if nx * mx + ny * my + nz * mz < min_cos:
        return False, 0.0, mx, my, mz
    return True, mx * dx + my * dy + mz * dz, mx, my, mz


@numba.njit(cache=True, nogil=True)
def _associate(cur_v, cur_n, ref_v, ref_n, rot, trans, fx, fy, cx, cy, max_dist, min_cos,
               res, jac, zs):
    """Projective data association and point-to-plane residuals of one ICP step.

    Each current cell with a normal (``cur_v``, ``cur_n`` (h, w, 3)) is moved by (``rot``
    (3, 3), ``trans`` (3,)), projected with the level's intrinsics into the reference level
    (:func:`land`) and paired with the cell it lands on (:func:`pair`).  Fills, per pair k,
    ``res[k]`` = n_ref . (p - q) (metres), ``jac[k]`` = (p x n_ref, n_ref) (derivative of the
    residual under a left perturbation (rotation vector, translation)) and ``zs[k]`` the depth
    of p in the reference frame.  Returns the number of pairs.
    """
    k = 0
    md2 = max_dist * max_dist
    h = ref_v.shape[0]
    w = ref_v.shape[1]
    for i in range(cur_v.shape[0]):
        for j in range(cur_v.shape[1]):
            normal = cur_n[i, j]
            if normal[0] == 0.0 and normal[1] == 0.0 and normal[2] == 0.0:
                continue
            px, py, pz, u, v = land(cur_v[i, j, 0], cur_v[i, j, 1], cur_v[i, j, 2], rot, trans,
                                    fx, fy, cx, cy, h, w)
            if u < 0:
                continue
            paired, r, mx, my, mz = pair(normal, ref_v, ref_n, v, u, px, py, pz, rot, md2,
                                         min_cos)
            if not paired:
                continue
            res[k] = r
            jac[k, 0] = py * mz - pz * my
            jac[k, 1] = pz * mx - px * mz
            jac[k, 2] = px * my - py * mx
            jac[k, 3] = mx
            jac[k, 4] = my
            jac[k, 5] = mz
            zs[k] = pz
            k += 1
    return k


@numba.njit(cache=True, nogil=True)
def _weighted_system(res, jac, zs, n, tukey_c, min_cut_m, noise):
    """The robustly weighted 6x6 normal equations of the first ``n`` pairs (``res`` (N,) m,
    ``jac`` (N, 6), ``zs`` (N,) m, from :func:`_associate`).

    Weight of a pair: 1 / sigma(z)^2 (the sigma table ``noise``,
    robot_change.noise.kernels.sigma_at) times Tukey's biweight of its
    normalised residual e = res / sigma(z), with constant ``tukey_c`` times the scale
    max(1.4826 median |e|, 0.5), and no narrower than ``min_cut_m`` metres.  Returns (A (6, 6)
    = J^T W J, b (6,) = J^T W r, the sum of the weights, radius: the root of the median squared
    depth, m)."""
    e = np.empty(n)
    inv_var = np.empty(n)
    z2 = np.empty(n)
    for k in range(n):
        sig = sigma_at(noise, zs[k])
        e[k] = abs(res[k]) / sig
        inv_var[k] = 1.0 / (sig * sig)
        z2[k] = zs[k] * zs[k]
    scale = max(1.4826 * np.median(e), 0.5)
    radius = math.sqrt(np.median(z2))
    cut = tukey_c * scale
    A = np.zeros((6, 6))
    b = np.zeros(6)
    wsum = 0.0
    for k in range(n):
        u = e[k] / (max(cut, min_cut_m * math.sqrt(inv_var[k])) if min_cut_m > 0.0 else cut)
        if u >= 1.0:
            continue
        wt = (1.0 - u * u) ** 2 * inv_var[k]
        wsum += wt
        for a in range(6):
            ja = jac[k, a] * wt
            b[a] += ja * res[k]
            for c in range(a, 6):
                A[a, c] += ja * jac[k, c]
    for a in range(6):
        for c in range(a):
            A[a, c] = A[c, a]
    return A, b, wsum, radius


@numba.njit(cache=True, nogil=True)
def _gauss_newton_step(A, b, radius, wsum, weak_eigenvalue):
    """Gauss-Newton step of the 6x6 system ``A`` step = -``b``, not moving along weak
    directions.

    Rotations are scaled by ``radius`` (m) so all six are metres; eigenvalues per unit weight
    (``wsum``) below ``weak_eigenvalue`` are weak.  Returns (step (6,) rotation vector then
    translation, eigenvalues (6,) ascending per unit weight, eigenvectors (6, 6) as columns,
    scaled)."""
    s = np.array([radius, radius, radius, 1.0, 1.0, 1.0])
    As = np.empty((6, 6))
    bs = np.empty(6)
    for a in range(6):
        bs[a] = b[a] / s[a]
        for c in range(6):
            As[a, c] = A[a, c] / (s[a] * s[c])
    lam, vec = np.linalg.eigh(As)
    lam_n = lam / max(wsum, 1e-300)
    step = np.zeros(6)
    for i in range(6):
        if lam_n[i] >= weak_eigenvalue:
            proj = 0.0
            for a in range(6):
                proj += vec[a, i] * bs[a]
            for a in range(6):
                step[a] -= proj / lam[i] * vec[a, i]
    for a in range(6):
        step[a] /= s[a]
    return step, lam_n, vec


@numba.njit(cache=True, nogil=True)
def _icp_iterations(cur_v, cur_n, ref_v, ref_n, T, fx, fy, cx, cy, max_dist, min_cos, tukey_c,
                    min_cut_m, weak_eigenvalue, iterations, tol_m, res, jac, zs, noise):
    """Gauss-Newton iterations of one level from ``T`` (4, 4) (T_ref_from_cur): per
    iteration :func:`_associate`, :func:`_weighted_system` and :func:`_gauss_newton_step`, a
    trust region (no step moves a point by more than half of ``max_dist``: a first step from
    many wrong pairs must not throw the estimate out of the basin), the step applied on the
    left; at most ``iterations``, ending early when fewer than 6 pairs are left or a step
    moves a point by less than ``tol_m``.  ``res``, ``jac``, ``zs``: scratch arrays of
    :func:`_associate`; ``noise`` the sigma table.  Returns (T, iterations done, converged,
    eigenvalues (6,) per unit
    weight, eigenvectors (6, 6), the last normal matrix (6, 6), whether there was one)."""
    T = T.copy()
    lam_n = np.zeros(6)
    vec = np.eye(6)
    A = np.zeros((6, 6))
    has_system = False
    n_it = 0
    cap = 0.5 * max_dist
    rot = np.empty((3, 3))
    trans = np.empty(3)
    inc = np.eye(4)
    for _ in range(iterations):
        for a in range(3):  # element by element: a slice copy compiles numba's shape error
            for b in range(3):
                rot[a, b] = T[a, b]
            trans[a] = T[a, 3]
        n = _associate(cur_v, cur_n, ref_v, ref_n, rot, trans, fx, fy, cx, cy, max_dist,
                       min_cos, res, jac, zs)
        if n < 6:
            break
        A, b, wsum, radius = _weighted_system(res, jac, zs, n, tukey_c, min_cut_m, noise)
        has_system = True
        step, lam_n, vec = _gauss_newton_step(A, b, radius, wsum, weak_eigenvalue)
        length = math.sqrt((step[0] ** 2 + step[1] ** 2 + step[2] ** 2) * radius * radius
                           + (step[3] ** 2 + step[4] ** 2 + step[5] ** 2))
        if length > cap:
            step = step * (cap / length)
            length = cap
        n_it += 1
        turn = exp_so3(step[:3])
        for a in range(3):
            for b in range(3):
                inc[a, b] = turn[a, b]
            inc[a, 3] = step[3 + a]
        T = inc @ T
        if length < tol_m:
            return T, n_it, True, lam_n, vec, A, has_system
    return T, n_it, False, lam_n, vec, A, has_system


def weak_names(lam_n: np.ndarray, vec: np.ndarray, weak_eigenvalue: float) -> tuple[str, ...]:
    """The :data:`AXES` names nearest to the eigenvectors (``vec`` (6, 6), columns) whose
    eigenvalues per unit weight (``lam_n`` (6,)) are below ``weak_eigenvalue``."""
    return tuple(dict.fromkeys(AXES[int(np.argmax(np.abs(vec[:, i])))] for i in range(6)
                               if lam_n[i] < weak_eigenvalue))


class Pairs:
    """Scratch arrays for the pairs of one level (one row per current cell)."""

    def __init__(self, level: Level) -> None:
        size = level.vertex.shape[0] * level.vertex.shape[1]
        self.res = np.empty(size)
        self.jac = np.empty((size, 6))
        self.zs = np.empty(size)


def icp_level(rl: Level, cl: Level, T: np.ndarray, params: RegistrationParams, li: int,
              min_cos: float, pairs: Pairs, min_cut_m: float = 0.0):
    """:func:`_icp_iterations` of level ``li`` from ``T`` (Tukey's cut at least ``min_cut_m``
    metres); returns (T, iterations, converged, eigenvalues, eigenvectors, last normal matrix
    or None)."""
    T, n_it, converged, lam_n, vec, A, has_system = _icp_iterations(
        cl.vertex, cl.normal, rl.vertex, rl.normal, np.ascontiguousarray(T, dtype=np.float64),
        rl.fx, rl.fy, rl.cx, rl.cy, params.max_distance_m[li], min_cos, params.tukey_c,
        min_cut_m, params.weak_eigenvalue, params.iterations[li], params.tol_m, pairs.res,
        pairs.jac, pairs.zs, params.noise_args()[0])
    return T, n_it, converged, lam_n, vec, (A if has_system else None)


def best_of(ends: list[tuple], best: int) -> tuple:
    """:func:`icp_level`'s tuple of ``ends[best]`` with the iterations of every end."""
    return (ends[best][0], sum(e[1] for e in ends), *ends[best][2:])
