"""robot_change.change.transport: exact EMD, ground distances, greedy EMD, and their NumPy/SciPy
twins.

References: scipy.optimize.linprog (HiGHS) for every EMD value, POT's ``ot.emd2`` when
installed, ``scipy.linalg.sqrtm`` for the 2-Wasserstein ground distance, and plain NumPy
linear algebra for the tree kernel.
"""

from __future__ import annotations

import math
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.linalg import sqrtm
from scipy.optimize import linprog
from scipy.spatial.distance import cdist

from robot_change.change import transport_greedy as G
from robot_change.change import transport_simplex as S
from robot_change.change import transport_tree as T
from robot_change.change.transport import (
    STOP_REASONS,
    EmdResult,
    GreedyResult,
    emd,
    greedy_emd,
    ground_distance,
    mixture_emd,
)
from robot_change.errors import InputError
from robot_change.mixture.model import Mixture

TOL = 1e-9


# --------------------------------------------------------------------------- twins


def lp_emd(a, b, cost):
    """EMD by scipy.optimize.linprog (HiGHS): (value, flow (Ka, Kb))."""
    a = np.asarray(a, float) / np.sum(a)
    b = np.asarray(b, float) / np.sum(b)
    cost = np.asarray(cost, float)
    m, n = cost.shape
    a_eq = np.zeros((m + n, m * n))
    for i in range(m):
        a_eq[i, i * n:(i + 1) * n] = 1.0
    for j in range(n):
        a_eq[m + j, j::n] = 1.0
    # HiGHS' default feasibility tolerances (1e-7) let the marginals drift by ~1e-7, and the
    # optimum by a few 1e-9 on 100 x 100 problems: tightened to 1e-10
    res = linprog(cost.ravel(), A_eq=a_eq, b_eq=np.concatenate([a, b]), bounds=(0, None),
                  method="highs", options=dict(primal_feasibility_tolerance=1e-10,
                                               dual_feasibility_tolerance=1e-10))
    assert res.status == 0, res.message
    return float(res.fun), res.x.reshape(m, n)


def greedy_twin(a, b, cost, candidates, max_removals):
    """Plain loop of greedy EMD with linprog.

    Returns (order, emd_after, stop_reason, gaps): ``gaps`` are, per round, the margin between
    the best and the second-best candidate and between the best and the current EMD (how
    unambiguous the round was).
    """
    a = np.asarray(a, float) / np.sum(a)
    b = np.asarray(b, float) / np.sum(b)
    n = len(b)
    tol = 1e-12 * np.abs(cost).max()
    removed = np.zeros(n, bool)
    current = lp_emd(a, b, cost)[0]
    order, after, gaps = [], [current], []
    stop = STOP_REASONS[3]
    while len(order) < max_removals:
        ks = [k for k in range(n) if candidates[k] and not removed[k]]
        if not ks:
            stop = STOP_REASONS[1]
            break
        values = {}
        for k in ks:
            bb = np.where(removed, 0.0, b)
            bb[k] = 0.0
            if bb.sum() <= 0:
                continue
            values[k] = lp_emd(a, bb, cost)[0]
        if not values:
            stop = STOP_REASONS[2]
            break
        ranked = sorted(values.values())
        best_k = min(values, key=lambda k: (values[k], k))
        gaps.append(min(ranked[1] - ranked[0] if len(ranked) > 1 else np.inf,
                        abs(current - ranked[0])))
        if not values[best_k] < current - tol:
            stop = STOP_REASONS[0]
            break
        removed[best_k] = True
        order.append(best_k)
        current = values[best_k]
        after.append(current)
    return np.array(order, dtype=np.int64), np.array(after), stop, gaps


def tree_twin(m, n, bi, bj, a, b, cost):
    """Flows and potentials of a spanning-tree basis by dense linear algebra.

    Flows: the m + n balance equations restricted to the basic cells (least squares: one is
    redundant).  Potentials: ``u_i + v_j = cost_ij`` on the basic cells with ``u_0 = 0``.
    """
    ne = m + n - 1
    bal = np.zeros((m + n, ne))
    pot_eq = np.zeros((ne + 1, m + n))
    rhs = np.zeros(ne + 1)
    for e in range(ne):
        bal[bi[e], e] = 1.0
        bal[m + bj[e], e] = 1.0
        pot_eq[e, bi[e]] = 1.0
        pot_eq[e, m + bj[e]] = 1.0
        rhs[e] = cost[bi[e], bj[e]]
    pot_eq[ne, 0] = 1.0
    x = np.linalg.lstsq(bal, np.concatenate([a, b]), rcond=None)[0]
    pot = np.linalg.solve(pot_eq, rhs)
    return x, pot


def w2_twin(mu_a, mu_b, cov_a, cov_b):
    """2-Wasserstein between Gaussians, pair by pair, with scipy.linalg.sqrtm."""
    out = np.zeros((len(mu_a), len(mu_b)))
    for i in range(len(mu_a)):
        ra = np.real(sqrtm(cov_a[i]))
        for j in range(len(mu_b)):
            cross = np.real(sqrtm(ra @ cov_b[j] @ ra))
            bures = np.trace(cov_a[i]) + np.trace(cov_b[j]) - 2.0 * np.trace(cross)
            out[i, j] = math.sqrt(max(np.sum((mu_a[i] - mu_b[j]) ** 2) + bures, 0.0))
    return out


# --------------------------------------------------------------------------- problems


def random_problem(rng, kind=None, m=None, n=None):
    """A random transportation problem of one of several kinds (ties, zeros, integers...)."""
    m = int(rng.integers(1, 16)) if m is None else m
    n = int(rng.integers(1, 16)) if n is None else n
    kind = kind or rng.choice(["float", "int_cost", "int_all", "zeros", "points"])
    a = rng.random(m)
    b = rng.random(n)
    if kind == "points":
        cost = cdist(rng.random((m, 3)), rng.random((n, 3)))
    elif kind in ("int_cost", "int_all"):
        cost = rng.integers(0, 4, (m, n)).astype(float)
    else:
        cost = rng.random((m, n))
    if kind == "int_all":  # many optimal plans and degenerate bases
        a = rng.integers(0, 4, m).astype(float)
        b = rng.integers(0, 4, n).astype(float)
    if kind == "zeros":
        a[rng.random(m) < 0.4] = 0.0
        b[rng.random(n) < 0.4] = 0.0
    if a.sum() == 0:
        a[-1] = 1.0
    if b.sum() == 0:
        b[0] = 1.0
    return a, b, cost


def check_flow(res: EmdResult, a, b, cost):
    a = np.asarray(a, float) / np.sum(a)
    b = np.asarray(b, float) / np.sum(b)
    assert res.flow.shape == (len(a), len(b))
    assert (res.flow >= 0).all()
    np.testing.assert_allclose(res.flow.sum(axis=1), a, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.flow.sum(axis=0), b, rtol=0, atol=1e-12)
    assert abs(np.sum(res.flow * cost) - res.distance) <= 1e-12


def separated_greedy_problem(rng, m, n, n_novel):
    """Fixed side of m random points; var side: n - n_novel of them jittered, n_novel far away.

    Distinct random weights keep the greedy rounds apart (checked by the caller via the gaps).
    """
    pts = rng.random((m, 3)) * 3.0
    keep = rng.choice(m, n - n_novel, replace=n - n_novel > m)
    var = np.vstack([pts[keep] + 0.05 * rng.standard_normal((n - n_novel, 3)),
                     rng.random((n_novel, 3)) * 3.0 + np.array([0.0, 0.0, 4.0])])
    perm = rng.permutation(n)
    var = var[perm]
    a = rng.random(m) + 0.2
    b = rng.random(n) + 0.2
    return a, b, cdist(pts, var)


# --------------------------------------------------------------------------- emd


@pytest.mark.parametrize("seed", range(4))
def test_emd_matches_linprog_on_random_problems(seed):
    rng = np.random.default_rng(seed)
    for _ in range(60):
        a, b, cost = random_problem(rng)
        res = emd(a, b, cost)
        ref, _ = lp_emd(a, b, cost)
        assert abs(res.distance - ref) <= TOL, (a, b, cost)
        check_flow(res, a, b, cost)


@pytest.mark.parametrize("kind", ["float", "int_cost", "int_all", "zeros", "points"])
@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (7, 1), (3, 12), (12, 3), (30, 30)])
def test_emd_matches_linprog_by_kind_and_shape(kind, shape):
    rng = np.random.default_rng(zlib.crc32(repr((kind, shape)).encode()))
    for _ in range(3):
        a, b, cost = random_problem(rng, kind, *shape)
        res = emd(a, b, cost)
        assert abs(res.distance - lp_emd(a, b, cost)[0]) <= TOL
        check_flow(res, a, b, cost)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_emd_matches_linprog_hypothesis(data):
    m = data.draw(st.integers(1, 8), "m")
    n = data.draw(st.integers(1, 8), "n")
    weight = st.one_of(st.just(0.0), st.integers(1, 4).map(float),
                       st.floats(1e-3, 1.0, allow_nan=False))
    a = np.array(data.draw(st.lists(weight, min_size=m, max_size=m), "a"))
    b = np.array(data.draw(st.lists(weight, min_size=n, max_size=n), "b"))
    if a.sum() == 0:
        a[0] = 1.0
    if b.sum() == 0:
        b[-1] = 1.0
    value = st.one_of(st.integers(0, 3).map(float), st.floats(0.0, 10.0, allow_nan=False))
    cost = np.array(data.draw(st.lists(value, min_size=m * n, max_size=m * n), "cost"))
    cost = cost.reshape(m, n)
    res = emd(a, b, cost)
    assert abs(res.distance - lp_emd(a, b, cost)[0]) <= TOL
    check_flow(res, a, b, cost)


@pytest.mark.parametrize("shape", [(1, 100), (100, 1), (16, 40), (40, 16), (70, 50),
                                   (100, 100)])
@pytest.mark.parametrize("kind", ["float", "int_all", "zeros", "points"])
def test_emd_large_problems_match_linprog(kind, shape):
    rng = np.random.default_rng(zlib.crc32(repr((kind, shape, "large")).encode()))
    a, b, cost = random_problem(rng, kind, *shape)
    res = emd(a, b, cost)
    assert abs(res.distance - lp_emd(a, b, cost)[0]) <= TOL
    check_flow(res, a, b, cost)


def test_emd_matches_pot_from_1x1_to_100x100():
    ot = pytest.importorskip("ot", reason="POT (the `pot` test extra) not installed")
    rng = np.random.default_rng(70)
    for trial in range(60):
        m, n = (int(k) for k in rng.integers(1, 101, 2))
        kind = ["float", "int_cost", "int_all", "zeros", "points"][trial % 5]
        a, b, cost = random_problem(rng, kind, m, n)
        a, b = a / a.sum(), b / b.sum()
        res = emd(a, b, cost)
        assert abs(res.distance - ot.emd2(a, b, cost, numItermax=10_000_000)) <= TOL
        check_flow(res, a, b, cost)


def test_bland_rule_path_matches_linprog():
    """Bland's rule from the first pivot (the anti-cycling fallback) is exact too."""
    rng = np.random.default_rng(11)
    for _ in range(40):
        a, b, cost = random_problem(rng, rng.choice(["int_all", "int_cost", "zeros"]))
        a, b = a / a.sum(), b / b.sum()
        dist, flow, status, _ = S._emd_kernel(a, b, cost, S._REL_TOL_COST, 0)
        assert status == 0
        assert abs(dist - lp_emd(a, b, cost)[0]) <= TOL
        np.testing.assert_allclose(flow.sum(axis=1), a, atol=1e-12)


def test_emd_normalises_weights():
    rng = np.random.default_rng(3)
    a, b, cost = random_problem(rng, "float", 5, 7)
    d1 = emd(a, b, cost).distance
    d2 = emd(3.0 * a, 0.01 * b, cost).distance
    assert abs(d1 - d2) <= 1e-12
    assert abs(emd(a, b, cost).flow.sum() - 1.0) <= 1e-12


def test_emd_zero_for_identical_distributions():
    rng = np.random.default_rng(4)
    pts = rng.random((9, 3))
    w = rng.random(9)
    w[2] = 0.0
    assert emd(w, w, cdist(pts, pts)).distance == 0.0


def test_emd_symmetric_for_transposed_cost():
    rng = np.random.default_rng(5)
    for _ in range(20):
        a, b, cost = random_problem(rng)
        assert abs(emd(a, b, cost).distance - emd(b, a, cost.T).distance) <= 1e-12


@pytest.mark.parametrize("scale", [1e-3, 2.5, 1e4])
def test_emd_scales_with_cost(scale):
    rng = np.random.default_rng(6)
    a, b, cost = random_problem(rng, "float", 8, 11)
    d = emd(a, b, cost).distance
    assert abs(emd(a, b, scale * cost).distance - scale * d) <= 1e-12 * scale


def test_single_components_give_distance_of_means():
    rng = np.random.default_rng(8)
    for _ in range(5):
        p, q = rng.random(3), rng.random(3)
        d = emd([0.3], [7.0], ground_distance(p[None], q[None])).distance
        assert abs(d - np.linalg.norm(p - q)) <= 1e-15


def test_one_row_sends_all_mass_to_every_column():
    b = np.array([0.2, 0.0, 0.5, 0.3])
    cost = np.array([[1.0, 9.0, 2.0, 3.0]])
    res = emd([1.0], b, cost)
    assert res.distance == pytest.approx(0.2 + 1.0 + 0.9, abs=1e-15)
    np.testing.assert_allclose(res.flow, b[None], atol=1e-15)


def test_emd_point_masses_triangle_inequality():
    rng = np.random.default_rng(9)
    pts = [rng.random((k, 3)) for k in (4, 6, 5)]
    ws = [rng.random(len(p)) for p in pts]
    d = {(i, j): emd(ws[i], ws[j], cdist(pts[i], pts[j])).distance
         for i in range(3) for j in range(3)}
    assert d[0, 2] <= d[0, 1] + d[1, 2] + 1e-12


def test_emd_result_is_frozen():
    res = emd([1.0], [1.0], [[2.0]])
    assert res == EmdResult(2.0, res.flow)
    with pytest.raises(AttributeError):
        res.distance = 3.0


@pytest.mark.parametrize("a, b, cost, match", [
    ([], [1.0], np.zeros((0, 1)), "weights_a"),
    ([1.0], [], np.zeros((1, 0)), "weights_b"),
    ([[1.0]], [1.0], [[1.0]], "shape"),
    ([np.nan, 1.0], [1.0], [[1.0], [1.0]], "NaN"),
    ([np.inf, 1.0], [1.0], [[1.0], [1.0]], "NaN or inf"),
    ([-0.1, 1.0], [1.0], [[1.0], [1.0]], ">= 0"),
    ([0.0, 0.0], [1.0], [[1.0], [1.0]], "all zero"),
    ([1.0], [0.0], [[1.0]], "all zero"),
    pytest.param([1e308, 1e308], [1.0], [[1.0], [1.0]], "overflow",
                 marks=pytest.mark.filterwarnings("ignore:overflow:RuntimeWarning")),
    ([1.0, 1.0], [1.0], [[1.0]], "shape"),
    ([1.0], [1.0, 1.0], [[1.0], [1.0]], "shape"),
    ([1.0], [1.0], [[np.nan]], "NaN"),
    ([1.0], [1.0], [[np.inf]], "NaN"),
    ([1.0], [1.0], "cost", "numeric"),
    (["x"], [1.0], [[1.0]], "numeric"),
])
def test_emd_bad_input(a, b, cost, match):
    with pytest.raises(InputError, match=match):
        emd(a, b, cost)


def test_emd_strided_list_and_scalar_inputs():
    rng = np.random.default_rng(10)
    a, b, cost = random_problem(rng, "points", 12, 14)
    ref = emd(a[::2].copy(), b[::2].copy(), cost[::2, ::2].copy())
    got = emd(a[::2], b[::2], cost[::2, ::2])          # non-contiguous views
    assert got.distance == ref.distance
    np.testing.assert_array_equal(got.flow, ref.flow)
    lists = emd(a[::2].tolist(), b[::2].tolist(), cost[::2, ::2].tolist())
    assert lists.distance == ref.distance
    with pytest.raises(InputError, match="weights_a must have shape"):
        emd(1.0, [1.0], [[1.0]])
    with pytest.raises(InputError, match="cost must have shape"):
        emd([1.0], [1.0], 1.0)


@pytest.mark.parametrize("w", [
    [0.2, 0.0, 3.0], [1e-300, 1e-300], [5.0], [0.0, np.nan], [np.inf, 1.0], [-1e-9, 1.0],
    [0.0, 0.0], [1e308, 1e308], [1e308, 1e307],
])
def test_normalised_matches_numpy(w):
    w = np.array(w)
    with np.errstate(over="ignore", invalid="ignore"):
        total = w.sum()
        valid = bool(np.isfinite(w).all() and (w >= 0).all() and 0 < total < np.inf)
    got = S._normalised(w)
    if valid:
        np.testing.assert_allclose(got, w / total, rtol=1e-15, atol=0)
    else:
        assert got.shape == (0,)


def test_checked_kernel_flags_exactly_what_the_python_checks_reject():
    """Status _BAD_INPUT iff _check_weights / _check_cost raise; else the same EMD."""
    rng = np.random.default_rng(18)
    for _ in range(200):
        a, b, cost = random_problem(rng, "float", int(rng.integers(1, 6)), int(rng.integers(1, 6)))
        for arr in (a, b, cost.ravel()):
            if rng.random() < 0.3:
                arr[rng.integers(arr.size)] = rng.choice([np.nan, np.inf, -np.inf, -0.5, 0.0])
        try:
            S._check_weights(a, "a")
            S._check_weights(b, "b")
            S._check_cost(cost, len(a), len(b))
            valid = True
        except InputError:
            valid = False
        dist, _, status, _ = S._checked_emd_kernel(a, b, cost, S._REL_TOL_COST)
        assert (status == S._BAD_INPUT) == (not valid)
        if valid:
            assert status == 0
            assert abs(dist - lp_emd(a, b, cost)[0]) <= TOL


# --------------------------------------------------------------------------- kernels


def test_least_cost_start_is_a_feasible_spanning_tree():
    rng = np.random.default_rng(12)
    for _ in range(200):
        a, b, cost = random_problem(rng)
        a, b = a / a.sum(), b / b.sum()
        m, n = cost.shape
        ws = S._workspace(m, n)
        bi = np.zeros(m + n - 1, np.int64)
        bj = np.zeros(m + n - 1, np.int64)
        T._least_cost_start(m, n, a, b, cost, bi, bj, ws[5], ws[6], ws[7], ws[8],
                            ws[0][0], ws[2])
        assert len(set(zip(bi.tolist(), bj.tolist(), strict=True))) == m + n - 1
        x, _ = tree_twin(m, n, bi, bj, a, b, cost)  # full rank: lstsq solves it exactly
        bal = np.zeros((m, n))
        np.add.at(bal, (bi, bj), x)
        np.testing.assert_allclose(bal.sum(axis=1), a, atol=1e-12)
        np.testing.assert_allclose(bal.sum(axis=0), b, atol=1e-12)
        assert (x >= -1e-12).all()
        # the very first cell is a cheapest one
        assert cost[bi[0], bj[0]] == cost.min()


def tree_arrays_twin(m, n, bi, bj):
    """Parent, edge to the parent and subtree size of every node of the basis, rooted at row 0
    (breadth-first in plain Python); None when the cells are not a spanning tree."""
    nn = m + n
    adj = [[] for _ in range(nn)]
    for e, (i, j) in enumerate(zip(bi.tolist(), bj.tolist(), strict=True)):
        adj[i].append((m + j, e))
        adj[m + j].append((i, e))
    parent = np.full(nn, -2)
    pred = np.full(nn, -1)
    parent[0] = -1
    queue = [0]
    for z in queue:
        for w, e in adj[z]:
            if parent[w] == -2:
                parent[w], pred[w] = z, e
                queue.append(w)
    if len(queue) != nn:
        return None
    size = np.ones(nn, np.int64)
    for z in reversed(queue[1:]):
        size[parent[z]] += size[z]
    return parent, pred, size


def check_tree_arrays(m, n, bi, bj, tree):
    """The kernel's parent / pred / thread / rev / succ / last against their definitions."""
    nn = m + n
    twin = tree_arrays_twin(m, n, bi, bj)
    assert twin is not None, "the basic cells are not a spanning tree"
    parent, pred, size = twin
    np.testing.assert_array_equal(tree[T._PARENT][:nn], parent)
    np.testing.assert_array_equal(tree[T._PRED][:nn], pred)
    np.testing.assert_array_equal(tree[T._SUCC][:nn], size)
    seq = [0]
    while len(seq) <= nn and tree[T._THREAD][seq[-1]] != 0:
        seq.append(int(tree[T._THREAD][seq[-1]]))
    assert sorted(seq) == list(range(nn)), "the thread is not one cycle through every node"
    for k, z in enumerate(seq):
        assert tree[T._REV][z] == seq[k - 1]
    pos = {z: k for k, z in enumerate(seq)}
    for z in range(nn):  # preorder: a node's subtree is the segment starting at it
        segment = seq[pos[z]:pos[z] + size[z]]
        for w in segment:
            y = w
            while y != z:
                y = parent[y]
                assert y != -1, f"{w} in the segment of {z} is not below it"
        assert tree[T._LAST][z] == segment[-1]


def least_cost_basis(a, b, cost):
    """The solver's workspace for ``cost`` (m, n) and its least-cost start: (workspace, tree,
    link, net, pot, x, bi, bj)."""
    m, n = cost.shape
    ws = S._workspace(m, n)
    _, link, net, pot, x = ws[:5]
    bi = np.zeros(m + n - 1, np.int64)
    bj = np.zeros(m + n - 1, np.int64)
    T._least_cost_start(m, n, a, b, cost, bi, bj, ws[5], ws[6], ws[7], ws[8], ws[0][0], net)
    return ws, ws[9], link, net, pot, x, bi, bj


def test_build_tree_matches_numpy_twins():
    rng = np.random.default_rng(16)
    for _ in range(150):
        a, b, cost = random_problem(rng)
        a, b = a / a.sum(), b / b.sum()
        m, n = cost.shape
        ws, tree, link, net, pot, x, bi, bj = least_cost_basis(a, b, cost)
        b2 = rng.random(n)  # other masses: any flows, negative ones included
        b2 /= b2.sum()
        assert T._build_tree(m, n, bi, bj, a, b2, cost, tree, link, net, pot, x)
        check_tree_arrays(m, n, bi, bj, tree)
        x_ref, pot_ref = tree_twin(m, n, bi, bj, a, b2, cost)
        np.testing.assert_allclose(x[:m + n - 1], x_ref, atol=1e-12)
        np.testing.assert_allclose(pot, pot_ref, atol=1e-12)


def test_build_tree_rejects_a_non_tree():
    a = b = np.array([0.5, 0.5])
    ws = S._workspace(2, 2)
    _, link, net, pot, x = ws[:5]
    for bi, bj in (([0, 0, 0], [0, 1, 0]),     # cell (0, 0) twice, row 1 unreached
                   ([0, 0, 1], [0, 1, 1])):    # fine: a path
        ok = T._build_tree(2, 2, np.array(bi), np.array(bj), a, b, np.ones((2, 2)), ws[9],
                           link, net, pot, x)
        assert ok == (tree_arrays_twin(2, 2, np.array(bi), np.array(bj)) is not None)
    m, n = 3, 3  # a cycle (0,0)-(0,1)-(1,1)-(1,0) and row 2 / column 2 cut off
    ws = S._workspace(m, n)
    bi = np.array([0, 0, 1, 1, 2])
    bj = np.array([0, 1, 1, 0, 2])
    assert not T._build_tree(m, n, bi, bj, np.ones(3) / 3, np.ones(3) / 3, np.ones((3, 3)),
                             ws[9], ws[1], ws[2], ws[3], ws[4])


@pytest.mark.parametrize("kind", ["float", "int_all", "zeros", "points"])
def test_pivots_keep_tree_potentials_and_flows_exact(kind):
    """Pivot by pivot (entering cell: the most negative reduced cost, by NumPy), the updated
    tree arrays, potentials and flows equal the ones computed from scratch, the objective falls
    by theta |d|, and the last basis is optimal (linprog)."""
    rng = np.random.default_rng(17 + len(kind))
    for trial in range(12):
        m, n = int(rng.integers(1, 14)), int(rng.integers(1, 14))
        a, b, cost = random_problem(rng, kind, m, n)
        a, b = a / a.sum(), b / b.sum()
        ws, tree, link, net, pot, x, bi, bj = least_cost_basis(a, b, cost)
        assert T._build_tree(m, n, bi, bj, a, b, cost, tree, link, net, pot, x)
        bland = bool(trial % 3 == 0)
        tol = 1e-12 * np.abs(cost).max()
        for _ in range(10 * (m + n) ** 2):
            red = cost - pot[:m, None] - pot[None, m:m + n]
            p, q = np.unravel_index(np.argmin(red), red.shape)
            if bland:
                hits = np.argwhere(red < -tol)
                p, q = hits[0] if len(hits) else (p, q)
            if not red[p, q] < -tol:
                break
            before = float(np.sum(cost[bi, bj] * x[:m + n - 1]))
            theta = T._pivot(m, n, p, q, red[p, q], bland, -1, bi, bj, tree, pot, x,
                             tree[T._ORDER])
            check_tree_arrays(m, n, bi, bj, tree)
            x_ref, pot_ref = tree_twin(m, n, bi, bj, a, b, cost)
            np.testing.assert_allclose(pot, pot_ref, atol=1e-12)
            np.testing.assert_allclose(x[:m + n - 1], x_ref, atol=1e-12)
            assert (x_ref >= -1e-12).all()
            after = float(np.sum(cost[bi, bj] * x[:m + n - 1]))
            assert after == pytest.approx(before + theta * red[p, q], abs=1e-12)
            pot_fresh = pot.copy()
            T._tree_potentials(m, bi, bj, cost, tree, pot_fresh)
            np.testing.assert_allclose(pot_fresh, pot_ref, atol=1e-12)
        else:
            pytest.fail("no optimum within the pivot bound")
        x_fresh = x.copy()
        T._tree_flows(m, n, a, b, tree, net, x_fresh, False)
        np.testing.assert_allclose(x_fresh[:m + n - 1], tree_twin(m, n, bi, bj, a, b, cost)[0],
                                   atol=1e-12)
        value = float(np.sum(cost[bi, bj] * np.maximum(x_fresh[:m + n - 1], 0.0)))
        assert abs(value - lp_emd(a, b, cost)[0]) <= TOL


def test_dual_warm_start_matches_linprog():
    """From the optimum of one column mass vector, the dual simplex reaches the other's."""
    rng = np.random.default_rng(14)
    for trial in range(60):
        a, b, cost = random_problem(rng, None if trial % 2 else "int_all")
        a, b = a / a.sum(), b / b.sum()
        m, n = cost.shape
        ws = S._workspace(m, n)
        bi = np.zeros(m + n - 1, np.int64)
        bj = np.zeros(m + n - 1, np.int64)
        assert S._cold_solve(a, b, cost, 1e-12, 100, bi, bj, ws)[0] == 0
        b2 = rng.random(n) * (rng.random(n) < 0.8)
        if b2.sum() == 0:
            b2[0] = 1.0
        b2 /= b2.sum()
        bland = int(rng.integers(0, 2)) * 100
        status, _ = S._dual(m, n, a, b2, cost, bi, bj, np.inf, bland, *ws[:5], ws[9])
        assert status == 0
        check_tree_arrays(m, n, bi, bj, ws[9])
        x_ref, pot_ref = tree_twin(m, n, bi, bj, a, b2, cost)
        np.testing.assert_allclose(ws[4][:m + n - 1], x_ref, atol=1e-12)
        np.testing.assert_allclose(ws[3], pot_ref, atol=1e-12)
        red = cost - pot_ref[:m, None] - pot_ref[None, m:]
        assert red.min() >= -1e-12 and x_ref.min() >= -1e-12  # dual and primal feasible
        value = S._objective(m, n, bi, bj, cost, ws[4])
        assert abs(value - lp_emd(a, b2, cost)[0]) <= TOL


def test_dual_cutoff_stops_early_and_never_above_the_optimum():
    rng = np.random.default_rng(15)
    a, b, cost = random_problem(rng, "points", 12, 12)
    a, b = a / a.sum(), b / b.sum()
    m, n = cost.shape
    ws = S._workspace(m, n)
    bi = np.zeros(m + n - 1, np.int64)
    bj = np.zeros(m + n - 1, np.int64)
    S._cold_solve(a, b, cost, 1e-12, 100, bi, bj, ws)
    b2 = b.copy()
    b2[np.argmax(b)] = 0.0
    b2 /= b2.sum()
    opt = lp_emd(a, b2, cost)[0]
    status, _ = S._dual(m, n, a, b2, cost, bi.copy(), bj.copy(), opt - 1e-3, 100, *ws[:5], ws[9])
    assert status == S._CUT_OFF
    status, _ = S._dual(m, n, a, b2, cost, bi, bj, opt + 1e-9, 100, *ws[:5], ws[9])
    assert status == 0


# --------------------------------------------------------------------------- greedy


@pytest.mark.parametrize("seed", range(6))
def test_greedy_matches_linprog_twin(seed):
    rng = np.random.default_rng(100 + seed)
    m, n = int(rng.integers(3, 9)), int(rng.integers(3, 9))
    n_novel = int(rng.integers(0, min(3, n - 1) + 1))
    a, b, cost = separated_greedy_problem(rng, m, n, n_novel)
    candidates = rng.random(n) < 0.8
    max_removals = int(rng.integers(1, n + 1))
    order, after, stop, gaps = greedy_twin(a, b, cost, candidates, max_removals)
    assert min(gaps, default=np.inf) > 1e-6, "ambiguous problem: pick another seed"
    res = greedy_emd(a, b, cost, candidates, max_removals)
    np.testing.assert_array_equal(res.order, order)
    np.testing.assert_allclose(res.emd_after, after, rtol=0, atol=TOL)
    assert res.stop_reason == stop
    assert res.order.dtype == np.int64 and res.emd_after.dtype == np.float64


def test_greedy_removes_the_novel_components_first():
    rng = np.random.default_rng(21)
    a, b, cost = separated_greedy_problem(rng, 10, 12, 3)
    novel = np.flatnonzero(cost.min(axis=0) > 1.0)
    assert len(novel) == 3
    res = greedy_emd(a, b, cost)
    assert set(res.order[:3].tolist()) == set(novel.tolist())
    assert (res.drops > 0).all()


def test_greedy_30x30_consistent_with_emd():
    """At K = 30 (too slow for the linprog twin), every recorded value is an exact EMD."""
    rng = np.random.default_rng(22)
    a, b, cost = separated_greedy_problem(rng, 30, 30, 5)
    for candidates in (np.ones(30, bool), rng.random(30) < 0.2):
        res = greedy_emd(a, b, cost, candidates)
        assert res.emd_after[0] == pytest.approx(emd(a, b, cost).distance, abs=1e-12)
        for i in range(1, len(res.order) + 1):
            bb = b.copy()
            bb[res.order[:i]] = 0.0
            assert abs(res.emd_after[i] - emd(a, bb, cost).distance) <= 1e-12
        assert np.all(np.diff(res.emd_after) < 0)
        assert candidates[res.order].all()
        # the round after the last removal: no candidate lowers the EMD
        if res.stop_reason == STOP_REASONS[0]:
            bb = b.copy()
            bb[res.order] = 0.0
            for k in np.flatnonzero(candidates & (bb > 0)):
                b3 = bb.copy()
                b3[k] = 0.0
                assert emd(a, b3, cost).distance >= res.emd_after[-1] - 1e-12


def test_greedy_30x30_candidates_against_linprog():
    rng = np.random.default_rng(23)
    a, b, cost = separated_greedy_problem(rng, 30, 30, 3)
    candidates = np.zeros(30, bool)
    candidates[rng.choice(30, 5, replace=False)] = True
    candidates[np.argmax(cost.min(axis=0))] = True
    order, after, stop, gaps = greedy_twin(a, b, cost, candidates, 30)
    assert min(gaps) > 1e-6
    res = greedy_emd(a, b, cost, candidates)
    np.testing.assert_array_equal(res.order, order)
    np.testing.assert_allclose(res.emd_after, after, atol=TOL)


def test_greedy_single_values_match_linprog():
    rng = np.random.default_rng(24)
    a, b, cost = separated_greedy_problem(rng, 6, 7, 2)
    candidates = np.ones(7, bool)
    candidates[3] = False
    res = greedy_emd(a, b, cost, candidates, compute_single=True)
    for k in range(7):
        if not candidates[k]:
            assert np.isnan(res.emd_single[k])
            continue
        bb = b.copy()
        bb[k] = 0.0
        assert abs(res.emd_single[k] - lp_emd(a, bb, cost)[0]) <= TOL
    assert res.emd_after[1] == np.nanmin(res.emd_single)
    assert np.isnan(greedy_emd(a, b, cost).emd_single).all()


def test_greedy_bland_rule_gives_the_same_trajectory():
    rng = np.random.default_rng(25)
    a, b, cost = separated_greedy_problem(rng, 12, 12, 3)
    a, b = a / a.sum(), b / b.sum()
    cand = np.ones(12, bool)
    plain = G._greedy_kernel(a, b, cost, cand, 12, False, S._REL_TOL_COST, -1)
    bland = G._greedy_kernel(a, b, cost, cand, 12, False, S._REL_TOL_COST, 0)
    np.testing.assert_array_equal(plain[0], bland[0])
    np.testing.assert_allclose(plain[1], bland[1], atol=1e-12)
    assert bland[6] == 0


def test_greedy_stop_reasons():
    rng = np.random.default_rng(26)
    a, b, cost = separated_greedy_problem(rng, 5, 6, 2)
    none = greedy_emd(a, b, cost, np.zeros(6, bool))
    assert none.stop_reason == "no candidate left" and len(none.order) == 0
    assert none.emd_after.shape == (1,)
    assert none.emd_after[0] == pytest.approx(emd(a, b, cost).distance, abs=1e-15)
    zero = greedy_emd(a, b, cost, max_removals=0)
    assert zero.stop_reason == "max_removals reached" and len(zero.order) == 0
    one = greedy_emd(a, b, cost, max_removals=1)
    assert one.stop_reason == "max_removals reached" and len(one.order) == 1
    # a single variable component: removing it would leave no mass
    solo = greedy_emd(a, [1.0], cost[:, :1])
    assert solo.stop_reason == "every removal would leave no mass"
    # all candidates removed: nothing left to try
    far = np.array([[10.0, 11.0, 1.0]])
    res = greedy_emd([1.0], [0.3, 0.3, 0.4], far, np.array([True, True, False]))
    np.testing.assert_array_equal(np.sort(res.order), [0, 1])
    assert res.stop_reason == "no candidate left"
    assert res.emd_after[-1] == pytest.approx(1.0, abs=1e-15)


def test_greedy_zero_weight_components_are_never_removed():
    rng = np.random.default_rng(27)
    a, b, cost = separated_greedy_problem(rng, 6, 8, 2)
    b[[1, 5]] = 0.0
    res = greedy_emd(a, b, cost)
    assert 1 not in res.order and 5 not in res.order
    assert (res.drops > 0).all()


def test_greedy_identical_sides_remove_nothing():
    rng = np.random.default_rng(28)
    pts = rng.random((10, 3))
    w = rng.random(10)
    res = greedy_emd(w, w, cdist(pts, pts))
    assert res.emd_after.tolist() == [0.0]
    assert res.stop_reason == STOP_REASONS[0]
    assert isinstance(res, GreedyResult)


@pytest.mark.parametrize("kwargs, match", [
    (dict(candidates=np.ones(3, bool)), "candidates"),
    (dict(candidates=np.ones(4, int)), "boolean"),
    (dict(max_removals=-1), "max_removals"),
    (dict(max_removals=1.5), "max_removals"),
    (dict(max_removals=True), "max_removals"),
])
def test_greedy_bad_input(kwargs, match):
    with pytest.raises(InputError, match=match):
        greedy_emd(np.ones(2), np.ones(4), np.ones((2, 4)), **kwargs)


def test_greedy_bad_weights_and_cost():
    with pytest.raises(InputError, match="weights_fixed"):
        greedy_emd([-1.0, 2.0], [1.0], [[1.0], [1.0]])
    with pytest.raises(InputError, match="weights_var"):
        greedy_emd([1.0], [np.nan], [[1.0]])
    with pytest.raises(InputError, match="shape"):
        greedy_emd([1.0], [1.0, 1.0], [[1.0]])


# --------------------------------------------------------------------------- ground distance


def random_spd(rng, k, d=3, scale=1.0):
    g = rng.standard_normal((k, d, d))
    return scale * (g @ g.transpose(0, 2, 1) + 0.05 * np.eye(d))


def test_euclidean_ground_distance_matches_cdist():
    rng = np.random.default_rng(30)
    p, q = rng.random((7, 3)), rng.random((4, 3))
    np.testing.assert_allclose(ground_distance(p, q), cdist(p, q), atol=1e-15)


def test_wasserstein2_matches_sqrtm_twin():
    rng = np.random.default_rng(31)
    mu_a, mu_b = rng.random((6, 3)), rng.random((5, 3))
    cov_a, cov_b = random_spd(rng, 6, scale=0.01), random_spd(rng, 5, scale=0.01)
    got = ground_distance(mu_a, mu_b, cov_a, cov_b, kind="wasserstein2")
    np.testing.assert_allclose(got, w2_twin(mu_a, mu_b, cov_a, cov_b), rtol=1e-9, atol=1e-12)
    back = ground_distance(mu_b, mu_a, cov_b, cov_a, kind="wasserstein2")
    np.testing.assert_allclose(back, got.T, rtol=1e-9, atol=1e-12)


def test_wasserstein2_equal_covariances_is_euclidean():
    rng = np.random.default_rng(32)
    mu_a, mu_b = rng.random((4, 3)), rng.random((4, 3))
    cov = random_spd(rng, 1)[0]
    covs = np.repeat(cov[None], 4, axis=0)
    got = ground_distance(mu_a, mu_b, covs, covs.copy(), kind="wasserstein2")
    np.testing.assert_allclose(got, cdist(mu_a, mu_b), rtol=1e-12, atol=0)
    same = ground_distance(mu_a, mu_a, covs, covs, kind="wasserstein2")
    assert (np.diag(same) == 0.0).all()


def test_wasserstein2_commuting_closed_form():
    """Sa, Sb with the same eigenvectors: Bures term = sum (sqrt(la) - sqrt(lb))^2."""
    rng = np.random.default_rng(33)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    la, lb = rng.random(3) + 0.1, rng.random(3) + 0.1
    sa, sb = q @ np.diag(la) @ q.T, q @ np.diag(lb) @ q.T
    mu_a, mu_b = rng.random(3), rng.random(3)
    got = ground_distance(mu_a[None], mu_b[None], sa[None], sb[None], kind="wasserstein2")
    want = math.sqrt(np.sum((mu_a - mu_b) ** 2) + np.sum((np.sqrt(la) - np.sqrt(lb)) ** 2))
    assert got[0, 0] == pytest.approx(want, rel=1e-12)


def test_wasserstein2_one_dimensional():
    """1-D Gaussians: W2^2 = (m1 - m2)^2 + (s1 - s2)^2."""
    got = ground_distance([[0.0]], [[3.0]], [[[4.0]]], [[[1.0]]], kind="wasserstein2")
    assert got[0, 0] == pytest.approx(math.sqrt(9.0 + 1.0), rel=1e-14)


def test_wasserstein2_degenerate_covariances():
    """Rank-deficient (flat) covariances: finite and non-negative, matches the twin."""
    rng = np.random.default_rng(34)
    flat = np.diag([1e-2, 1e-2, 0.0])[None]
    other = random_spd(rng, 2, scale=1e-3)
    mu = rng.random((1, 3))
    got = ground_distance(mu, rng.random((2, 3)), flat, other, kind="wasserstein2")
    assert np.isfinite(got).all() and (got >= 0).all()
    point = ground_distance(mu, mu, np.zeros((1, 3, 3)), np.zeros((1, 3, 3)),
                            kind="wasserstein2")
    assert point[0, 0] == 0.0


@pytest.mark.parametrize("args, kwargs, match", [
    ((np.zeros((2, 3)), np.zeros((2, 3))), dict(kind="manhattan"), "kind"),
    ((np.zeros((2, 3)), np.zeros((2, 2))), {}, "dimension"),
    ((np.zeros(3), np.zeros((2, 3))), {}, "means_a"),
    ((np.zeros((0, 3)), np.zeros((2, 3))), {}, "means_a"),
    ((np.full((1, 3), np.nan), np.zeros((2, 3))), {}, "NaN"),
    ((np.zeros((1, 3)), np.zeros((1, 3))), dict(kind="wasserstein2"), "needs covariances_a"),
    ((np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3)[None], np.eye(2)[None]),
     dict(kind="wasserstein2"), "covariances_b must have shape"),
    ((np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3)[None], np.full((1, 3, 3), np.inf)),
     dict(kind="wasserstein2"), "NaN"),
    ((np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3)[None], np.triu(np.ones((3, 3)))[None]),
     dict(kind="wasserstein2"), "symmetric"),
    ((np.zeros((1, 3)), np.zeros((1, 3)), np.eye(3)[None], -np.eye(3)[None]),
     dict(kind="wasserstein2"), "semi-definite"),
])
def test_ground_distance_bad_input(args, kwargs, match):
    with pytest.raises(InputError, match=match):
        ground_distance(*args, **kwargs)


# --------------------------------------------------------------------------- mixtures


def random_mixture(rng, k):
    w = rng.random(k) + 0.1
    return Mixture(w / w.sum(), rng.random((k, 3)), random_spd(rng, k, scale=1e-3))


@pytest.mark.parametrize("kind", ["euclidean", "wasserstein2"])
def test_mixture_emd(kind):
    rng = np.random.default_rng(40)
    a, b = random_mixture(rng, 5), random_mixture(rng, 7)
    assert mixture_emd(a, a, kind) == 0.0
    cost = ground_distance(a.means, b.means, a.covariances, b.covariances, kind=kind)
    assert mixture_emd(a, b, kind) == pytest.approx(lp_emd(a.weights, b.weights, cost)[0],
                                                    abs=TOL)
    assert mixture_emd(a, b, kind) == pytest.approx(mixture_emd(b, a, kind), abs=1e-12)


def test_mixture_emd_single_components():
    rng = np.random.default_rng(41)
    a, b = random_mixture(rng, 1), random_mixture(rng, 1)
    assert mixture_emd(a, b) == pytest.approx(np.linalg.norm(a.means[0] - b.means[0]),
                                              abs=1e-15)
    w2 = w2_twin(a.means, b.means, a.covariances, b.covariances)[0, 0]
    assert mixture_emd(a, b, "wasserstein2") == pytest.approx(w2, rel=1e-9)


def test_mixture_emd_bad_input():
    rng = np.random.default_rng(42)
    a = random_mixture(rng, 2)
    with pytest.raises(InputError, match="Mixture"):
        mixture_emd(a, np.ones(3))
    with pytest.raises(InputError, match="kind"):
        mixture_emd(a, a, "l1")
