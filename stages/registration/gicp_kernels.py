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

ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_CAUCHY = 2


@njit(**NJIT_FLAGS)
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


@njit(**NJIT_FLAGS)
def _mahalanobis_weight(C_B: np.ndarray, C_A: np.ndarray, T: np.ndarray, W_out: np.ndarray) -> bool:
    """W = (C_B + R C_A R^T)^-1 into W_out (3, 3); False when the sum is singular."""
    M = np.empty((3, 3))
    RC = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            RC[r, c] = T[r, 0] * C_A[0, c] + T[r, 1] * C_A[1, c] + T[r, 2] * C_A[2, c]
    for r in range(3):
        for c in range(3):
            M[r, c] = C_B[r, c] + RC[r, 0] * T[c, 0] + RC[r, 1] * T[c, 1] + RC[r, 2] * T[c, 2]
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
    if not (abs(det) > 1e-300):
        return False
    inv = 1.0 / det
    W_out[0, 0] = c00 * inv
    W_out[1, 0] = c01 * inv
    W_out[2, 0] = c02 * inv
    W_out[0, 1] = (M[0, 2] * M[2, 1] - M[0, 1] * M[2, 2]) * inv
    W_out[1, 1] = (M[0, 0] * M[2, 2] - M[0, 2] * M[2, 0]) * inv
    W_out[2, 1] = (M[0, 1] * M[2, 0] - M[0, 0] * M[2, 1]) * inv
    W_out[0, 2] = (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]) * inv
    W_out[1, 2] = (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) * inv
    W_out[2, 2] = (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) * inv
    return True


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
        d = np.empty(3)
        J = np.empty((3, 6))
        W = np.empty((3, 3))
        WJ = np.empty((3, 6))
        Hc = H_parts[c]
        gc = g_parts[c]
        for i in range(c * chunk, min(n, (c + 1) * chunk)):
            j = correspondences[i]
            if j < 0:
                continue
            if not _mahalanobis_weight(tgt_cov[j], src_cov[i], T, W):
                continue
            residual_jacobian(src_points[i], tgt_points[j], T, d, J)
            Wd0 = W[0, 0] * d[0] + W[0, 1] * d[1] + W[0, 2] * d[2]
            Wd1 = W[1, 0] * d[0] + W[1, 1] * d[1] + W[1, 2] * d[2]
            Wd2 = W[2, 0] * d[0] + W[2, 1] * d[1] + W[2, 2] * d[2]
            r2 = d[0] * Wd0 + d[1] * Wd1 + d[2] * Wd2
            w, rho = robust_weight_and_cost(r2, robust_kind, robust_scale)
            cost_parts[c] += rho
            used_parts[c] += 1
            for r in range(3):
                for q in range(6):
                    WJ[r, q] = W[r, 0] * J[0, q] + W[r, 1] * J[1, q] + W[r, 2] * J[2, q]
            for p in range(6):
                gc[p] += w * (J[0, p] * Wd0 + J[1, p] * Wd1 + J[2, p] * Wd2)
                for q in range(p, 6):
                    Hc[p, q] += w * (J[0, p] * WJ[0, q] + J[1, p] * WJ[1, q] + J[2, p] * WJ[2, q])
    H = np.zeros((6, 6))
    g = np.zeros(6)
    cost = 0.0
    used = 0
    for c in range(n_chunks):
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
