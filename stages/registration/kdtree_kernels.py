"""Numba kernels of a kd-tree over (N, D) points: build, nearest neighbour within a radius, k nearest.

Each node holding more than ``leaf_size`` points is split at the middle of its points' widest extent.
The tree's points are stored reordered (``tree_points``, leaf after leaf) with ``order`` mapping a tree
position back to the input row and ``leaf_of`` giving each position's leaf. Nodes are rows of
``node_info`` (M, 5) int64: split coordinate (-1 for a leaf), left child (the right child is the next
node), first and one-past-last tree position, parent (-1 for the root). ``node_split`` (M,) holds the
split value (the left child's points are <= it, the right child's >= it) and ``node_cell`` (M, 2, D) the
node's cell, the box its ancestors' splits cut out of space (lower and upper corner, infinite outwards).
Node 0 is the root; no leaf lies deeper than ``MAX_DEPTH`` - 1 (a node that deep stays a leaf whatever
its size), which bounds the search stacks.

A search descends to the query's leaf first and visits the other side of a split only while the squared
distance from the query to the far cell (accumulated per coordinate, Arya & Mount's incremental
distance) is below the best found so far. The search for the two nearest points (``nearest_two``) can
start from known points nearby (e.g. the previous iteration's) instead: it scans their leaf and climbs,
and while the ball through the second best point found is not inside the current node's cell (points
outside the cell could be closer), it searches the node's sibling (when the ball reaches the sibling's
cell) and moves up to the parent.

Private kernels: contiguous arrays and scalars in, no validation. Use ``kdtree.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS

MAX_DEPTH = 128
"""Search stack entries; the build stops splitting at this depth."""


@njit(**NJIT_FLAGS)
def _grown(rows: np.ndarray, size: int) -> np.ndarray:
    """``rows`` (M, 5) int64 copied into a longer (size, 5) array, the new rows -1."""
    out = np.full((size, 5), -1, dtype=np.int64)
    out[: rows.shape[0]] = rows
    return out


@njit(**NJIT_FLAGS)
def _partition(work: np.ndarray, order: np.ndarray, dim: int, lo: int, hi: int, split: float) -> int:
    """Reorder rows ``lo:hi`` of ``work`` (and ``order``) so that rows with coordinate ``dim`` below
    ``split`` come first; returns the first row at or above it."""
    dims = work.shape[1]
    i, j = lo, hi - 1
    while True:
        while i <= j and work[i, dim] < split:
            i += 1
        while i <= j and work[j, dim] >= split:
            j -= 1
        if i >= j:
            return i
        for e in range(dims):
            work[i, e], work[j, e] = work[j, e], work[i, e]
        order[i], order[j] = order[j], order[i]
        i += 1
        j -= 1


@njit(**NJIT_FLAGS)
def build_kernel(
    points: np.ndarray, leaf_size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Build the tree over ``points`` (N, D) float64, N >= 1, leaves of at most ``leaf_size`` points
    (more only where they coincide or at ``MAX_DEPTH`` - 1). A node's split halves a box around its
    points (its cell within the root's bounding box) along the box's longest side; when all points fall
    on one side, the split moves to the middle of the points' extent along that side.

    Returns:
        (tree_points (N, D), order (N,) int64, leaf_of (N,) int64, node_info (M, 5) int64,
        node_split (M,) float64, node_cell (M, 2, D) float64), as the module docstring describes.
    """
    n, dims = points.shape
    order = np.arange(n)
    tree_points = points.copy()
    capacity = 2 * (2 * n // (leaf_size + 1) + 1) + 1  # grown below when the splits are uneven
    info = np.full((capacity, 5), -1, dtype=np.int64)
    split_of = np.zeros(capacity)
    boxes = np.empty((capacity, 2, dims))  # a box around each node's points (its cell within the root's box)
    info[0, 2], info[0, 3] = 0, n
    boxes[0, 0, :] = np.inf
    boxes[0, 1, :] = -np.inf
    for i in range(n):
        for c in range(dims):
            boxes[0, 0, c] = min(boxes[0, 0, c], tree_points[i, c])
            boxes[0, 1, c] = max(boxes[0, 1, c], tree_points[i, c])
    n_nodes = 1
    pending = np.empty((2 * MAX_DEPTH + 2, 2), dtype=np.int64)  # (node, depth): one per level and one more
    pending[0] = 0
    top = 1
    while top > 0:
        top -= 1
        node, depth = pending[top, 0], pending[top, 1]
        lo, hi = info[node, 2], info[node, 3]
        if hi - lo <= leaf_size or depth >= MAX_DEPTH - 1:
            continue
        dim = 0
        for c in range(1, dims):
            if boxes[node, 1, c] - boxes[node, 0, c] > boxes[node, 1, dim] - boxes[node, 0, dim]:
                dim = c
        if not boxes[node, 1, dim] > boxes[node, 0, dim]:
            continue  # all points coincide: one leaf
        split = 0.5 * (boxes[node, 0, dim] + boxes[node, 1, dim])
        mid = _partition(tree_points, order, dim, lo, hi, split)
        if mid <= lo or mid >= hi:  # all on one side: slide the split to the points' extent along dim
            first = tree_points[lo, dim]
            least, most = first, first
            for i in range(lo, hi):
                least = min(least, tree_points[i, dim])
                most = max(most, tree_points[i, dim])
            if not most > least:  # coincide along dim: shrink the box and try again
                boxes[node, 0, dim] = least
                boxes[node, 1, dim] = least
                top += 1  # the same node again
                continue
            boxes[node, 0, dim] = least
            boxes[node, 1, dim] = most
            split = 0.5 * (least + most)
            if not split > least:  # least and most are neighbouring floats
                split = most
            mid = _partition(tree_points, order, dim, lo, hi, split)  # least goes left, most right
        if n_nodes + 2 > capacity:
            capacity *= 2
            info = _grown(info, capacity)
            split_of = np.concatenate((split_of, np.zeros(capacity - split_of.shape[0])))
            boxes = np.concatenate((boxes, np.empty((capacity - boxes.shape[0], 2, dims))))
        left = n_nodes
        n_nodes += 2
        info[node, 0], info[node, 1] = dim, left
        split_of[node] = split
        info[left, 2], info[left, 3], info[left, 4] = lo, mid, node
        info[left + 1, 2], info[left + 1, 3], info[left + 1, 4] = mid, hi, node
        boxes[left] = boxes[node]
        boxes[left + 1] = boxes[node]
        boxes[left, 1, dim] = split
        boxes[left + 1, 0, dim] = split
        pending[top, 0], pending[top, 1] = left, depth + 1
        pending[top + 1, 0], pending[top + 1, 1] = left + 1, depth + 1
        top += 2
    node_info = info[:n_nodes].copy()
    node_split = split_of[:n_nodes].copy()
    node_cell = np.empty((n_nodes, 2, dims))
    node_cell[0, 0, :] = -np.inf
    node_cell[0, 1, :] = np.inf
    leaf_of = np.empty(n, dtype=np.int64)
    for node in range(n_nodes):  # children come after their parent
        dim, left = node_info[node, 0], node_info[node, 1]
        if dim < 0:
            leaf_of[node_info[node, 2] : node_info[node, 3]] = node
            continue
        node_cell[left] = node_cell[node]
        node_cell[left + 1] = node_cell[node]
        node_cell[left, 1, dim] = node_split[node]
        node_cell[left + 1, 0, dim] = node_split[node]
    return tree_points, order, leaf_of, node_info, node_split, node_cell


@njit(inline="always", **NJIT_FLAGS)
def _heap_add(knn_d2: np.ndarray, knn_pos: np.ndarray, count: int, d2: float, pos: int) -> int:
    """Add (d2, pos) to the max-heap on ``knn_d2`` of ``count`` entries (room for k): pushed while
    count < k, else it replaces the top (the caller checked d2 < top). Returns the new count."""
    k = knn_d2.shape[0]
    if count < k:
        j = count
        while j > 0:
            parent = (j - 1) >> 1
            if knn_d2[parent] >= d2:
                break
            knn_d2[j] = knn_d2[parent]
            knn_pos[j] = knn_pos[parent]
            j = parent
        knn_d2[j] = d2
        knn_pos[j] = pos
        return count + 1
    j = 0
    while True:
        child = 2 * j + 1
        if child >= k:
            break
        if child + 1 < k and knn_d2[child + 1] > knn_d2[child]:
            child += 1
        if knn_d2[child] <= d2:
            break
        knn_d2[j] = knn_d2[child]
        knn_pos[j] = knn_pos[child]
        j = child
    knn_d2[j] = d2
    knn_pos[j] = pos
    return k


@njit(inline="always", **NJIT_FLAGS)
def _search(
    tree_points: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    query: np.ndarray,
    bound_d2: float,
    knn_pos: np.ndarray,
    knn_d2: np.ndarray,
    stack_node: np.ndarray,
    stack_d2: np.ndarray,
    stack_off: np.ndarray,
    offsets: np.ndarray,
) -> None:
    """The k = len(knn_pos) tree positions nearest ``query`` (D,) into ``knn_pos`` and their squared
    distances into ``knn_d2``, as a max-heap (the farthest first, the rest in no particular order).

    Only points strictly closer than ``bound_d2`` are taken (inf: no bound); at least k must be.
    ``stack_node`` (MAX_DEPTH,), ``stack_d2`` (MAX_DEPTH,), ``stack_off`` (MAX_DEPTH, D) and ``offsets``
    (D,) are scratch space.
    """
    dims = tree_points.shape[1]
    k = knn_pos.shape[0]
    count = 0
    limit = bound_d2
    for c in range(dims):
        offsets[c] = 0.0
    node = 0
    cell_d2 = 0.0
    top = 0
    while True:
        while node_info[node, 0] >= 0:
            dim = node_info[node, 0]
            diff = query[dim] - node_split[node]
            near = node_info[node, 1]
            far = near + 1
            if diff >= 0.0:
                near, far = far, near
            far_d2 = cell_d2 - offsets[dim] * offsets[dim] + diff * diff
            if far_d2 < limit:
                stack_node[top] = far
                stack_d2[top] = far_d2
                for c in range(dims):
                    stack_off[top, c] = offsets[c]
                stack_off[top, dim] = diff
                top += 1
            node = near
        for i in range(node_info[node, 2], node_info[node, 3]):
            d2 = 0.0
            for c in range(dims):
                e = tree_points[i, c] - query[c]
                d2 += e * e
            if d2 < limit:
                count = _heap_add(knn_d2, knn_pos, count, d2, i)
                if count == k:
                    limit = knn_d2[0]
        found = False
        while top > 0:
            top -= 1
            if stack_d2[top] < limit:
                node = stack_node[top]
                cell_d2 = stack_d2[top]
                for c in range(dims):
                    offsets[c] = stack_off[top, c]
                found = True
                break
        if not found:
            return


@njit(**NJIT_FLAGS)
def _sort_pairs(d2: np.ndarray, pos: np.ndarray) -> None:
    """Sort (d2, pos) pairs by ascending d2 in place (insertion sort: k is small)."""
    for i in range(1, d2.shape[0]):
        v, p = d2[i], pos[i]
        j = i
        while j > 0 and d2[j - 1] > v:
            d2[j] = d2[j - 1]
            pos[j] = pos[j - 1]
            j -= 1
        d2[j] = v
        pos[j] = p


@njit(inline="always", **NJIT_FLAGS)
def _search_one(
    tree_points: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    query: np.ndarray,
    node: int,
    cell_d2: float,
    best: int,
    best_d2: float,
    stack_node: np.ndarray,
    stack_d2: np.ndarray,
    stack_off: np.ndarray,
    offsets: np.ndarray,
) -> tuple[int, float]:
    """``_search`` for k = 1 on scalars, in the subtree of ``node``: (tree position, squared distance)
    of the point nearest ``query`` strictly closer than ``best_d2``, or (``best``, ``best_d2``) when
    none is. ``offsets`` (D,) come in holding the query's offset from the node's cell per coordinate
    and ``cell_d2`` their sum of squares (zeros at the root)."""
    dims = tree_points.shape[1]
    top = 0
    while True:
        while node_info[node, 0] >= 0:
            dim = node_info[node, 0]
            diff = query[dim] - node_split[node]
            near = node_info[node, 1]
            far = near + 1
            if diff >= 0.0:
                near, far = far, near
            far_d2 = cell_d2 - offsets[dim] * offsets[dim] + diff * diff
            if far_d2 < best_d2:
                stack_node[top] = far
                stack_d2[top] = far_d2
                for c in range(dims):
                    stack_off[top, c] = offsets[c]
                stack_off[top, dim] = diff
                top += 1
            node = near
        for i in range(node_info[node, 2], node_info[node, 3]):
            d2 = 0.0
            for c in range(dims):
                e = tree_points[i, c] - query[c]
                d2 += e * e
            if d2 < best_d2:
                best_d2 = d2
                best = i
        found = False
        while top > 0:
            top -= 1
            if stack_d2[top] < best_d2:
                node = stack_node[top]
                cell_d2 = stack_d2[top]
                for c in range(dims):
                    offsets[c] = stack_off[top, c]
                found = True
                break
        if not found:
            return best, best_d2


@njit(inline="always", **NJIT_FLAGS)
def nearest_one(
    tree_points: np.ndarray,
    leaf_of: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    node_cell: np.ndarray,
    query: np.ndarray,
    max_d2: float,
    candidate: int,
    stack_node: np.ndarray,
    stack_d2: np.ndarray,
    stack_off: np.ndarray,
    offsets: np.ndarray,
) -> tuple[int, float]:
    """(tree position, squared distance) of the point nearest ``query`` (D,) closer than sqrt(max_d2);
    (-1, max_d2) when none is.

    ``candidate`` (a tree position, -1 for none): the search starts from its leaf and climbs (module
    docstring); without one it descends from the root.
    ``stack_node`` (MAX_DEPTH,), ``stack_d2`` (MAX_DEPTH,), ``stack_off`` (MAX_DEPTH, D) and ``offsets``
    (D,) are scratch space.
    """
    dims = tree_points.shape[1]
    if candidate < 0:
        for c in range(dims):
            offsets[c] = 0.0
        return _search_one(tree_points, node_info, node_split, query, 0, 0.0, -1, max_d2, stack_node, stack_d2,
                           stack_off, offsets)  # fmt: skip
    best = -1
    best_d2 = max_d2
    node = leaf_of[candidate]
    for i in range(node_info[node, 2], node_info[node, 3]):
        d2 = 0.0
        for c in range(dims):
            e = tree_points[i, c] - query[c]
            d2 += e * e
        if d2 < best_d2:
            best_d2 = d2
            best = i
    while True:
        inside = True
        for c in range(dims):
            gap = min(query[c] - node_cell[node, 0, c], node_cell[node, 1, c] - query[c])
            if gap < 0.0 or gap * gap < best_d2:
                inside = False
                break
        parent = node_info[node, 4]
        if inside or parent < 0:
            return best, best_d2
        sibling = node_info[parent, 1]
        if sibling == node:
            sibling += 1
        cell_d2 = 0.0
        for c in range(dims):
            off = max(node_cell[sibling, 0, c] - query[c], query[c] - node_cell[sibling, 1, c], 0.0)
            offsets[c] = off
            cell_d2 += off * off
        if cell_d2 < best_d2:
            best, best_d2 = _search_one(tree_points, node_info, node_split, query, sibling, cell_d2, best, best_d2,
                                        stack_node, stack_d2, stack_off, offsets)  # fmt: skip
        node = parent


@njit(inline="always", **NJIT_FLAGS)
def _search_two(
    tree_points: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    query: np.ndarray,
    node: int,
    cell_d2: float,
    best: int,
    best_d2: float,
    runner_up: int,
    second_d2: float,
    skip1: int,
    skip2: int,
    stack_node: np.ndarray,
    stack_d2: np.ndarray,
    stack_off: np.ndarray,
    offsets: np.ndarray,
) -> tuple[int, float, int, float]:
    """The nearest and second nearest point to ``query`` in the subtree of ``node``, given the best two
    found so far: (tree position of the nearest, its squared distance, the second's position and
    squared distance).
    Points at positions ``skip1`` and ``skip2`` (already counted) are passed over. ``offsets`` and
    ``cell_d2`` as ``_search_one``."""
    dims = tree_points.shape[1]
    top = 0
    while True:
        while node_info[node, 0] >= 0:
            dim = node_info[node, 0]
            diff = query[dim] - node_split[node]
            near = node_info[node, 1]
            far = near + 1
            if diff >= 0.0:
                near, far = far, near
            far_d2 = cell_d2 - offsets[dim] * offsets[dim] + diff * diff
            if far_d2 < second_d2:
                stack_node[top] = far
                stack_d2[top] = far_d2
                for c in range(dims):
                    stack_off[top, c] = offsets[c]
                stack_off[top, dim] = diff
                top += 1
            node = near
        for i in range(node_info[node, 2], node_info[node, 3]):
            d2 = 0.0
            for c in range(dims):
                e = tree_points[i, c] - query[c]
                d2 += e * e
            if d2 < second_d2 and i != skip1 and i != skip2:
                if d2 < best_d2:
                    runner_up, second_d2 = best, best_d2
                    best, best_d2 = i, d2
                else:
                    runner_up, second_d2 = i, d2
        found = False
        while top > 0:
            top -= 1
            if stack_d2[top] < second_d2:
                node = stack_node[top]
                cell_d2 = stack_d2[top]
                for c in range(dims):
                    offsets[c] = stack_off[top, c]
                found = True
                break
        if not found:
            return best, best_d2, runner_up, second_d2


@njit(inline="always", **NJIT_FLAGS)
def nearest_two(
    tree_points: np.ndarray,
    leaf_of: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    node_cell: np.ndarray,
    query: np.ndarray,
    max_d2: float,
    candidate: int,
    other: int,
    stack_node: np.ndarray,
    stack_d2: np.ndarray,
    stack_off: np.ndarray,
    offsets: np.ndarray,
) -> tuple[int, float, int, float]:
    """(tree position of the point nearest ``query`` (D,), its squared distance, the second nearest's
    position and squared distance), counting only points closer than sqrt(max_d2): -1 and max_d2 for a
    missing first or second.

    With known points near the query (``candidate``, ``other``: tree positions, e.g. the last search's
    two nearest; -1 for none) the search starts at the candidate's leaf and climbs while the ball
    through the second nearest found is not inside the current cell (module docstring); without, it
    descends from the root. Scratch arrays as ``_search``.
    """
    dims = tree_points.shape[1]
    for c in range(dims):
        offsets[c] = 0.0
    if candidate < 0:
        return _search_two(tree_points, node_info, node_split, query, 0, 0.0, -1, max_d2, -1, max_d2, -1, -1,
                           stack_node, stack_d2, stack_off, offsets)  # fmt: skip
    best, best_d2, runner_up, second_d2 = -1, max_d2, -1, max_d2
    for pos in (candidate, other):
        if pos < 0:
            continue
        d2 = 0.0
        for c in range(dims):
            e = tree_points[pos, c] - query[c]
            d2 += e * e
        if d2 < second_d2:
            if d2 < best_d2:
                runner_up, second_d2 = best, best_d2
                best, best_d2 = pos, d2
            else:
                runner_up, second_d2 = pos, d2
    node = leaf_of[candidate]
    for i in range(node_info[node, 2], node_info[node, 3]):
        d2 = 0.0
        for c in range(dims):
            e = tree_points[i, c] - query[c]
            d2 += e * e
        if d2 < second_d2 and i != candidate and i != other:
            if d2 < best_d2:
                runner_up, second_d2 = best, best_d2
                best, best_d2 = i, d2
            else:
                runner_up, second_d2 = i, d2
    while True:
        inside = True
        for c in range(dims):
            gap = min(query[c] - node_cell[node, 0, c], node_cell[node, 1, c] - query[c])
            if gap < 0.0 or gap * gap < second_d2:
                inside = False
                break
        parent = node_info[node, 4]
        if inside or parent < 0:
            return best, best_d2, runner_up, second_d2
        sibling = node_info[parent, 1]
        if sibling == node:
            sibling += 1
        cell_d2 = 0.0
        for c in range(dims):
            off = max(node_cell[sibling, 0, c] - query[c], query[c] - node_cell[sibling, 1, c], 0.0)
            offsets[c] = off
            cell_d2 += off * off
        if cell_d2 < second_d2:
            best, best_d2, runner_up, second_d2 = _search_two(
                tree_points, node_info, node_split, query, sibling, cell_d2, best, best_d2, runner_up, second_d2,
                candidate, other, stack_node, stack_d2, stack_off, offsets,
            )  # fmt: skip
        node = parent


@njit(**NJIT_FLAGS)
def nearest_kernel(
    tree_points: np.ndarray,
    order: np.ndarray,
    leaf_of: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    node_cell: np.ndarray,
    queries: np.ndarray,
    max_d2: float,
    index_out: np.ndarray,
    d2_out: np.ndarray,
) -> None:
    """Nearest tree point of each query (Q, D) closer than sqrt(max_d2): its input row into
    ``index_out`` (Q,) int64 (-1 for none) and its squared distance into ``d2_out`` (Q,) (inf for none)."""
    dims = tree_points.shape[1]
    stack_node = np.empty(MAX_DEPTH, dtype=np.int64)
    stack_d2 = np.empty(MAX_DEPTH)
    stack_off = np.empty((MAX_DEPTH, dims))
    offsets = np.empty(dims)
    for q in range(queries.shape[0]):
        offsets[:] = 0.0
        pos, d2 = _search_one(tree_points, node_info, node_split, queries[q], 0, 0.0, -1, max_d2, stack_node,
                              stack_d2, stack_off, offsets)  # fmt: skip
        index_out[q] = order[pos] if pos >= 0 else -1
        d2_out[q] = d2 if pos >= 0 else np.inf


@njit(**NJIT_FLAGS)
def knn_kernel(
    tree_points: np.ndarray,
    order: np.ndarray,
    leaf_of: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    node_cell: np.ndarray,
    queries: np.ndarray,
    index_out: np.ndarray,
    d2_out: np.ndarray,
) -> None:
    """The k nearest tree points of each query (Q, D), nearest first: input rows into ``index_out``
    (Q, k) int64, squared distances into ``d2_out`` (Q, k); k <= the number of tree points."""
    dims = tree_points.shape[1]
    k = index_out.shape[1]
    stack_node = np.empty(MAX_DEPTH, dtype=np.int64)
    stack_d2 = np.empty(MAX_DEPTH)
    stack_off = np.empty((MAX_DEPTH, dims))
    offsets = np.empty(dims)
    knn_pos = np.empty(k, dtype=np.int64)
    knn_d2 = np.empty(k)
    for q in range(queries.shape[0]):
        _search(tree_points, node_info, node_split, queries[q], np.inf, knn_pos, knn_d2, stack_node, stack_d2,
                stack_off, offsets)  # fmt: skip
        _sort_pairs(knn_d2, knn_pos)
        for j in range(k):
            index_out[q, j] = order[knn_pos[j]]
            d2_out[q, j] = knn_d2[j]


@njit(**NJIT_FLAGS)
def self_knn_kernel(
    tree_points: np.ndarray,
    order: np.ndarray,
    leaf_of: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    node_cell: np.ndarray,
    start: int,
    stop: int,
    index_out: np.ndarray,
) -> None:
    """The k nearest tree points of the tree points at positions ``start:stop`` (each itself included),
    in no particular order, as input rows: row ``order[i]`` of ``index_out`` (N, k) int64 for tree
    position i.

    The points are visited in tree order, so consecutive queries are neighbours: the largest distance
    from a point to its predecessor's k nearest bounds its own k-th distance, and its search takes only
    points within that bound (the result is exact; the search is shorter).
    """
    dims = tree_points.shape[1]
    k = index_out.shape[1]
    stack_node = np.empty(MAX_DEPTH, dtype=np.int64)
    stack_d2 = np.empty(MAX_DEPTH)
    stack_off = np.empty((MAX_DEPTH, dims))
    offsets = np.empty(dims)
    knn_pos = np.empty(k, dtype=np.int64)
    knn_d2 = np.empty(k)
    for i in range(start, stop):
        bound = np.inf
        if i > start:
            bound = 0.0
            for j in range(k):
                d2 = 0.0
                for c in range(dims):
                    e = tree_points[knn_pos[j], c] - tree_points[i, c]
                    d2 += e * e
                bound = max(bound, d2)
            bound = bound * (1.0 + 1e-9) + 1e-300
        _search(tree_points, node_info, node_split, tree_points[i], bound, knn_pos, knn_d2, stack_node, stack_d2,
                stack_off, offsets)  # fmt: skip
        row = order[i]
        for j in range(k):
            index_out[row, j] = order[knn_pos[j]]
