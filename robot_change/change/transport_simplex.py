"""The network simplex that solves the transportation problem exactly: primal and dual
simplex on the spanning-tree basis (:mod:`robot_change.change.transport_tree`), cold and warm
solves, the exact EMD kernels, and the Python checks of their inputs.

Masses: ``a`` (m,) rows and ``b`` (n,) columns, each >= 0 and summing to 1; ``cost`` (m, n)
finite, C-contiguous float64 (any unit; the EMD is in it).  Statuses ``_OK`` .. ``_BAD_INPUT``.
Every kernel is ``@njit(cache=True, nogil=True)`` with a plain NumPy/SciPy twin in
``tests/test_emd.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from robot_change.change.transport_tree import (
    _ORDER,
    _PRED,
    _SUCC,
    _THREAD,
    _TOL_FLOW,
    _build_tree,
    _least_cost_start,
    _pivot,
    _tree_flows,
    _tree_potentials,
)
from robot_change.errors import InputError, SolverError

#: Reduced costs below ``-_REL_TOL_COST * max|cost|`` are negative.
_REL_TOL_COST = 1e-12
#: Pivots with the fast rules (primal: block search; dual: most infeasible) before Bland's rule.
_DANTZIG_PIVOTS_PER_NODE = 50
#: Hard bound on pivots per solve; Bland's rule terminates far below it.
_MAX_PIVOTS_PER_NODE = 100_000

_OK, _ITER_LIMIT, _BAD_TREE, _NO_ENTERING, _CUT_OFF = 0, 1, 2, 3, 4
#: Status of :func:`_checked_emd_kernel` for weights or costs that fail a check.
_BAD_INPUT = 5
#: Block search of the primal simplex: ``_BLOCK_FACTOR * sqrt(m n)`` cells, at least
#: ``_MIN_BLOCK``.
_BLOCK_FACTOR = 1.0
_MIN_BLOCK = 10


@njit(cache=True, nogil=True)
def _primal(m, n, a, b, cost, bi, bj, tol_c, bland_after, tree, link, net, pot, x):
    """Primal network simplex from the feasible basis ``(bi, bj)``, in place.

    Pricing: block search (``_BLOCK_FACTOR * sqrt(m n)`` cells, at least
    ``_MIN_BLOCK``, continuing cyclically where the last block ended; the most negative reduced
    cost of the first block holding one enters); after ``bland_after`` pivots Bland's rule (the
    first improving cell in row-major order, ties of the leaving cell to the smallest index).
    Potentials and flows are updated by :func:`_pivot`; optimality is only declared after a
    full scan with potentials recomputed from scratch, and the final flows are recomputed from
    scratch too (rounding of the updates never reaches the result).

    Parameters
    ----------
    tree : array of int64, shape (8, m + n + 1), work (see :func:`_build_tree`); its row
        ``_ORDER`` is the pivot's work.
    link : array of int64, shape (2 (m + n - 1),), work
    net, pot : arrays, shape (m + n,), work / written
    x : array, shape (m + n - 1,), written with the flows of the final basis.

    Returns
    -------
    status : int
        0 optimal, 1 pivot bound reached, 2 the cells are not a spanning tree.
    n_pivots : int
    """
    nn = m + n
    if not _build_tree(m, n, bi, bj, a, b, cost, tree, link, net, pot, x):
        return _BAD_TREE, 0
    order = tree[_ORDER]
    cells = m * n
    block = max(min(_MIN_BLOCK, cells), int(_BLOCK_FACTOR * np.sqrt(cells)))
    max_pivots = _MAX_PIVOTS_PER_NODE * nn
    vpot = pot[m:]
    pivots = 0
    fresh = True  # potentials just recomputed from scratch
    ci = 0
    cj = 0
    while True:
        best = -tol_c
        p = -1
        q = -1
        if pivots >= bland_after:
            for i in range(m):
                ui = pot[i]
                for j in range(n):
                    d = cost[i, j] - ui - vpot[j]
                    if d < best:
                        best = d
                        p = i
                        q = j
                        break
                if p >= 0:
                    break
        else:
            scanned = 0
            in_block = 0
            i = ci
            j = cj
            while scanned < cells:
                lim = min(n - j, block - in_block, cells - scanned)
                ui = pot[i]
                for jj in range(j, j + lim):
                    d = cost[i, jj] - ui - vpot[jj]
                    if d < best:
                        best = d
                        p = i
                        q = jj
                scanned += lim
                in_block += lim
                j += lim
                if j == n:
                    j = 0
                    i += 1
                    if i == m:
                        i = 0
                if in_block == block:
                    in_block = 0
                    if p >= 0:
                        break
            ci = i
            cj = j
        if p < 0:
            if fresh:
                break
            _tree_potentials(m, bi, bj, cost, tree, pot)
            fresh = True
            continue
        if pivots >= max_pivots:
            return _ITER_LIMIT, pivots
        bland = pivots >= bland_after
        pivots += 1
        fresh = False
        _pivot(m, n, np.int64(p), np.int64(q), best, bland, np.int64(-1), bi, bj, tree, pot,
               x, order)  # typed ints: no literal specialisation of _pivot to compile
    _tree_flows(m, n, a, b, tree, net, x, np.bool_(False))  # a bool: one compile for both
    return _OK, pivots


@njit(cache=True, nogil=True)
def _dual(m, n, a, b, cost, bi, bj, cutoff, bland_after, ws_i, link, net, pot, x, tree):
    """Dual transportation simplex from a dual-feasible basis ``(bi, bj)``, in place.

    Leaving: the most negative flow (Bland: the smallest cell index among the negative ones).
    Entering: the cell of least reduced cost crossing the cut the leaving cell makes, from the
    rows of the column's side to the columns of the row's side (ties to the smallest cell).  The
    tree is updated as in the primal (:func:`_pivot`); flows and potentials are then recomputed
    from the tree in O(m + n) (few pivots per solve: no rounding builds up).

    Parameters as :func:`_primal`; ``ws_i`` (3, m + n + 1) int64: rows 1 and 2 are the
    subtree mark and the row / column lists.  ``cutoff``: stop as soon as the dual objective
    ``a @ u + b @ v`` (a lower bound of the optimum, non-decreasing over the pivots) exceeds it.

    Returns
    -------
    status : int
        0 primal feasible (hence optimal), 1 pivot bound, 2 not a spanning tree, 3 no cell can
        enter (the problem is infeasible to rounding), 4 cut off (the optimum > ``cutoff``).
    n_pivots : int
    """
    insub, lists = ws_i[1], ws_i[2]
    pred, thread, succ = tree[_PRED], tree[_THREAD], tree[_SUCC]
    order = tree[_ORDER]
    nn = m + n
    ne = nn - 1
    max_pivots = _MAX_PIVOTS_PER_NODE * nn
    if not _build_tree(m, n, bi, bj, a, b, cost, tree, link, net, pot, x):
        return _BAD_TREE, 0
    pivots = 0
    while True:
        if cutoff < np.inf:
            bound = 0.0
            for i in range(m):
                bound += a[i] * pot[i]
            for j in range(n):
                bound += b[j] * pot[m + j]
            if bound > cutoff:
                return _CUT_OFF, pivots
        bland = pivots >= bland_after
        le = -1
        worst = -_TOL_FLOW
        worst_key = nn * nn
        for e in range(ne):
            if bland:
                if x[e] < -_TOL_FLOW:
                    key = bi[e] * n + bj[e]
                    if key < worst_key:
                        worst_key = key
                        le = e
            elif x[e] < worst:
                worst = x[e]
                le = e
        if le < 0:
            return _OK, pivots
        if pivots >= max_pivots:
            return _ITER_LIMIT, pivots
        pivots += 1
        i = bi[le]
        z = i if pred[i] == le else m + bj[le]  # the leaving cell's end below the other
        for w in range(nn):
            insub[w] = 0
        w = z
        for _ in range(succ[z]):
            insub[w] = 1
            w = thread[w]
        want_rows = 0 if z < m else 1
        n_rows = 0
        n_cols = 0
        for r in range(m):
            if insub[r] == want_rows:
                lists[n_rows] = r
                n_rows += 1
        for c in range(n):
            if insub[m + c] != want_rows:
                lists[m + n_cols] = c
                n_cols += 1
        best = np.inf
        p = -1
        q = -1
        for s in range(n_rows):
            r = lists[s]
            ur = pot[r]
            for t in range(n_cols):
                c = lists[m + t]
                d = cost[r, c] - ur - pot[m + c]
                if d < best:  # rows and columns ascending: ties go to the smallest cell
                    best = d
                    p = r
                    q = c
        if p < 0:
            return _NO_ENTERING, pivots
        _pivot(m, n, np.int64(p), np.int64(q), cost[p, q] - pot[p] - pot[m + q], bland,
               np.int64(z), bi, bj, tree, pot, x, order)
        _tree_flows(m, n, a, b, tree, net, x, np.bool_(False))
        _tree_potentials(m, bi, bj, cost, tree, pot)


@njit(cache=True, nogil=True)
def _objective(m, n, bi, bj, cost, x):
    """``sum cost * flow`` over the basic cells, flows below 0 (rounding) counted as 0."""
    total = 0.0
    for e in range(m + n - 1):
        if x[e] > 0.0:
            total += cost[bi[e], bj[e]] * x[e]
    return total


@njit(cache=True, nogil=True)
def _tolerance(cost, rel_tol):
    """``rel_tol * max|cost|``."""
    top = 0.0
    for v in cost.ravel():
        top = max(top, abs(v))
    return rel_tol * top


@njit(cache=True, nogil=True)
def _workspace(m, n):
    """Work arrays of one solve: (ws_i (3, m+n+1) int64: the least-cost start's best columns,
    the dual's subtree mark and lists; link, net, pot, x, sa, sb, row_on, col_on, tree (8,
    m+n+1) int64: see :func:`_build_tree`)."""
    nn = m + n
    return (np.zeros((3, nn + 1), dtype=np.int64), np.zeros(2 * nn, dtype=np.int64),
            np.zeros(nn), np.zeros(nn), np.zeros(nn), np.zeros(m), np.zeros(n),
            np.zeros(m, dtype=np.bool_), np.zeros(n, dtype=np.bool_),
            np.zeros((8, nn + 1), dtype=np.int64))


@njit(cache=True, nogil=True)
def _cold_solve(a, b, cost, tol_c, bland_after, bi, bj, ws):
    """Least-cost start then primal simplex; returns (status, n_pivots)."""
    m, n = cost.shape
    ws_i, link, net, pot, x, sa, sb, row_on, col_on, tree = ws
    _least_cost_start(m, n, a, b, cost, bi, bj, sa, sb, row_on, col_on, ws_i[0], net)
    return _primal(m, n, a, b, cost, bi, bj, tol_c, bland_after, tree, link, net, pot, x)


@njit(cache=True, nogil=True)
def _warm_solve(a, b, cost, tol_c, cutoff, bland_after, bi, bj, ws):
    """Dual simplex from the optimal basis of other column masses (dual feasible: the costs
    are the same); a cold solve if that fails.  Returns (status, n_pivots), status 4 when the
    optimum is above ``cutoff``."""
    m, n = cost.shape
    ws_i, link, net, pot, x, tree = ws[0], ws[1], ws[2], ws[3], ws[4], ws[9]
    status, piv = _dual(m, n, a, b, cost, bi, bj, cutoff, bland_after, ws_i, link, net, pot, x,
                        tree)
    if status != _OK and status != _CUT_OFF:
        status, piv2 = _cold_solve(a, b, cost, tol_c, bland_after, bi, bj, ws)
        piv += piv2
    return status, piv


@njit(cache=True, nogil=True)
def _emd_kernel(a, b, cost, rel_tol, bland_after):
    """Exact EMD.

    Parameters
    ----------
    a : array, shape (m,)
        Row masses, >= 0, summing to 1.
    b : array, shape (n,)
        Column masses, >= 0, summing to 1.
    cost : array, shape (m, n)
    rel_tol : float
        Reduced costs below ``-rel_tol * max|cost|`` are negative.
    bland_after : int
        Pivots per solve before Bland's rule; < 0: ``_DANTZIG_PIVOTS_PER_NODE * (m + n)``.

    Returns
    -------
    distance : float
    flow : array, shape (m, n)
    status : int
        0 optimal; else the solver failed (a bug).
    n_pivots : int
    """
    return _solve_emd(a, b, cost, _tolerance(cost, rel_tol), bland_after)


@njit(cache=True, nogil=True)
def _solve_emd(a, b, cost, tol_c, bland_after):
    """:func:`_emd_kernel` with the absolute tolerance ``tol_c`` given."""
    m, n = cost.shape
    if bland_after < 0:
        bland_after = _DANTZIG_PIVOTS_PER_NODE * (m + n)
    ws = _workspace(m, n)
    bi = np.zeros(m + n - 1, dtype=np.int64)
    bj = np.zeros(m + n - 1, dtype=np.int64)
    status, piv = _cold_solve(a, b, cost, tol_c, bland_after, bi, bj, ws)
    x = ws[4]
    flow = np.zeros((m, n))
    for e in range(m + n - 1):
        if x[e] > 0.0:
            flow[bi[e], bj[e]] += x[e]
    return _objective(m, n, bi, bj, cost, x), flow, status, piv


@njit(cache=True, nogil=True)
def _normalised(w):
    """``w / sum(w)``, shape (K,); shape (0,) unless every weight is finite and >= 0 and the
    sum finite and > 0."""
    total = 0.0
    for v in w:
        if not (v >= 0.0 and v < np.inf):  # negative, NaN or inf
            return w[:0].copy()
        total += v
    if not (total > 0.0 and total < np.inf):
        return w[:0].copy()
    return w / total


@njit(cache=True, nogil=True)
def _checked_emd_kernel(weights_a, weights_b, cost, rel_tol):
    """:func:`_emd_kernel` from raw weights: checks and normalises them, checks the cost is
    finite (in the pass that finds ``max|cost|``).  Status ``_BAD_INPUT`` when a check fails
    (the caller finds which, with the Python checks, for the message)."""
    m, n = cost.shape
    a = _normalised(weights_a)
    b = _normalised(weights_b)
    top = 0.0
    for i in range(m):
        for j in range(n):
            v = abs(cost[i, j])
            if not v < np.inf:
                return 0.0, np.zeros((m, n)), _BAD_INPUT, 0
            if v > top:
                top = v
    if a.shape[0] != m or b.shape[0] != n:
        return 0.0, np.zeros((m, n)), _BAD_INPUT, 0
    return _solve_emd(a, b, cost, rel_tol * top, -1)


def _check_weights(weights, name: str) -> np.ndarray:
    """Weights as a float64 (K,) array normalised to sum 1; InputError otherwise."""
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric (K,) array: {exc}") from None
    if w.ndim != 1 or w.shape[0] == 0:
        raise InputError(f"{name} must have shape (K,) with K >= 1, got {w.shape}")
    total = w.sum()
    lowest = w.min()  # NaN if any is NaN
    if not (np.isfinite(total) and lowest >= 0 and total > 0):
        if not np.isfinite(w).all():
            raise InputError(f"{name} contain NaN or inf")
        if lowest < 0:
            raise InputError(f"{name} must be >= 0, got min {lowest:.6g}")
        if total > 0:  # finite weights whose sum overflows
            raise InputError(f"{name} are too large to sum (total overflows); rescale them")
        raise InputError(f"{name} are all zero: at least one component needs mass")
    return w / total


def _check_cost(cost, ka: int, kb: int) -> np.ndarray:
    """(Ka, Kb) finite float64 C-contiguous cost; InputError otherwise."""
    try:
        c = np.ascontiguousarray(cost, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"cost must be a numeric (Ka, Kb) array: {exc}") from None
    if c.shape != (ka, kb):
        raise InputError(f"cost must have shape ({ka}, {kb}) (len(weights_a), len(weights_b)), "
                         f"got {c.shape}")
    if not np.isfinite(c.sum()) and not np.isfinite(c).all():
        raise InputError("cost contains NaN or inf")
    return c


def _raise_solver_failure(status: int, shape) -> None:
    raise SolverError(f"transportation simplex failed (status {status}) on a {shape} problem; "
                       "this is a bug in robot_change.change.transport: please report it with "
                       "the inputs")
