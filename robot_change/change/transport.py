"""Earth Mover's Distance between small discrete distributions, and greedy EMD for change.

ALGORITHM.md section 3: the EMD between two Gaussian mixtures takes the component weights as
masses (each side normalised to 1) and a ground distance between components; it is solved
exactly, and the greedy loop removes the components of one mixture that lower the EMD most.

- :func:`emd` solves the transportation problem exactly (K up to a few dozen per side).
- :func:`ground_distance` gives the (Ka, Kb) ground distance: Euclidean between the means
  (default) or the closed-form 2-Wasserstein distance between the Gaussians.
- :func:`greedy_emd` runs the whole greedy removal loop in one numba call and returns its
  trajectory; which prefix of it is a real change is the caller's decision
  (:mod:`robot_change.change.detect`).
- :func:`mixture_emd` is EMD between two :class:`~robot_change.mixture.model.Mixture`.

The solver (all in numba) is the network simplex on the bipartite graph rows x columns (the
transportation simplex).  A basis is ``Ka + Kb - 1`` cells forming a spanning tree; it always
holds exactly that many cells, zero flows included, so degenerate problems (ties, zero weights,
Ka or Kb = 1) need no special case.

- Cold start (:func:`emd`, the greedy loop's first solve): the least-cost rule, crossing out
  exactly one row or column per cell, so the start is a feasible spanning tree.  Then primal
  pivots on a rooted tree (root row 0) kept as parent / edge-to-parent / thread (the cyclic
  preorder) / reverse thread / subtree size / last node of the subtree arrays:

  * pricing by block search: blocks of ``sqrt(Ka Kb)`` cells (at least 10) scanned cyclically
    from where the last one ended; the most negative reduced cost of the first block that has
    one enters;
  * the cycle closes at the deepest common ancestor (climb from the smaller subtree); the
    leaving cell is the smallest flow the cycle takes from, ties to the last one met going round
    the cycle from that ancestor (the strongly feasible rule);
  * the subtree cut off by the leaving cell is re-hung from the entering cell: its potentials
    shift by the entering reduced cost, its preorder is rebuilt in O(subtree) (the parts hanging
    off the reversed path, each in its old order), and only the path's and the cycle's
    ancestors' sizes change.  Flows change on the cycle only;
  * optimality is declared only after a full scan with the potentials recomputed from scratch,
    and the final flows are recomputed from scratch from the tree, so the rounding of the
    updates never reaches the result;
  * after ``_DANTZIG_PIVOTS_PER_NODE * (Ka + Kb)`` pivots the rule switches to Bland's (first
    improving cell in row-major order, smallest-index leaving cell), which cannot cycle.

  :func:`emd` checks and normalises the inputs inside the same kernel call (the Python checks
  only run to word the error), so a 10 x 10 call costs a few microseconds.
- Warm start (greedy): removing a component only changes the column masses, so the previous
  optimal tree stays dual feasible (the costs are the same); dual simplex pivots (the most
  negative flow leaves, the crossing cell of least reduced cost enters, which keeps every
  reduced cost >= 0; Bland's rule after the same bound) restore primal feasibility, hence
  optimality.  The tree is updated as in the primal; the pivots are few per solve (K ~ 30), so
  flows and potentials are then recomputed from the tree (one preorder pass).  The dual objective
  is a lower bound that only rises, so a candidate removal is abandoned as soon as its bound
  exceeds the best removal found so far in the round; the candidates are tried in increasing
  order of their starting bound.  A failed warm solve (pivot bound, rounding) falls back to a
  cold solve.

Tolerances: a reduced cost counts as negative below ``-1e-12 * max|cost|``; a flow counts as
negative below ``-1e-13`` (the masses sum to 1) and flows up to ``1e-13`` count as 0 in the
primal ratio test; flows in ``(-1e-13, 0)`` are reported as 0.

Numeric module: arrays in, arrays out.  Every kernel is ``@njit(cache=True, nogil=True)`` with
a plain NumPy/SciPy twin in ``tests/test_emd.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from robot_change import validate
from robot_change.errors import InputError, SolverError
from robot_change.mixture.model import Mixture

__all__ = [
    "GROUND_DISTANCES",
    "STOP_REASONS",
    "EmdResult",
    "GreedyResult",
    "emd",
    "greedy_emd",
    "ground_distance",
    "mixture_emd",
]

GROUND_DISTANCES = ("euclidean", "wasserstein2")
#: Why :func:`greedy_emd` stopped (:attr:`GreedyResult.stop_reason`).
STOP_REASONS = ("no removal lowers the EMD", "no candidate left",
                "every removal would leave no mass", "max_removals reached")
_STOP_NO_IMPROVEMENT, _STOP_NO_CANDIDATE, _STOP_ZERO_MASS, _STOP_MAX_REMOVALS = 0, 1, 2, 3

#: Reduced costs below ``-_REL_TOL_COST * max|cost|`` are negative.
_REL_TOL_COST = 1e-12
#: Flows below ``-_TOL_FLOW`` are negative (masses sum to 1).
_TOL_FLOW = 1e-13
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
#: Rows of the primal simplex's tree array (:func:`_build_tree`).
_PARENT, _PRED, _THREAD, _REV, _SUCC, _LAST, _HEAD, _STACK = 0, 1, 2, 3, 4, 5, 6, 7
_ORDER = _HEAD  # the pivot's work row (the adjacency heads are only needed to build the tree)


# --------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True)
def _row_best(i, n, cost, col_on, best_j, best_c):
    """Cheapest column still on in row i: writes ``best_j[i]``, ``best_c[i]``."""
    bc = np.inf
    bj = -1
    for j in range(n):
        if col_on[j] and cost[i, j] < bc:
            bc = cost[i, j]
            bj = j
    best_j[i] = bj
    best_c[i] = bc


@njit(cache=True, nogil=True)
def _least_cost_start(m, n, a, b, cost, bi, bj, sa, sb, row_on, col_on, best_j, best_c):
    """Least-cost feasible spanning-tree basis, written into ``bi, bj`` (m + n - 1 cells).

    Cells are taken in increasing cost (ties in row-major order) among rows and columns not yet
    crossed out; each cell crosses out exactly one line (its row if the row's remaining mass is
    used up first, ties to the row, never the last row or the last column), which makes the
    cells a spanning tree whose flows are the allocations (>= 0).  The cheapest cell is found
    from each row's cheapest open column, recomputed only for rows whose column closed.

    Parameters
    ----------
    a : array, shape (m,)
    b : array, shape (n,)
    cost : array, shape (m, n)
    bi, bj : arrays of int64, shape (m + n - 1,), written
    sa, sb : arrays, shapes (m,), (n,), work
    row_on, col_on : arrays of bool, shapes (m,), (n,), work
    best_j : array of int64, shape (>= m,), work
    best_c : array, shape (>= m,), work
    """
    for i in range(m):
        sa[i] = a[i]
        row_on[i] = True
    for j in range(n):
        sb[j] = b[j]
        col_on[j] = True
    for i in range(m):
        _row_best(i, n, cost, col_on, best_j, best_c)
    rows_left = m
    cols_left = n
    ne = m + n - 1
    for k in range(ne):
        i = -1
        c = np.inf
        for r in range(m):
            if row_on[r] and (i < 0 or best_c[r] < c):
                c = best_c[r]
                i = r
        j = best_j[i]
        bi[k] = i
        bj[k] = j
        if k == ne - 1:
            break
        if rows_left == 1:
            cross_row = False
        elif cols_left == 1:
            cross_row = True
        else:
            cross_row = sa[i] <= sb[j]
        if cross_row:
            sb[j] -= sa[i]
            row_on[i] = False
            rows_left -= 1
        else:
            sa[i] -= sb[j]
            col_on[j] = False
            cols_left -= 1
            for r in range(m):
                if row_on[r] and best_j[r] == j:
                    _row_best(r, n, cost, col_on, best_j, best_c)


@njit(cache=True, nogil=True)
def _build_tree(m, n, bi, bj, a, b, cost, tree, link, net, pot, x):
    """Rooted tree arrays, potentials and flows of the basis ``(bi, bj)`` (depth-first).

    Nodes are rows ``0..m-1`` and columns ``m..m+n-1``; the root is row 0.

    Parameters
    ----------
    bi, bj : arrays of int64, shape (m + n - 1,)
        Row and column of each basic cell (tree edge ``e``).
    tree : array of int64, shape (>= 8, >= m + n), written
        Rows ``_PARENT`` (-1 at the root), ``_PRED`` (edge to the parent), ``_THREAD`` (next
        node in preorder, cyclic), ``_REV`` (previous node in preorder), ``_SUCC`` (subtree
        size), ``_LAST`` (last node of the subtree in preorder); rows ``_HEAD`` (first
        adjacency slot) and ``_STACK`` are work.
    link : array of int64, shape (>= 2 (m + n - 1),), work
    net : array, shape (m + n,), work
    pot : array, shape (m + n,), written
        ``u`` (rows) then ``v`` (columns), ``u_i + v_j = cost_ij`` on the tree, ``u_0 = 0``.
    x : array, shape (m + n - 1,), written
        Flow on each basic cell.

    Returns
    -------
    ok : bool
        False when the cells do not form a spanning tree.
    """
    nn = m + n
    parent, pred, thread, rev = tree[_PARENT], tree[_PRED], tree[_THREAD], tree[_REV]
    head, stack = tree[_HEAD], tree[_STACK]
    for z in range(nn):
        head[z] = -1
        parent[z] = -2
    for e in range(nn - 1):
        r = bi[e]
        c = m + bj[e]
        link[2 * e] = head[r]
        head[r] = 2 * e
        link[2 * e + 1] = head[c]
        head[c] = 2 * e + 1
    # depth-first from the root: a node is appended to the preorder when popped
    parent[0] = -1
    pred[0] = -1
    pot[0] = 0.0
    stack[0] = 0
    top = 1
    prev = -1
    count = 0
    while top > 0:
        top -= 1
        z = stack[top]
        if prev >= 0:
            thread[prev] = z
            rev[z] = prev
        prev = z
        count += 1
        slot = head[z]
        while slot >= 0:
            e = slot >> 1
            w = m + bj[e] if z < m else bi[e]
            if parent[w] == -2:
                parent[w] = z
                pred[w] = e
                pot[w] = cost[bi[e], bj[e]] - pot[z]
                stack[top] = w
                top += 1
            elif w != parent[z]:
                return False  # a cycle (or a repeated cell)
            slot = link[slot]
    if count != nn:
        return False  # not connected
    thread[prev] = 0
    rev[0] = prev
    _tree_flows(m, n, a, b, tree, net, x, True)
    return True


@njit(cache=True, nogil=True)
def _tree_flows(m, n, a, b, tree, net, x, sizes):
    """Flows of the tree (children before parents: reverse preorder), into ``x``; with
    ``sizes`` also the subtree sizes and last nodes (rows ``_SUCC``, ``_LAST``)."""
    nn = m + n
    parent, pred, rev = tree[_PARENT], tree[_PRED], tree[_REV]
    succ, last = tree[_SUCC], tree[_LAST]
    for z in range(m):
        net[z] = a[z]
    for z in range(n):
        net[m + z] = -b[z]
    if sizes:
        for z in range(nn):
            succ[z] = 1
            last[z] = z
    z = rev[0]
    while z != 0:
        x[pred[z]] = net[z] if z < m else -net[z]
        w = parent[z]
        net[w] += net[z]
        if sizes:
            succ[w] += succ[z]
            if last[w] == w:  # z is w's last child in preorder
                last[w] = last[z]
        z = rev[z]


@njit(cache=True, nogil=True)
def _tree_potentials(m, bi, bj, cost, tree, pot):
    """Potentials from scratch (parents before children: preorder), ``u_0 = 0``."""
    parent, pred, thread = tree[_PARENT], tree[_PRED], tree[_THREAD]
    pot[0] = 0.0
    z = thread[0]
    while z != 0:
        e = pred[z]
        pot[z] = cost[bi[e], bj[e]] - pot[parent[z]]
        z = thread[z]


@njit(cache=True, nogil=True)
def _pivot(m, n, p, q, d, bland, u_leave, bi, bj, tree, pot, x, order):
    """One pivot: cell ``(p, q)`` of reduced cost ``d`` enters, in place.

    The cycle is the entering cell plus the tree path between row ``p`` and column ``m + q``
    (met at their deepest common ancestor, the *join*, found by climbing from the smaller
    subtree).  Primal (``u_leave < 0``): the cells crossed column -> row lose flow; the leaving
    cell is the smallest of them (flows <= ``_TOL_FLOW`` count as 0): with ``bland`` the
    smallest cell index among ties, otherwise the last one met going round the cycle from the
    join (the strongly feasible rule); flows change on the cycle.  Dual (``u_leave >= 0``): the
    cell joining ``u_leave`` to its parent leaves, flows are left to the caller.

    The subtree ``S`` cut off by the leaving cell is re-hung from the entering cell's end
    outside it, as its first child: the path from the end inside ``S`` to the old root of ``S``
    is reversed; the preorder of ``S`` is rebuilt in ``O(|S|)`` (for each path node, its old
    subtree without the previous path node's, in the old order); the potentials of ``S`` shift
    by ``+-d``; sizes and last nodes change on the path and the cycle's ancestors only.

    Parameters
    ----------
    p, q : int
        Entering cell.
    d : float
        Its reduced cost ``cost[p, q] - pot[p] - pot[m + q]``.
    bland : bool
    u_leave : int
        -1 for the primal ratio test, else the node whose parent cell leaves.
    bi, bj, tree, pot, x
        As :func:`_build_tree`, updated.  The entering cell takes the leaving cell's slot.
    order : array of int64, shape (>= m + n,), work

    Returns
    -------
    theta : float
        The flow moved (0 for a degenerate pivot; 0 in the dual case).
    """
    parent, pred, thread, rev = tree[_PARENT], tree[_PRED], tree[_THREAD], tree[_REV]
    succ, last = tree[_SUCC], tree[_LAST]
    P = p
    Q = m + q
    u = P
    v = Q
    while u != v:
        if succ[u] < succ[v]:
            u = parent[u]
        else:
            v = parent[v]
    join = u
    theta = 0.0
    u_out = u_leave
    if u_leave < 0:
        # leaving cell: on the row side the rows' parent cells lose flow (first minimum met from
        # P); on the column side the columns' (last minimum met from Q, i.e. nearest the join)
        theta = np.inf
        u_out = -1
        key_out = 0
        w = P
        while w != join:
            if w < m:
                e = pred[w]
                xv = x[e] if x[e] > _TOL_FLOW else 0.0
                key = bi[e] * n + bj[e]
                if xv < theta or (bland and xv == theta and key < key_out):
                    theta = xv
                    u_out = w
                    key_out = key
            w = parent[w]
        w = Q
        while w != join:
            if w >= m:
                e = pred[w]
                xv = x[e] if x[e] > _TOL_FLOW else 0.0
                key = bi[e] * n + bj[e]
                if xv < theta or (xv == theta and (not bland or key < key_out)):
                    theta = xv
                    u_out = w
                    key_out = key
            w = parent[w]
        if theta > 0.0:
            w = P
            while w != join:
                if w < m:
                    x[pred[w]] -= theta
                else:
                    x[pred[w]] += theta
                w = parent[w]
            w = Q
            while w != join:
                if w >= m:
                    x[pred[w]] -= theta
                else:
                    x[pred[w]] += theta
                w = parent[w]
    # u_in: the entering cell's end inside S (the side of the leaving cell)
    on_row_side = False
    w = P
    while w != join:
        if w == u_out:
            on_row_side = True
            break
        w = parent[w]
    if on_row_side:
        u_in = P
        v_in = Q
        d_row = d
    else:
        u_in = Q
        v_in = P
        d_row = -d
    d_col = -d_row
    e_out = pred[u_out]
    # new preorder of S (from the old arrays): for each path node s_0 = u_in .. s_k = u_out,
    # its old subtree without s_(i-1)'s, in the old order; potentials shift on the way
    cnt = 0
    prev_s = -1
    s = u_in
    while True:
        end = last[s]
        if prev_s >= 0 and end == last[prev_s]:
            end = rev[prev_s]
        z = s
        while True:
            order[cnt] = z
            cnt += 1
            pot[z] += d_row if z < m else d_col
            if z == end:
                break
            z = thread[z]
            if z == prev_s:
                z = thread[last[prev_s]]
        if s == u_out:
            break
        prev_s = s
        s = parent[s]
    size = succ[u_out]
    old_last = last[u_out]
    before = rev[u_out]
    after = thread[old_last]
    w_out = parent[u_out]
    new_last = order[size - 1]
    # the path: reverse parents, new sizes (|S| minus the old size of the previous path node)
    prev_size = 0
    par_new = v_in
    pred_new = e_out
    s = u_in
    while True:
        old_size = succ[s]
        succ[s] = size - prev_size
        prev_size = old_size
        last[s] = new_last
        old_par = parent[s]
        old_pred = pred[s]
        parent[s] = par_new
        pred[s] = pred_new
        if s == u_out:
            break
        par_new = s
        pred_new = old_pred
        s = old_par
    # cut S out of the thread, then in again right after v_in (as its first child)
    thread[before] = after
    rev[after] = before
    nxt = thread[v_in]
    z = v_in
    for t in range(size):
        y = order[t]
        thread[z] = y
        rev[y] = z
        z = y
    thread[new_last] = nxt
    rev[nxt] = new_last
    # ancestors: sizes change below the join only; last nodes where they ended S / at v_in
    w = w_out
    while w != join:
        succ[w] -= size
        w = parent[w]
    w = v_in
    while w != join:
        succ[w] += size
        w = parent[w]
    w = w_out
    while w >= 0 and last[w] == old_last:
        last[w] = before
        w = parent[w]
    w = v_in
    while w >= 0 and last[w] == v_in:
        last[w] = new_last
        w = parent[w]
    bi[e_out] = p
    bj[e_out] = q
    if u_leave < 0:
        x[e_out] = theta
    return theta


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
    _tree_flows(m, n, a, b, tree, net, x, False)
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
        _tree_flows(m, n, a, b, tree, net, x, False)
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


@njit(cache=True, nogil=True)
def _greedy_kernel(a, b, cost, candidates, max_removals, compute_single, rel_tol, bland_after):
    """The greedy removal loop of :func:`greedy_emd`.

    Each round solves the candidates warm from the current optimal basis, in increasing order
    of the lower bound that basis's potentials give (the dual objective with the new column
    masses); a candidate is dropped as soon as its bound exceeds the best value found so far
    (or ``emd - tol_drop``), so only the promising ones are solved to the end.

    Parameters
    ----------
    a : array, shape (m,)
        Masses of the fixed side (rows), summing to 1.
    b : array, shape (n,)
        Masses of the side components are removed from (columns), summing to 1.
    cost : array, shape (m, n)
    candidates : array of bool, shape (n,)
    max_removals : int
    compute_single : bool
        Solve every candidate of the first round to the end (for ``emd_single``).
    rel_tol, bland_after
        As :func:`_emd_kernel`; a removal must also lower the EMD by more than
        ``rel_tol * max|cost|``.

    Returns
    -------
    order : array of int64, shape (k,)
    emd_after : array, shape (k + 1,)
    emd_single : array, shape (n,)
        EMD after removing only component j (first round), NaN if not solved to the end.
    n_solves : int
        Solves started (1 cold, then warm ones, cut-off ones included).
    n_pivots : int
    stop_code : int
    status : int
        0, or the status of a solve that failed (a bug).
    """
    m, n = cost.shape
    ne = m + n - 1
    tol_c = _tolerance(cost, rel_tol)
    tol_drop = tol_c
    if bland_after < 0:
        bland_after = _DANTZIG_PIVOTS_PER_NODE * (m + n)
    ws = _workspace(m, n)
    link, net, pot, x, tree = ws[1], ws[2], ws[3], ws[4], ws[9]
    cur_bi = np.zeros(ne, dtype=np.int64)
    cur_bj = np.zeros(ne, dtype=np.int64)
    try_bi = np.zeros(ne, dtype=np.int64)
    try_bj = np.zeros(ne, dtype=np.int64)
    best_bi = np.zeros(ne, dtype=np.int64)
    best_bj = np.zeros(ne, dtype=np.int64)
    bb = np.zeros(n)
    removed = np.zeros(n, dtype=np.bool_)
    k_list = np.zeros(n, dtype=np.int64)
    bounds = np.zeros(n)
    masses = np.zeros(n)
    n_max = min(max_removals, n)
    order = np.zeros(n_max, dtype=np.int64)
    emd_after = np.zeros(n_max + 1)
    emd_single = np.full(n, np.nan)

    status, n_pivots = _cold_solve(a, b, cost, tol_c, bland_after, cur_bi, cur_bj, ws)
    if status != _OK:
        return order[:0], emd_after[:1], emd_single, 1, n_pivots, _STOP_NO_IMPROVEMENT, status
    current = _objective(m, n, cur_bi, cur_bj, cost, x)
    emd_after[0] = current
    n_solves = 1
    steps = 0
    stop = _STOP_MAX_REMOVALS
    while steps < n_max:
        # potentials of the current optimum: dual feasible for every candidate
        _build_tree(m, n, cur_bi, cur_bj, a, b, cost, tree, link, net, pot, x)
        ua = 0.0
        for i in range(m):
            ua += a[i] * pot[i]
        any_candidate = False
        n_cand = 0
        for k in range(n):
            if removed[k] or not candidates[k]:
                continue
            any_candidate = True
            mass = 0.0
            bv = 0.0
            for j in range(n):
                if j != k and not removed[j]:
                    mass += b[j]
                    bv += b[j] * pot[m + j]
            if not mass > 0.0:
                continue
            k_list[n_cand] = k
            masses[n_cand] = mass
            bounds[n_cand] = ua + bv / mass
            n_cand += 1
        if not any_candidate:
            stop = _STOP_NO_CANDIDATE
            break
        if n_cand == 0:
            stop = _STOP_ZERO_MASS
            break
        threshold = current - tol_drop
        single = compute_single and steps == 0
        best = np.inf
        best_k = -1
        for idx in np.argsort(bounds[:n_cand], kind="mergesort"):
            k = k_list[idx]
            cutoff = np.inf if single else min(best, threshold)
            if bounds[idx] > cutoff:
                break  # the bounds ascend: no later candidate can do better
            mass = masses[idx]
            for j in range(n):
                bb[j] = 0.0 if (j == k or removed[j]) else b[j] / mass
            for e in range(try_bi.shape[0]):
                try_bi[e] = cur_bi[e]
                try_bj[e] = cur_bj[e]
            status, piv = _warm_solve(a, bb, cost, tol_c, cutoff, bland_after, try_bi, try_bj,
                                      ws)
            n_solves += 1
            n_pivots += piv
            if status == _CUT_OFF:
                continue
            if status != _OK:
                return (order[:steps].copy(), emd_after[:steps + 1].copy(), emd_single,
                        n_solves, n_pivots, stop, status)
            value = _objective(m, n, try_bi, try_bj, cost, x)
            if single:
                emd_single[k] = value
            if value < best or (value == best and k < best_k):
                best = value
                best_k = k
                for e in range(best_bi.shape[0]):
                    best_bi[e] = try_bi[e]
                    best_bj[e] = try_bj[e]
        if not (best_k >= 0 and best < threshold):
            stop = _STOP_NO_IMPROVEMENT
            break
        removed[best_k] = True
        order[steps] = best_k
        steps += 1
        emd_after[steps] = best
        current = best
        for e in range(cur_bi.shape[0]):
            cur_bi[e] = best_bi[e]
            cur_bj[e] = best_bj[e]
    return (order[:steps].copy(), emd_after[:steps + 1].copy(), emd_single, n_solves, n_pivots,
            stop, _OK)


# --------------------------------------------------------------------------- public API


@dataclass(frozen=True)
class EmdResult:
    """Result of :func:`emd`.

    Attributes
    ----------
    distance : float
        ``sum(cost * flow)``: the EMD between the two normalised mass vectors.
    flow : array, shape (Ka, Kb)
        An optimal transport plan: ``flow >= 0``, row sums the normalised ``weights_a``,
        column sums the normalised ``weights_b`` (to rounding).
    """

    distance: float
    flow: np.ndarray


@dataclass(frozen=True)
class GreedyResult:
    """Trajectory of :func:`greedy_emd`.

    Attributes
    ----------
    order : array of int64, shape (k,)
        Indices of the removed components of the variable side, in the order removed.
    emd_after : array, shape (k + 1,)
        ``emd_after[0]`` the EMD before any removal; ``emd_after[i]`` after removing
        ``order[:i]`` (remaining weights renormalised).  Strictly decreasing.
    emd_single : array, shape (Kb,)
        With ``compute_single``: EMD after removing component j alone (the first round's
        values); NaN for components that are not candidates, whose removal would leave no
        mass, when ``max_removals == 0``, and everywhere without ``compute_single``.
    stop_reason : str
        One of :data:`STOP_REASONS`.
    n_solves : int
        Transportation problems started (1 cold, the rest warm-started; those cut off early
        by their lower bound included).
    n_pivots : int
        Simplex pivots over all solves.
    """

    order: np.ndarray
    emd_after: np.ndarray
    emd_single: np.ndarray
    stop_reason: str
    n_solves: int
    n_pivots: int

    @property
    def drops(self) -> np.ndarray:
        """EMD lowered by each removal, shape (k,): ``-diff(emd_after)``, all > 0."""
        return -np.diff(self.emd_after)


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
                       "this is a bug in robot_change.change.transport: please report it with the inputs")


def emd(weights_a, weights_b, cost) -> EmdResult:
    """Exact Earth Mover's Distance between two discrete distributions.

    Parameters
    ----------
    weights_a : array, shape (Ka,)
        Masses of the first distribution, >= 0, not all zero; normalised to sum 1 here.
    weights_b : array, shape (Kb,)
        Masses of the second distribution, likewise.
    cost : array, shape (Ka, Kb)
        Finite ground distance (e.g. :func:`ground_distance`).

    Returns
    -------
    EmdResult
        ``distance`` = min over transport plans of ``sum(cost * flow)``, and one optimal
        ``flow``.

    Raises
    ------
    InputError
        Wrong shapes, empty, NaN / inf, negative or all-zero weights.
    """
    # fast path: conversions and shapes here, the value checks inside the kernel; the Python
    # checks below only run to name what is wrong
    try:
        a = np.asarray(weights_a, dtype=np.float64)
        b = np.asarray(weights_b, dtype=np.float64)
        c = np.ascontiguousarray(cost, dtype=np.float64)
    except (TypeError, ValueError):
        a = b = c = None
    if (a is None or a.ndim != 1 or b.ndim != 1 or c.shape != (a.shape[0], b.shape[0])
            or a.shape[0] == 0 or b.shape[0] == 0):
        _raise_emd_input_error(weights_a, weights_b, cost)
    if not a.flags.c_contiguous:
        a = a.copy()
    if not b.flags.c_contiguous:
        b = b.copy()
    distance, flow, status, _ = _checked_emd_kernel(a, b, c, _REL_TOL_COST)
    if status == _BAD_INPUT:
        _raise_emd_input_error(weights_a, weights_b, cost)
    if status != _OK:
        _raise_solver_failure(status, c.shape)
    return EmdResult(float(distance), flow)


def _raise_emd_input_error(weights_a, weights_b, cost) -> None:
    """The InputError :func:`emd`'s checks give for these inputs."""
    a = _check_weights(weights_a, "weights_a")
    b = _check_weights(weights_b, "weights_b")
    _check_cost(cost, a.shape[0], b.shape[0])
    raise SolverError("emd: the input checks of the kernel and of Python disagree; this is a bug "
                      "in robot_change.change.transport")


def greedy_emd(weights_fixed, weights_var, cost, candidates=None,
               max_removals: int | None = None, compute_single: bool = False) -> GreedyResult:
    """Greedy EMD: remove the components of the variable side that lower the EMD most.

    One round: for each remaining candidate j, remove it, renormalise the remaining variable
    weights, solve the EMD; the removal with the lowest EMD is recorded (ties to the smallest
    index).  Rounds repeat until no removal lowers the EMD by more than
    ``1e-12 * max|cost|``, no candidate remains, every removal would leave no mass, or
    ``max_removals`` removals were made.

    Parameters
    ----------
    weights_fixed : array, shape (Ka,)
        Masses of the side kept whole (e.g. the reference to find what appeared in the current).
    weights_var : array, shape (Kb,)
        Masses of the side components are removed from.
    cost : array, shape (Ka, Kb)
        Ground distance, rows the fixed side.
    candidates : array of bool, shape (Kb,), optional
        Components that may be removed; default all.
    max_removals : int, optional
        At most this many removals (>= 0); default Kb.
    compute_single : bool
        Also solve every candidate of the first round exactly, for
        :attr:`GreedyResult.emd_single` (slower: no candidate is cut off in that round).

    Returns
    -------
    GreedyResult
        The whole trajectory; which prefix of ``order`` is a real change is the caller's call.

    Raises
    ------
    InputError
        As :func:`emd`, and a ``candidates`` that is not a (Kb,) boolean mask or a
        ``max_removals`` that is not an integer >= 0.
    """
    a = _check_weights(weights_fixed, "weights_fixed")
    b = _check_weights(weights_var, "weights_var")
    kb = b.shape[0]
    c = _check_cost(cost, a.shape[0], kb)
    if candidates is None:
        cand = np.ones(kb, dtype=np.bool_)
    else:
        cand = np.asarray(candidates)
        if cand.dtype != np.bool_ or cand.shape != (kb,):
            raise InputError(f"candidates must be a boolean mask of shape ({kb},), "
                             f"got {cand.dtype} {cand.shape}")
        cand = np.ascontiguousarray(cand)
    if max_removals is None:
        max_removals = kb
    validate.whole("greedy_emd", "max_removals", max_removals, 0, 2**31 - 1)
    order, emd_after, single, n_solves, n_pivots, stop, status = _greedy_kernel(
        a, b, c, cand, int(max_removals), bool(compute_single), _REL_TOL_COST, -1)
    if status != _OK:
        _raise_solver_failure(status, c.shape)
    return GreedyResult(order, emd_after, single, STOP_REASONS[stop], int(n_solves),
                        int(n_pivots))


# --------------------------------------------------------------------------- ground distance


def _check_means(means, name: str) -> np.ndarray:
    try:
        mu = np.asarray(means, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric (K, 3) array: {exc}") from None
    if mu.ndim != 2 or mu.shape[0] == 0 or mu.shape[1] == 0:
        raise InputError(f"{name} must have shape (K, D) with K, D >= 1, got {mu.shape}")
    if not np.isfinite(mu).all():
        raise InputError(f"{name} contain NaN or inf")
    return mu


def _check_covariances(cov, name: str, k: int, d: int) -> np.ndarray:
    if cov is None:
        raise InputError(f'kind="wasserstein2" needs {name} of shape ({k}, {d}, {d})')
    try:
        s = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric (K, D, D) array: {exc}") from None
    if s.shape != (k, d, d):
        raise InputError(f"{name} must have shape ({k}, {d}, {d}), got {s.shape}")
    if not np.isfinite(s).all():
        raise InputError(f"{name} contain NaN or inf")
    asym = np.abs(s - s.transpose(0, 2, 1)).max(axis=(1, 2)) if k else np.zeros(0)
    scale = np.abs(s).max(axis=(1, 2))
    if (asym > 1e-9 * np.maximum(scale, 1e-300)).any():
        raise InputError(f"{name} must be symmetric; symmetrise them "
                         "(0.5 * (C + C.transpose(0, 2, 1)))")
    s = 0.5 * (s + s.transpose(0, 2, 1))
    evals = np.linalg.eigvalsh(s)
    if (evals[:, 0] < -1e-9 * np.maximum(evals[:, -1], 1e-300)).any():
        bad = np.flatnonzero(evals[:, 0] < -1e-9 * np.maximum(evals[:, -1], 1e-300)).tolist()
        raise InputError(f"{name} of components {bad} are not positive semi-definite")
    return s


def _sqrtm_psd(s: np.ndarray) -> np.ndarray:
    """Symmetric square roots of PSD matrices, shape (K, D, D), eigenvalues clipped at 0."""
    evals, evecs = np.linalg.eigh(s)
    root = np.sqrt(np.clip(evals, 0.0, None))
    return (evecs * root[:, None, :]) @ evecs.transpose(0, 2, 1)


def _bures_squared(cov_a: np.ndarray, cov_b: np.ndarray) -> np.ndarray:
    """``tr(Sa + Sb - 2 (Sa^1/2 Sb Sa^1/2)^1/2)`` for every pair, shape (Ka, Kb), >= 0.

    Exactly 0 where ``Sa == Sb`` element for element (the rounding of the formula would leave
    ~1e-16 tr S, i.e. a distance of ~1e-8 sqrt(tr S)).
    """
    root_a = _sqrtm_psd(cov_a)                                   # (Ka, D, D)
    mid = root_a[:, None] @ cov_b[None] @ root_a[:, None]        # (Ka, Kb, D, D)
    mid = 0.5 * (mid + np.swapaxes(mid, -1, -2))
    cross = np.sqrt(np.clip(np.linalg.eigvalsh(mid), 0.0, None)).sum(axis=-1)
    tr_a = np.trace(cov_a, axis1=1, axis2=2)
    tr_b = np.trace(cov_b, axis1=1, axis2=2)
    bures = np.clip(tr_a[:, None] + tr_b[None, :] - 2.0 * cross, 0.0, None)
    same = (cov_a[:, None] == cov_b[None]).all(axis=(2, 3))
    bures[same] = 0.0
    return bures


def ground_distance(means_a, means_b, covariances_a=None, covariances_b=None,
                    kind: str = "euclidean") -> np.ndarray:
    """Ground distance between the components of two mixtures.

    Parameters
    ----------
    means_a : array, shape (Ka, D)
    means_b : array, shape (Kb, D)
    covariances_a : array, shape (Ka, D, D), optional
        Symmetric positive semi-definite; needed for ``kind="wasserstein2"``.
    covariances_b : array, shape (Kb, D, D), optional
    kind : {"euclidean", "wasserstein2"}
        ``"euclidean"``: ``|mu_a - mu_b|``.  ``"wasserstein2"``: the 2-Wasserstein distance
        between the Gaussians, ``sqrt(|mu_a - mu_b|^2 + tr(Sa + Sb - 2 (Sa^1/2 Sb Sa^1/2)^1/2))``
        (symmetric square roots by eigendecomposition, tiny negative eigenvalues clipped).

    Returns
    -------
    distance : array, shape (Ka, Kb)
        Non-negative, in the unit of the means.

    Raises
    ------
    InputError
        Unknown kind, wrong shapes, NaN / inf, missing, asymmetric or indefinite covariances.
    """
    if kind not in GROUND_DISTANCES:
        raise InputError(f"kind must be one of {GROUND_DISTANCES}, got {kind!r}")
    mu_a = _check_means(means_a, "means_a")
    mu_b = _check_means(means_b, "means_b")
    if mu_a.shape[1] != mu_b.shape[1]:
        raise InputError(f"means_a and means_b must have the same dimension, got "
                         f"{mu_a.shape[1]} and {mu_b.shape[1]}")
    sq = ((mu_a[:, None, :] - mu_b[None, :, :]) ** 2).sum(axis=-1)
    if kind == "wasserstein2":
        d = mu_a.shape[1]
        cov_a = _check_covariances(covariances_a, "covariances_a", mu_a.shape[0], d)
        cov_b = _check_covariances(covariances_b, "covariances_b", mu_b.shape[0], d)
        sq = sq + _bures_squared(cov_a, cov_b)
    return np.sqrt(sq)


def mixture_emd(a, b, kind: str = "euclidean") -> float:
    """EMD between two :class:`~robot_change.mixture.model.Mixture` (weights as masses).

    Parameters
    ----------
    a, b : Mixture
    kind : {"euclidean", "wasserstein2"}
        Ground distance, see :func:`ground_distance`.

    Returns
    -------
    float
    """
    for name, mix in (("a", a), ("b", b)):
        if not isinstance(mix, Mixture):
            raise InputError(f"{name} must be a Mixture, got {type(mix).__name__}")
    cost = ground_distance(a.means, b.means, a.covariances, b.covariances, kind=kind)
    return emd(a.weights, b.weights, cost).distance
