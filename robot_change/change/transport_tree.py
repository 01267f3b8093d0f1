"""The spanning-tree basis of the transportation simplex: the least-cost start, the rooted
tree arrays of a basis, its flows and potentials, and one pivot (the exact EMD's bookkeeping,
:mod:`robot_change.change.transport_simplex`).

An (m, n) problem's basis is ``m + n - 1`` cells ``bi, bj`` (int64, shape (m + n - 1,)) forming
a spanning tree of the nodes rows ``0..m-1`` and columns ``m..m+n-1``, rooted at row 0; ``tree``
(int64, shape (8, >= m + n)) holds its rows ``_PARENT`` .. ``_STACK``, ``pot`` (m + n,) the
potentials ``u`` then ``v`` (the cost's unit), ``x`` (m + n - 1,) the flows (masses summing
to 1).  Every kernel is ``@njit(cache=True, nogil=True)`` with a plain NumPy twin in
``tests/test_emd.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Flows below ``-_TOL_FLOW`` are negative (masses sum to 1).
_TOL_FLOW = 1e-13
#: Rows of the primal simplex's tree array (:func:`_build_tree`).
_PARENT, _PRED, _THREAD, _REV, _SUCC, _LAST, _HEAD, _STACK = 0, 1, 2, 3, 4, 5, 6, 7
_ORDER = _HEAD  # the pivot's work row (the adjacency heads are only needed to build the tree)


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
    _tree_flows(m, n, a, b, tree, net, x, np.bool_(True))  # a bool, not a literal: one compile
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
