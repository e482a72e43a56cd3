"""Numba kernels for the GICP / MC-GICP cost (eq. 3) and its Gauss-Newton linearisation.

Residual of correspondence i (source point a_i, target point b_i): d_i = b_i - (R a_i + t), with
the Mahalanobis weight W_i = (C_i^B + R C_i^A R^T)^-1. Parameters are a right perturbation
T <- T exp(delta), delta = (omega (rad, 3), v (m, 3)) in the source frame, so
dd/domega = R [a]_x and dd/dv = -R. Private kernels: contiguous arrays and scalars in.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS
from fleetcal.stages.registration.kdtree_kernels import MAX_DEPTH, nearest_one, nearest_two

FAR_MOVE_FRACTION = 0.1
"""A query that moved farther than this fraction of the maximum correspondence distance since its last
search is searched for its nearest point only (``match_linearize_kernel``)."""

ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_CAUCHY = 2


@njit(inline="always", **NJIT_FLAGS)
def robust_weight_and_cost(r2: float, kind: int, scale: float) -> tuple[float, float]:
    """(IRLS weight d rho / d r^2, rho(r^2)) for a squared Mahalanobis residual r^2."""
    if kind == ROBUST_HUBER:
        r = np.sqrt(r2)
        if r <= scale:
            return 1.0, r2
        return scale / r, 2.0 * scale * r - scale * scale
    if kind == ROBUST_CAUCHY:
        c2 = scale * scale
        return 1.0 / (1.0 + r2 / c2), c2 * np.log1p(r2 / c2)
    return 1.0, r2


@njit(**NJIT_FLAGS)
def residual_jacobian(
    a: np.ndarray, b: np.ndarray, T: np.ndarray, d_out: np.ndarray, J_out: np.ndarray
) -> None:
    """Residual d = b - (R a + t) into d_out (3,) and its Jacobian wrt delta into J_out (3, 6)."""
    for r in range(3):
        d_out[r] = b[r] - (T[r, 0] * a[0] + T[r, 1] * a[1] + T[r, 2] * a[2] + T[r, 3])
        # R [a]_x, with [a]_x = [[0, -a2, a1], [a2, 0, -a0], [-a1, a0, 0]]
        J_out[r, 0] = T[r, 1] * a[2] - T[r, 2] * a[1]
        J_out[r, 1] = -T[r, 0] * a[2] + T[r, 2] * a[0]
        J_out[r, 2] = T[r, 0] * a[1] - T[r, 1] * a[0]
        J_out[r, 3] = -T[r, 0]
        J_out[r, 4] = -T[r, 1]
        J_out[r, 5] = -T[r, 2]


@njit(inline="always", **NJIT_FLAGS)
def _accumulate(
    a: np.ndarray, C_A: np.ndarray, b: np.ndarray, C_B: np.ndarray, T: np.ndarray, robust_kind: int,
    robust_scale: float, H: np.ndarray, g: np.ndarray,
) -> float:
    """Add correspondence (a, b) to the upper triangle of H (6, 6) and to g (6,); returns its cost
    rho(d^T W d), or -1 when C_B + R C_A R^T is singular (nothing added).

    Worked in the source frame: with d' = R^T d and W' = R^T W R = (C_A + R^T C_B R)^-1, the cost is
    d'^T W' d' and J = R [[a]_x, -I] gives J^T W J = [[S^T W' S, -S^T W'], [-W' S, W']], S = [a]_x, and
    J^T W d = [e x a, -e] with e = W' d'. Scalars only (no temporaries per correspondence).
    """
    # d' = R^T (b - R a - t)
    r0 = b[0] - T[0, 3]
    r1 = b[1] - T[1, 3]
    r2_ = b[2] - T[2, 3]
    d0 = T[0, 0] * r0 + T[1, 0] * r1 + T[2, 0] * r2_ - a[0]
    d1 = T[0, 1] * r0 + T[1, 1] * r1 + T[2, 1] * r2_ - a[1]
    d2 = T[0, 2] * r0 + T[1, 2] * r1 + T[2, 2] * r2_ - a[2]
    # K = C_B R (3 x 3), M = C_A + R^T K (symmetric: upper triangle)
    k00 = C_B[0, 0] * T[0, 0] + C_B[0, 1] * T[1, 0] + C_B[0, 2] * T[2, 0]
    k01 = C_B[0, 0] * T[0, 1] + C_B[0, 1] * T[1, 1] + C_B[0, 2] * T[2, 1]
    k02 = C_B[0, 0] * T[0, 2] + C_B[0, 1] * T[1, 2] + C_B[0, 2] * T[2, 2]
    k10 = C_B[1, 0] * T[0, 0] + C_B[1, 1] * T[1, 0] + C_B[1, 2] * T[2, 0]
    k11 = C_B[1, 0] * T[0, 1] + C_B[1, 1] * T[1, 1] + C_B[1, 2] * T[2, 1]
    k12 = C_B[1, 0] * T[0, 2] + C_B[1, 1] * T[1, 2] + C_B[1, 2] * T[2, 2]
    k20 = C_B[2, 0] * T[0, 0] + C_B[2, 1] * T[1, 0] + C_B[2, 2] * T[2, 0]
    k21 = C_B[2, 0] * T[0, 1] + C_B[2, 1] * T[1, 1] + C_B[2, 2] * T[2, 1]
    k22 = C_B[2, 0] * T[0, 2] + C_B[2, 1] * T[1, 2] + C_B[2, 2] * T[2, 2]
    m00 = C_A[0, 0] + T[0, 0] * k00 + T[1, 0] * k10 + T[2, 0] * k20
    m01 = C_A[0, 1] + T[0, 0] * k01 + T[1, 0] * k11 + T[2, 0] * k21
    m02 = C_A[0, 2] + T[0, 0] * k02 + T[1, 0] * k12 + T[2, 0] * k22
    m11 = C_A[1, 1] + T[0, 1] * k01 + T[1, 1] * k11 + T[2, 1] * k21
    m12 = C_A[1, 2] + T[0, 1] * k02 + T[1, 1] * k12 + T[2, 1] * k22
    m22 = C_A[2, 2] + T[0, 2] * k02 + T[1, 2] * k12 + T[2, 2] * k22
    # W' = M^-1 by cofactors
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    det = m00 * c00 + m01 * c01 + m02 * c02
    if not (abs(det) > 1e-300):
        return -1.0
    inv = 1.0 / det
    w00 = c00 * inv
    w01 = c01 * inv
    w02 = c02 * inv
    w11 = (m00 * m22 - m02 * m02) * inv
    w12 = (m01 * m02 - m00 * m12) * inv
    w22 = (m00 * m11 - m01 * m01) * inv
    e0 = w00 * d0 + w01 * d1 + w02 * d2
    e1 = w01 * d0 + w11 * d1 + w12 * d2
    e2 = w02 * d0 + w12 * d1 + w22 * d2
    w, rho = robust_weight_and_cost(d0 * e0 + d1 * e1 + d2 * e2, robust_kind, robust_scale)
    a0, a1, a2 = a[0], a[1], a[2]
    # P = W' S, S = [a]_x with columns (0, a2, -a1), (-a2, 0, a0), (a1, -a0, 0)
    p00 = w01 * a2 - w02 * a1
    p10 = w11 * a2 - w12 * a1
    p20 = w12 * a2 - w22 * a1
    p01 = w02 * a0 - w00 * a2
    p11 = w12 * a0 - w01 * a2
    p21 = w22 * a0 - w02 * a2
    p02 = w00 * a1 - w01 * a0
    p12 = w01 * a1 - w11 * a0
    p22 = w02 * a1 - w12 * a0
    # H_rr = S^T P (S^T rows: (0, a2, -a1), (-a2, 0, a0), (a1, -a0, 0))
    H[0, 0] += w * (a2 * p10 - a1 * p20)
    H[0, 1] += w * (a2 * p11 - a1 * p21)
    H[0, 2] += w * (a2 * p12 - a1 * p22)
    H[1, 1] += w * (a0 * p21 - a2 * p01)
    H[1, 2] += w * (a0 * p22 - a2 * p02)
    H[2, 2] += w * (a1 * p02 - a0 * p12)
    # H_rt[r, c] = -P[c, r]
    H[0, 3] -= w * p00
    H[0, 4] -= w * p10
    H[0, 5] -= w * p20
    H[1, 3] -= w * p01
    H[1, 4] -= w * p11
    H[1, 5] -= w * p21
    H[2, 3] -= w * p02
    H[2, 4] -= w * p12
    H[2, 5] -= w * p22
    H[3, 3] += w * w00
    H[3, 4] += w * w01
    H[3, 5] += w * w02
    H[4, 4] += w * w11
    H[4, 5] += w * w12
    H[5, 5] += w * w22
    # g = [e x a, -e]
    g[0] += w * (e1 * a2 - e2 * a1)
    g[1] += w * (e2 * a0 - e0 * a2)
    g[2] += w * (e0 * a1 - e1 * a0)
    g[3] -= w * e0
    g[4] -= w * e1
    g[5] -= w * e2
    return rho


@njit(**NJIT_FLAGS)
def _sum_parts(
    H_parts: np.ndarray, g_parts: np.ndarray, cost_parts: np.ndarray, used_parts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(H (6, 6) symmetric, g, cost, used) summed over the chunks' upper-triangle partial sums."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    cost = 0.0
    used = 0
    for c in range(H_parts.shape[0]):
        for p in range(6):
            g[p] += g_parts[c, p]
            for q in range(p, 6):
                H[p, q] += H_parts[c, p, q]
        cost += cost_parts[c]
        used += used_parts[c]
    for p in range(6):
        for q in range(p):
            H[p, q] = H[q, p]
    return H, g, cost, used


@njit(**NJIT_FLAGS)
def fitness_kernel(
    src_points: np.ndarray, tgt_points: np.ndarray, correspondences: np.ndarray, T: np.ndarray, max_d2: float
) -> tuple[int, float]:
    """(number of correspondences whose points R a_i + t and b_j lie closer than sqrt(max_d2) in 3-D,
    the sum of their squared distances); -1 correspondences are skipped."""
    inliers = 0
    total = 0.0
    for i in range(src_points.shape[0]):
        j = correspondences[i]
        if j < 0:
            continue
        d2 = 0.0
        for r in range(3):
            e = T[r, 0] * src_points[i, 0] + T[r, 1] * src_points[i, 1] + T[r, 2] * src_points[i, 2] + T[r, 3]
            e -= tgt_points[j, r]
            d2 += e * e
        if d2 <= max_d2:
            inliers += 1
            total += d2
    return inliers, total


@njit(**NJIT_FLAGS)
def linearize_kernel(
    src_points: np.ndarray,
    src_cov: np.ndarray,
    tgt_points: np.ndarray,
    tgt_cov: np.ndarray,
    correspondences: np.ndarray,
    T: np.ndarray,
    robust_kind: int,
    robust_scale: float,
    n_chunks: int,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Accumulate H = sum w J^T W J (6, 6), g = sum w J^T W d (6,) and cost sum rho(d^T W d).

    Args:
        src_points: (N, 3) source points a_i, source frame.
        src_cov: (N, 3, 3) source covariances C^A.
        tgt_points: (M, 3) target points b_j, target frame.
        tgt_cov: (M, 3, 3) target covariances C^B.
        correspondences: (N,) int64 target index per source point, -1 for none.
        T: (4, 4) current T_target_source.
        robust_kind: ROBUST_NONE / ROBUST_HUBER / ROBUST_CAUCHY.
        robust_scale: kernel width on the Mahalanobis distance sqrt(d^T W d).
        n_chunks: number of partial sums (blocked summation). The kernel is serial and releases the
            GIL: at ~0.2 us per correspondence a prange version lost to thread start-up and, on
            the shared 2-core machine, to oversubscription (1 ms serial vs 9-35 ms with 2 threads).

    Returns:
        (H, g, cost, number of correspondences used). The Gauss-Newton step solves H delta = -g.
    """
    n = src_points.shape[0]
    H_parts = np.zeros((n_chunks, 6, 6))
    g_parts = np.zeros((n_chunks, 6))
    cost_parts = np.zeros(n_chunks)
    used_parts = np.zeros(n_chunks, dtype=np.int64)
    chunk = (n + n_chunks - 1) // n_chunks
    for c in range(n_chunks):
        Hc = H_parts[c]
        gc = g_parts[c]
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            j = correspondences[i]
            if j < 0:
                continue
            rho = _accumulate(src_points[i], src_cov[i], tgt_points[j], tgt_cov[j], T, robust_kind, robust_scale,
                              Hc, gc)
            if rho >= 0.0:
                cost_parts[c] += rho
                used_parts[c] += 1
    return _sum_parts(H_parts, g_parts, cost_parts, used_parts)


@njit(**NJIT_FLAGS)
def match_linearize_kernel(
    tree_points: np.ndarray,
    order: np.ndarray,
    leaf_of: np.ndarray,
    node_info: np.ndarray,
    node_split: np.ndarray,
    node_cell: np.ndarray,
    src_points: np.ndarray,
    src_features: np.ndarray,
    src_cov: np.ndarray,
    tgt_points: np.ndarray,
    tgt_cov: np.ndarray,
    T: np.ndarray,
    max_d2: float,
    robust_kind: int,
    robust_scale: float,
    n_chunks: int,
    searched_at: np.ndarray,
    nearest: np.ndarray,
    second: np.ndarray,
    second_dist: np.ndarray,
    correspondences: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Find each source point's correspondence at T and accumulate H, g and the cost in one pass
    (``linearize_kernel`` of those correspondences: the same sums in the same order).

    The correspondence of source point i is the target point nearest its query [R a_i + t, f_i] in the
    target's kd-tree (``kdtree_kernels``, over (M, 3 + n) points [b_j, target features]) if closer than
    sqrt(max_d2); f_i = ``src_features[i]`` (N, n), n = 0 for plain GICP. A search finds the nearest
    point b and the distance d2 of the second nearest (capped at sqrt(max_d2)). When the query has since
    moved by e and lies closer than d2 - e to b, b is still the nearest (any other point is at least
    d2 - e away), so later iterations search only the queries for which that fails, and those starting
    from the two points found last time (``kdtree_kernels.nearest_two``).

    Args:
        tree_points ... node_cell: the target tree's arrays (``KdTree.arrays``).
        searched_at: (N, 3 + n), in and out: each query where it was last searched.
        nearest: (N,) int64, in and out: tree position of the nearest point found there (-1: none).
        second: (N,) int64, in and out: tree position of the second nearest point found there (-1: none).
        second_dist: (N,), in and out: d2 of that search; negative for none yet (all -1 coming in the
            first time) and where no point was found.
        correspondences: (N,) int64, out: target row of each correspondence, -1 for none.
        Others: as ``linearize_kernel``.

    Returns:
        (H, g, cost, number of correspondences used), as ``linearize_kernel``.
    """
    n = src_points.shape[0]
    dims = tree_points.shape[1]
    n_features = dims - 3
    H_parts = np.zeros((n_chunks, 6, 6))
    g_parts = np.zeros((n_chunks, 6))
    cost_parts = np.zeros(n_chunks)
    used_parts = np.zeros(n_chunks, dtype=np.int64)
    chunk = (n + n_chunks - 1) // n_chunks
    stack_node = np.empty(MAX_DEPTH, dtype=np.int64)
    stack_d2 = np.empty(MAX_DEPTH)
    stack_off = np.empty((MAX_DEPTH, dims))
    offsets = np.empty(dims)
    query = np.empty(dims)
    far_move2 = FAR_MOVE_FRACTION**2 * max_d2
    for c in range(n_chunks):
        Hc = H_parts[c]
        gc = g_parts[c]
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            a = src_points[i]
            for r in range(3):
                query[r] = T[r, 0] * a[0] + T[r, 1] * a[1] + T[r, 2] * a[2] + T[r, 3]
            for e in range(n_features):
                query[3 + e] = src_features[i, e]
            pos = nearest[i]
            kept = False
            moved2 = 0.0
            if pos >= 0:
                for r in range(3):
                    step = query[r] - searched_at[i, r]
                    moved2 += step * step
            if second_dist[i] > 0.0:
                d2 = 0.0
                for e in range(dims):
                    diff = tree_points[pos, e] - query[e]
                    d2 += diff * diff
                kept = np.sqrt(d2) + np.sqrt(moved2) < second_dist[i]
                if kept and not d2 < max_d2:
                    pos = -1
            if kept:
                pass
            elif moved2 > far_move2:  # still moving fast: the nearest only, from the last one
                pos, d2 = nearest_one(tree_points, leaf_of, node_info, node_split, node_cell, query, max_d2,
                                      nearest[i], stack_node, stack_d2, stack_off, offsets)  # fmt: skip
                nearest[i] = pos
                second_dist[i] = -1.0
                for e in range(dims):
                    searched_at[i, e] = query[e]
            else:
                pos, d2, runner_up, second_d2 = nearest_two(tree_points, leaf_of, node_info, node_split, node_cell,
                                                            query, max_d2, nearest[i], second[i], stack_node, stack_d2,
                                                            stack_off, offsets)  # fmt: skip
                nearest[i] = pos
                second[i] = runner_up
                second_dist[i] = np.sqrt(second_d2) if pos >= 0 else -1.0
                for e in range(dims):
                    searched_at[i, e] = query[e]
            if pos < 0:
                correspondences[i] = -1
                continue
            j = order[pos]
            correspondences[i] = j
            rho = _accumulate(a, src_cov[i], tgt_points[j], tgt_cov[j], T, robust_kind, robust_scale, Hc, gc)
            if rho >= 0.0:
                cost_parts[c] += rho
                used_parts[c] += 1
    return _sum_parts(H_parts, g_parts, cost_parts, used_parts)
