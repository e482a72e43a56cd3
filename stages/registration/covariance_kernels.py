"""Numba kernels for per-point model covariances (GICP eq. 4-5, MC-GICP eq. 6-10).

Private kernels: contiguous arrays and scalars in, no validation. Use ``covariances.py``.
Flags come from ``pipeline.numba_flags`` (nogil, cache, fastmath switch). The kernels are serial:
with the closed-form 3x3 eigensolver a scan of 6k points takes ~3 ms, and a ``prange`` version was
slower on the shared 2-core machine (thread start-up and oversubscription: 17 ms with 2 threads vs
2.6 ms serial, measured).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS


@njit(inline="always", **NJIT_FLAGS)
def _local_covariance(points: np.ndarray, nbrs: np.ndarray, out: np.ndarray) -> None:
    """C^L: population covariance (1/k) of the k neighbour positions, written into out (3, 3)."""
    k = nbrs.shape[0]
    mx = 0.0
    my = 0.0
    mz = 0.0
    for j in range(k):
        p = nbrs[j]
        mx += points[p, 0]
        my += points[p, 1]
        mz += points[p, 2]
    mx /= k
    my /= k
    mz /= k
    for a in range(3):
        for b in range(3):
            out[a, b] = 0.0
    for j in range(k):
        p = nbrs[j]
        dx = points[p, 0] - mx
        dy = points[p, 1] - my
        dz = points[p, 2] - mz
        out[0, 0] += dx * dx
        out[0, 1] += dx * dy
        out[0, 2] += dx * dz
        out[1, 1] += dy * dy
        out[1, 2] += dy * dz
        out[2, 2] += dz * dz
    out[0, 0] /= k
    out[0, 1] /= k
    out[0, 2] /= k
    out[1, 1] /= k
    out[1, 2] /= k
    out[2, 2] /= k
    out[1, 0] = out[0, 1]
    out[2, 0] = out[0, 2]
    out[2, 1] = out[1, 2]


@njit(inline="always", **NJIT_FLAGS)
def _eigvec_of(A: np.ndarray, lam: float) -> tuple[float, float, float]:
    """Unit eigenvector of symmetric A (3, 3) for eigenvalue lam.

    The eigenvector is orthogonal to every row of A - lam I: take the largest cross product of two rows.
    """
    r00 = A[0, 0] - lam
    r11 = A[1, 1] - lam
    r22 = A[2, 2] - lam
    # rows (r00, a01, a02), (a01, r11, a12), (a02, a12, r22)
    c0x = A[0, 1] * A[1, 2] - A[0, 2] * r11
    c0y = A[0, 2] * A[0, 1] - r00 * A[1, 2]
    c0z = r00 * r11 - A[0, 1] * A[0, 1]
    c1x = A[0, 1] * r22 - A[0, 2] * A[1, 2]
    c1y = A[0, 2] * A[0, 2] - r00 * r22
    c1z = r00 * A[1, 2] - A[0, 1] * A[0, 2]
    c2x = r11 * r22 - A[1, 2] * A[1, 2]
    c2y = A[1, 2] * A[0, 2] - A[0, 1] * r22
    c2z = A[0, 1] * A[1, 2] - r11 * A[0, 2]
    n0 = c0x * c0x + c0y * c0y + c0z * c0z
    n1 = c1x * c1x + c1y * c1y + c1z * c1z
    n2 = c2x * c2x + c2y * c2y + c2z * c2z
    if n0 >= n1 and n0 >= n2:
        s = np.sqrt(n0)
        return c0x / s, c0y / s, c0z / s
    if n1 >= n2:
        s = np.sqrt(n1)
        return c1x / s, c1y / s, c1z / s
    s = np.sqrt(n2)
    return c2x / s, c2y / s, c2z / s


@njit(inline="always", **NJIT_FLAGS)
def sym3_eigh(A: np.ndarray, vals: np.ndarray, vecs: np.ndarray) -> None:
    """Eigen-decomposition of a symmetric 3x3 matrix, like ``np.linalg.eigh``: ascending values,
    unit eigenvectors in the columns of vecs. Closed form (trigonometric eigenvalues, cross-product
    eigenvectors); falls back to LAPACK when the two largest or two smallest eigenvalues nearly
    coincide (the closed-form vectors are then ill-conditioned).
    """
    p1 = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
    q = (A[0, 0] + A[1, 1] + A[2, 2]) / 3.0
    p2 = (A[0, 0] - q) ** 2 + (A[1, 1] - q) ** 2 + (A[2, 2] - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    ok = p > 1e-300
    if ok:
        b00 = (A[0, 0] - q) / p
        b11 = (A[1, 1] - q) / p
        b22 = (A[2, 2] - q) / p
        b01 = A[0, 1] / p
        b02 = A[0, 2] / p
        b12 = A[1, 2] / p
        r = 0.5 * (
            b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
        )
        r = min(1.0, max(-1.0, r))
        phi = np.arccos(r) / 3.0
        lam_max = q + 2.0 * p * np.cos(phi)
        lam_min = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
        lam_mid = 3.0 * q - lam_max - lam_min
        gap = min(lam_max - lam_mid, lam_mid - lam_min)
        ok = gap > 1e-3 * p
    if ok:
        n0, n1, n2 = _eigvec_of(A, lam_min)
        u0, u1, u2 = _eigvec_of(A, lam_max)
        d = u0 * n0 + u1 * n1 + u2 * n2
        u0 -= d * n0
        u1 -= d * n1
        u2 -= d * n2
        s = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        u0 /= s
        u1 /= s
        u2 /= s
        vals[0] = lam_min
        vals[1] = lam_mid
        vals[2] = lam_max
        vecs[0, 0], vecs[1, 0], vecs[2, 0] = n0, n1, n2
        vecs[0, 2], vecs[1, 2], vecs[2, 2] = u0, u1, u2
        vecs[0, 1] = u1 * n2 - u2 * n1
        vecs[1, 1] = u2 * n0 - u0 * n2
        vecs[2, 1] = u0 * n1 - u1 * n0
        return
    w, v = np.linalg.eigh(A)
    for a in range(3):
        vals[a] = w[a]
        for b in range(3):
            vecs[a, b] = v[a, b]


@njit(inline="always", **NJIT_FLAGS)
def _plane_model(local: np.ndarray, epsilon: float, vals: np.ndarray, vecs: np.ndarray, out: np.ndarray) -> None:
    """out (3, 3) = U diag(1, 1, eps) U^T, U the eigenvectors of the local covariance (eq. 4-5)."""
    sym3_eigh(local, vals, vecs)
    for a in range(3):
        for b in range(3):
            out[a, b] = vecs[a, 2] * vecs[b, 2] + vecs[a, 1] * vecs[b, 1] + epsilon * vecs[a, 0] * vecs[b, 0]


@njit(**NJIT_FLAGS)
def gicp_covariances_kernel(
    points: np.ndarray, neighbors: np.ndarray, epsilon: float, out: np.ndarray
) -> None:
    """GICP plane covariances (eq. 4-5): C = U diag(1, 1, eps) U^T from the SVD of C^L.

    Args:
        points: (N, 3) float64 positions.
        neighbors: (Q, k) int64 indices into ``points`` of the k nearest neighbours of each of Q points
            (itself included; Q = N for every point).
        epsilon: variance along the normal (relative to 1 in the plane).
        out: (Q, 3, 3) float64, written.
    """
    local = np.empty((3, 3))
    vals = np.empty(3)
    vecs = np.empty((3, 3))
    for i in range(neighbors.shape[0]):
        _local_covariance(points, neighbors[i], local)
        _plane_model(local, epsilon, vals, vecs, out[i])


@njit(**NJIT_FLAGS)
def voxel_block_covariances_kernel(points: np.ndarray, keys: np.ndarray, bits: int, reach: int, rows: np.ndarray,
                                   epsilon: float, min_points: int, out: np.ndarray, sparse: np.ndarray) -> None:
    """GICP plane covariances (eq. 4-5) from the points of each point's block of voxels, ``reach`` cells
    either way along each axis (reach 1: 3 x 3 x 3 voxels).

    The points are visited in ascending key order; the blocks' keys then ascend with them, so each of the
    block's columns (x and y fixed, z ``2 reach + 1`` cells) is found by a cursor that only moves forward.

    Args:
        points: (N, 3) float64 voxel means, one per voxel, in ascending order of ``keys``.
        keys: (N,) int64 ascending voxel keys of the points (``voxel.voxel_keys``: cells packed ``bits``
            bits each, x highest, z lowest).
        reach: the block's half-width in cells.
        rows: (R,) ascending indices of the points to do.
        epsilon: variance along the normal (relative to 1 in the plane).
        min_points: a block holding fewer points is left to the caller.
        out: (N, 3, 3) float64, written at ``rows`` where ``sparse`` is False.
        sparse: (N,) bool, written at ``rows``: True where the block held fewer than ``min_points`` points.
    """
    n = points.shape[0]
    width = 2 * reach + 1
    columns = np.empty(width * width, dtype=np.int64)
    for c in range(width * width):
        columns[c] = (c // width - reach) * (np.int64(1) << (2 * bits)) + (c % width - reach) * (np.int64(1) << bits)
    cursor = np.zeros(width * width, dtype=np.int64)
    block = np.empty(width * width * width, dtype=np.int64)  # one point a voxel at most
    local = np.empty((3, 3))
    vals = np.empty(3)
    vecs = np.empty((3, 3))
    for i in rows:
        count = 0
        for c in range(width * width):
            lowest = keys[i] + columns[c] - reach
            j = cursor[c]
            while j < n and keys[j] < lowest:
                j += 1
            cursor[c] = j
            while j < n and keys[j] <= lowest + 2 * reach and count < block.shape[0]:
                block[count] = j
                count += 1
                j += 1
        sparse[i] = count < min_points
        if not sparse[i]:
            _local_covariance(points, block[:count], local)
            _plane_model(local, epsilon, vals, vecs, out[i])


@njit(**NJIT_FLAGS)
def mcgicp_covariances_kernel(
    points: np.ndarray,
    descriptors: np.ndarray,
    neighbors: np.ndarray,
    descriptor_precision: np.ndarray,
    epsilon: float,
    min_variance: float,
    out: np.ndarray,
) -> None:
    """MC-GICP covariances (eq. 6-10 and C^D), one per point.

    For query point q with neighbours L: SVD of C^L gives U and the singular values s1 >= s2 >= s3;
    neighbours are projected onto the plane, z_j = [U1 U2]^T l_j (eq. 6), so Sigma_w = diag(s1, s2).
    Kernel weights lambda_j = exp(-1/2 (d_j - d_q)^T Lambda^-1 (d_j - d_q)) (eq. 7) give the weighted
    mean and covariance Sigma_t (eq. 8-9), normalised Omega = Sigma_w^-1/2 Sigma_t Sigma_w^-1/2 (eq. 10).
    The model covariance is C = U [[Omega + eps I, 0], [0, eps]] U^T; the ``+ eps I`` floor (not in the
    paper) keeps the in-plane variance no smaller than the normal one when all neighbours but q
    differ in descriptor (Sigma_t -> 0).

    Args:
        points: (N, 3) float64 positions.
        descriptors: (N, n) float64 descriptor channels.
        neighbors: (N, k) int64 neighbour indices (itself included).
        descriptor_precision: (n, n) float64 Lambda^-1.
        epsilon: variance along the normal.
        min_variance: floor for s1, s2 (collinear or coincident neighbours).
        out: (N, 3, 3) float64, written.
    """
    n = points.shape[0]
    k = neighbors.shape[1]
    nd = descriptors.shape[1]
    local = np.empty((3, 3))
    vals = np.empty(3)
    vecs = np.empty((3, 3))
    z = np.empty((k, 2))
    lam = np.empty(k)
    diff = np.empty(nd)
    for i in range(n):
        nbrs = neighbors[i]
        _local_covariance(points, nbrs, local)
        sym3_eigh(local, vals, vecs)
        s1 = max(vals[2], min_variance)
        s2 = max(vals[1], min_variance)
        wsum = 0.0
        m1 = 0.0
        m2 = 0.0
        for j in range(k):
            p = nbrs[j]
            z[j, 0] = vecs[0, 2] * points[p, 0] + vecs[1, 2] * points[p, 1] + vecs[2, 2] * points[p, 2]
            z[j, 1] = vecs[0, 1] * points[p, 0] + vecs[1, 1] * points[p, 1] + vecs[2, 1] * points[p, 2]
            for c in range(nd):
                diff[c] = descriptors[p, c] - descriptors[i, c]
            maha = 0.0
            for c in range(nd):
                for e in range(nd):
                    maha += diff[c] * descriptor_precision[c, e] * diff[e]
            lam[j] = np.exp(-0.5 * maha)
            wsum += lam[j]
            m1 += lam[j] * z[j, 0]
            m2 += lam[j] * z[j, 1]
        m1 /= wsum
        m2 /= wsum
        t11 = 0.0
        t12 = 0.0
        t22 = 0.0
        for j in range(k):
            d1 = z[j, 0] - m1
            d2 = z[j, 1] - m2
            t11 += lam[j] * d1 * d1
            t12 += lam[j] * d1 * d2
            t22 += lam[j] * d2 * d2
        o11 = t11 / wsum / s1 + epsilon
        o12 = t12 / wsum / np.sqrt(s1 * s2)
        o22 = t22 / wsum / s2 + epsilon
        for a in range(3):
            u1a = vecs[a, 2]
            u2a = vecs[a, 1]
            na = vecs[a, 0]
            for b in range(3):
                u1b = vecs[b, 2]
                u2b = vecs[b, 1]
                out[i, a, b] = (
                    o11 * u1a * u1b
                    + o12 * (u1a * u2b + u2a * u1b)
                    + o22 * u2a * u2b
                    + epsilon * na * vecs[b, 0]
                )


@njit(**NJIT_FLAGS)
def moved_rows_kernel(
    points: np.ndarray, covariances: np.ndarray, T: np.ndarray, points_out: np.ndarray, cov_out: np.ndarray
) -> None:
    """Points and covariances moved by T (4, 4): R p + t into ``points_out`` (N, 3) and R C R^T,
    row-major, into ``cov_out`` (N, 9) (views into one array are fine)."""
    for i in range(points.shape[0]):
        for r in range(3):
            points_out[i, r] = T[r, 0] * points[i, 0] + T[r, 1] * points[i, 1] + T[r, 2] * points[i, 2] + T[r, 3]
        C = covariances[i]
        for r in range(3):
            rc0 = T[r, 0] * C[0, 0] + T[r, 1] * C[1, 0] + T[r, 2] * C[2, 0]
            rc1 = T[r, 0] * C[0, 1] + T[r, 1] * C[1, 1] + T[r, 2] * C[2, 1]
            rc2 = T[r, 0] * C[0, 2] + T[r, 1] * C[1, 2] + T[r, 2] * C[2, 2]
            for c in range(3):
                cov_out[i, 3 * r + c] = rc0 * T[c, 0] + rc1 * T[c, 1] + rc2 * T[c, 2]
