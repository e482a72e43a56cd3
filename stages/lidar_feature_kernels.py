"""Numba kernels for ``stages.lidar_features`` (private; call the public wrappers there).

Inputs are C-contiguous float64/int64 arrays and scalars; outputs go into preallocated arrays.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.numba_flags import NJIT_FLAGS


@njit(**NJIT_FLAGS)
def smallest_eigenvector_sym3(
    a00: float, a01: float, a02: float, a11: float, a12: float, a22: float, out: np.ndarray
) -> bool:
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix, closed form.

    Eigenvalues by the trigonometric method (Smith 1961); the eigenvector is the largest cross
    product of two rows of ``A - lambda_min I``. Writes ``out`` (3,) and returns True; returns False
    (``out`` NaN) when the smallest eigenvalue is repeated (gap below 1e-6 of the spread: collinear
    or coincident neighbours, the normal is undefined) or the matrix is not finite.
    """
    out[0] = np.nan
    out[1] = np.nan
    out[2] = np.nan
    scale = max(abs(a00), abs(a11), abs(a22), abs(a01), abs(a02), abs(a12))
    if not (scale > 0.0) or not math.isfinite(scale):
        return False
    a00 /= scale
    a01 /= scale
    a02 /= scale
    a11 /= scale
    a12 /= scale
    a22 /= scale
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    b00 = a00 - q
    b11 = a11 - q
    b22 = a22 - q
    p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    if p < 1e-12:
        return False
    det_b = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02))
    r = det_b / (2.0 * p * p * p)
    r = min(1.0, max(-1.0, r))
    phi = math.acos(r) / 3.0
    lam_max = q + 2.0 * p * math.cos(phi)
    lam_min = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    lam_mid = 3.0 * q - lam_max - lam_min
    if lam_mid - lam_min < 1e-6 * (lam_max - lam_min):
        return False
    r0x = a00 - lam_min
    r0y = a01
    r0z = a02
    r1x = a01
    r1y = a11 - lam_min
    r1z = a12
    r2x = a02
    r2y = a12
    r2z = a22 - lam_min
    c0x = r0y * r1z - r0z * r1y
    c0y = r0z * r1x - r0x * r1z
    c0z = r0x * r1y - r0y * r1x
    c1x = r0y * r2z - r0z * r2y
    c1y = r0z * r2x - r0x * r2z
    c1z = r0x * r2y - r0y * r2x
    c2x = r1y * r2z - r1z * r2y
    c2y = r1z * r2x - r1x * r2z
    c2z = r1x * r2y - r1y * r2x
    n0 = c0x * c0x + c0y * c0y + c0z * c0z
    n1 = c1x * c1x + c1y * c1y + c1z * c1z
    n2 = c2x * c2x + c2y * c2y + c2z * c2z
    if n0 >= n1 and n0 >= n2:
        vx, vy, vz, nn = c0x, c0y, c0z, n0
    elif n1 >= n2:
        vx, vy, vz, nn = c1x, c1y, c1z, n1
    else:
        vx, vy, vz, nn = c2x, c2y, c2z, n2
    if not (nn > 0.0):
        return False
    inv = 1.0 / math.sqrt(nn)
    out[0] = vx * inv
    out[1] = vy * inv
    out[2] = vz * inv
    return True


@njit(**NJIT_FLAGS)
def normal_ray_angles(
    points_xyz: np.ndarray,
    neighbours: np.ndarray,
    k: int,
    sensor_xyz: np.ndarray,
    normals_out: np.ndarray,
    angles_out: np.ndarray,
) -> None:
    """Per-point PCA normal of its neighbours and the angle between that normal and the sensor ray.

    The covariance is GOM paper eq. 4, centred at the point itself:
    ``C = 1/k * sum_i (p_i - c)(p_i - c)^T`` over its k neighbours.

    Args:
        points_xyz: (N, 3) float64, finite, metres.
        neighbours: (N, m) int64 neighbour indices into ``points_xyz``, nearest first (e.g. a k-d tree
            query with m = k + 1); the point's own index and indices ``< 0`` or ``>= N`` (missing
            neighbours) are skipped, and at most ``k`` of the rest are used.
        k: neighbours per point.
        sensor_xyz: (3,) float64 sensor origin in the same frame.
        normals_out: (N, 3) float64 output, unit normals (sign arbitrary); NaN where undefined.
        angles_out: (N,) float64 output, angle in radians in [0, pi/2] between the normal line and the
            ray from the sensor to the point; NaN where the normal is undefined (fewer than 2
            neighbours, collinear neighbours) or the point sits on the sensor.
    """
    n = points_xyz.shape[0]
    m = neighbours.shape[1]
    normal = np.empty(3)
    for i in range(n):
        cx = points_xyz[i, 0]
        cy = points_xyz[i, 1]
        cz = points_xyz[i, 2]
        s00 = 0.0
        s01 = 0.0
        s02 = 0.0
        s11 = 0.0
        s12 = 0.0
        s22 = 0.0
        used = 0
        for j in range(m):
            if used == k:
                break
            idx = neighbours[i, j]
            if idx < 0 or idx >= n or idx == i:
                continue
            dx = points_xyz[idx, 0] - cx
            dy = points_xyz[idx, 1] - cy
            dz = points_xyz[idx, 2] - cz
            s00 += dx * dx
            s01 += dx * dy
            s02 += dx * dz
            s11 += dy * dy
            s12 += dy * dz
            s22 += dz * dz
            used += 1
        angles_out[i] = np.nan
        if used < 2:
            normals_out[i, 0] = np.nan
            normals_out[i, 1] = np.nan
            normals_out[i, 2] = np.nan
            continue
        w = 1.0 / used
        ok = smallest_eigenvector_sym3(s00 * w, s01 * w, s02 * w, s11 * w, s12 * w, s22 * w, normal)
        normals_out[i, 0] = normal[0]
        normals_out[i, 1] = normal[1]
        normals_out[i, 2] = normal[2]
        if not ok:
            continue
        rx = cx - sensor_xyz[0]
        ry = cy - sensor_xyz[1]
        rz = cz - sensor_xyz[2]
        rnorm = math.sqrt(rx * rx + ry * ry + rz * rz)
        if rnorm == 0.0:
            continue
        cosang = abs(normal[0] * rx + normal[1] * ry + normal[2] * rz) / rnorm
        angles_out[i] = math.acos(min(1.0, cosang))


@njit(**NJIT_FLAGS)
def grid_neighbours(
    points_xyz: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    n_rows: int,
    n_cols: int,
    k: int,
    half_rows: int,
    half_cols: int,
    max_range_jump: float,
    sensor_xyz: np.ndarray,
    neighbours_out: np.ndarray,
) -> None:
    """k nearest neighbours of each point among the points of a small range-image window.

    Points are binned into cells ``(row, col)`` (row: laser ring or elevation bin, col: azimuth bin,
    wrapping around); each point's candidates are the points of the cells within ``half_rows`` rows
    and ``half_cols`` columns of its own cell whose range (distance to the sensor) differs from the
    point's by at most ``max_range_jump`` times the point's range. The k candidates nearest in 3D
    (Euclidean) are written nearest first.

    Args:
        points_xyz: (N, 3) float64 finite points, metres.
        rows: (N,) int64 in [0, n_rows).
        cols: (N,) int64 in [0, n_cols).
        n_rows, n_cols: grid size.
        k: neighbours per point.
        half_rows, half_cols: window half sizes in cells.
        max_range_jump: relative range gate (e.g. 0.3); ``inf`` disables it.
        sensor_xyz: (3,) float64 sensor origin.
        neighbours_out: (N, k) int64 output, indices nearest first, ``-1`` where fewer than k
            candidates exist (the point itself is never listed).
    """
    n = points_xyz.shape[0]
    n_cells = n_rows * n_cols
    # counting sort by cell: every row's azimuth window is then one contiguous run (two at the wrap)
    cell_start = np.zeros(n_cells + 1, dtype=np.int64)
    for i in range(n):
        cell_start[rows[i] * n_cols + cols[i] + 1] += 1
    for c in range(n_cells):
        cell_start[c + 1] += cell_start[c]
    fill = cell_start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = rows[i] * n_cols + cols[i]
        order[fill[c]] = i
        fill[c] += 1
    xyz = np.empty((n, 3))
    ranges = np.empty(n)
    for a in range(n):
        i = order[a]
        xyz[a, 0] = points_xyz[i, 0]
        xyz[a, 1] = points_xyz[i, 1]
        xyz[a, 2] = points_xyz[i, 2]
        dx = points_xyz[i, 0] - sensor_xyz[0]
        dy = points_xyz[i, 1] - sensor_xyz[1]
        dz = points_xyz[i, 2] - sensor_xyz[2]
        ranges[a] = math.sqrt(dx * dx + dy * dy + dz * dz)
    best_d = np.empty(k)
    best_a = np.empty(k, dtype=np.int64)
    seg_lo = np.empty(2, dtype=np.int64)
    seg_hi = np.empty(2, dtype=np.int64)
    for a in range(n):
        i = order[a]
        for j in range(k):
            best_d[j] = np.inf
            best_a[j] = -1
        px = xyz[a, 0]
        py = xyz[a, 1]
        pz = xyz[a, 2]
        ra = ranges[a]
        gate = max_range_jump * ra
        col = cols[i]
        r_lo = max(0, rows[i] - half_rows)
        r_hi = min(n_rows - 1, rows[i] + half_rows)
        for r in range(r_lo, r_hi + 1):
            base = r * n_cols
            n_seg = 1
            if 2 * half_cols + 1 >= n_cols:
                seg_lo[0] = cell_start[base]
                seg_hi[0] = cell_start[base + n_cols]
            else:
                c0 = col - half_cols
                c1 = col + half_cols
                if c0 < 0:
                    seg_lo[0] = cell_start[base]
                    seg_hi[0] = cell_start[base + c1 + 1]
                    seg_lo[1] = cell_start[base + n_cols + c0]
                    seg_hi[1] = cell_start[base + n_cols]
                    n_seg = 2
                elif c1 >= n_cols:
                    seg_lo[0] = cell_start[base + c0]
                    seg_hi[0] = cell_start[base + n_cols]
                    seg_lo[1] = cell_start[base]
                    seg_hi[1] = cell_start[base + c1 - n_cols + 1]
                    n_seg = 2
                else:
                    seg_lo[0] = cell_start[base + c0]
                    seg_hi[0] = cell_start[base + c1 + 1]
            for g in range(n_seg):
                for b in range(seg_lo[g], seg_hi[g]):
                    if b == a or abs(ranges[b] - ra) > gate:
                        continue
                    dx = xyz[b, 0] - px
                    dy = xyz[b, 1] - py
                    dz = xyz[b, 2] - pz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 >= best_d[k - 1]:
                        continue
                    pos = k - 1
                    while pos > 0 and best_d[pos - 1] > d2:
                        best_d[pos] = best_d[pos - 1]
                        best_a[pos] = best_a[pos - 1]
                        pos -= 1
                    best_d[pos] = d2
                    best_a[pos] = b
        for j in range(k):
            neighbours_out[i, j] = order[best_a[j]] if best_a[j] >= 0 else -1


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module on tiny inputs."""
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    nbr = np.array([[0, 1, 2], [1, 0, 2], [2, 0, 1]], dtype=np.int64)
    normal_ray_angles(pts, nbr, 2, np.zeros(3), np.empty((3, 3)), np.empty(3))
    zeros = np.zeros(3, dtype=np.int64)
    grid_neighbours(pts, zeros, zeros, 1, 1, 2, 1, 1, np.inf, np.zeros(3), np.empty((3, 2), dtype=np.int64))
