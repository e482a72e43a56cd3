"""Numba kernels for ``stages.lidar_features`` (private; call the public wrappers there).

Inputs are C-contiguous float64/int64 arrays and scalars; outputs go into preallocated arrays.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS


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
def _angular_lower_bound_m(range_m: float, angle_rad: float) -> float:
    """Least distance, metres, from a point at ``range_m`` to any point seen ``angle_rad`` away."""
    if angle_rad >= 0.5 * math.pi:
        return range_m
    return range_m * math.sin(angle_rad)


@njit(**NJIT_FLAGS)
def _azimuth_gap_limit(range_m: float, worst_d2: float, cos_min: float) -> float:
    """Azimuth gap, radians, beyond which every point is at least ``sqrt(worst_d2)`` away.

    Inverse of: angle >= 2 asin(cos_min sin(gap / 2)) and distance >= range sin(angle).
    """
    if not (worst_d2 < range_m * range_m) or cos_min <= 0.0:
        return np.inf
    angle = math.asin(math.sqrt(worst_d2) / range_m)
    s = math.sin(0.5 * angle) / cos_min
    if s >= 1.0:
        return np.inf
    return 2.0 * math.asin(s)


@njit(**NJIT_FLAGS)
def grid_neighbours(
    points_xyz: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    elevation: np.ndarray,
    azimuth: np.ndarray,
    n_rows: int,
    n_cols: int,
    k: int,
    max_half_rows: int,
    max_half_cols: int,
    angular: bool,
    sensor_xyz: np.ndarray,
    neighbours_out: np.ndarray,
    exact_out: np.ndarray,
) -> None:
    """k nearest neighbours of each point searched in a spherical range image, proven exact.

    Points are binned into cells ``(row, col)`` (row: laser ring or elevation bin, col: azimuth bin
    of width 2 pi / n_cols, wrapping around). Each point searches its own row first, then rows
    further out, and in each row the columns outward from its own; with ``angular`` a row or a
    column run is skipped once the least possible distance to anything in it (the point's range
    times the sine of the least angle to the cell, from the rows' elevation extents and the
    column's azimuth gap) reaches the current k-th distance. The search stops at ``max_half_rows``
    and ``max_half_cols``; ``exact_out[i]`` is True when the k found are then provably the k
    nearest of the whole cloud (everything outside the window is farther), else False (fewer than k
    found, or the window cap was hit: the caller recomputes those points). Without ``angular``
    (organised grids, no angles) the full window is searched and ``exact_out`` is all False.

    Args:
        points_xyz: (N, 3) float64 finite points, metres.
        rows: (N,) int64 in [0, n_rows); cols: (N,) int64 in [0, n_cols).
        elevation: (N,) float64 radians seen from the sensor; azimuth: (N,) float64 radians in
            [-pi, pi); both used only with ``angular``; cols must be floor((azimuth + pi) / width).
        k: neighbours per point.
        max_half_rows, max_half_cols: window cap, cells each side.
        angular: rows/cols are elevation/azimuth bins (enables pruning and the exactness proof).
        sensor_xyz: (3,) float64 sensor origin.
        neighbours_out: (N, k) int64 output, nearest first, ``-1`` where fewer than k were found.
        exact_out: (N,) bool output.
    """
    n = points_xyz.shape[0]
    n_cells = n_rows * n_cols
    # counting sort by cell: each column of a row is one contiguous run
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
    xs = np.empty(n)
    ys = np.empty(n)
    zs = np.empty(n)
    for a in range(n):
        i = order[a]
        xs[a] = points_xyz[i, 0]
        ys[a] = points_xyz[i, 1]
        zs[a] = points_xyz[i, 2]
    # elevation extent and smallest cosine of each row; extents of all rows beyond each row
    row_lo = np.full(n_rows, np.inf)
    row_hi = np.full(n_rows, -np.inf)
    for i in range(n):
        r = rows[i]
        row_lo[r] = min(row_lo[r], elevation[i])
        row_hi[r] = max(row_hi[r], elevation[i])
    above_lo = np.full(n_rows + 1, np.inf)  # min elevation over rows > r  (index r + 1)
    for r in range(n_rows - 1, -1, -1):
        above_lo[r] = min(above_lo[r + 1], row_lo[r])
    below_hi = np.full(n_rows + 1, -np.inf)  # max elevation over rows < r  (index r)
    for r in range(n_rows):
        below_hi[r + 1] = max(below_hi[r], row_hi[r])
    max_abs_el = 0.0
    for r in range(n_rows):
        if row_lo[r] <= row_hi[r]:
            max_abs_el = max(max_abs_el, abs(row_lo[r]), abs(row_hi[r]))
    cos_min = math.cos(min(max_abs_el, 0.5 * math.pi))
    width = 2.0 * math.pi / n_cols
    best_d = np.empty(k)
    best_a = np.empty(k, dtype=np.int64)
    whole_row = 2 * max_half_cols + 1 >= n_cols
    for a in range(n):
        i = order[a]
        for j in range(k):
            best_d[j] = np.inf
            best_a[j] = -1
        worst = np.inf
        worst_at = 0
        px = xs[a]
        py = ys[a]
        pz = zs[a]
        dxs = px - sensor_xyz[0]
        dys = py - sensor_xyz[1]
        dzs = pz - sensor_xyz[2]
        rng = math.sqrt(dxs * dxs + dys * dys + dzs * dzs)
        el = elevation[i]
        az_in_cell = azimuth[i] + math.pi - cols[i] * width  # position inside its column, [0, width)
        row0 = rows[i]
        col0 = cols[i]
        proven = angular
        for w in range(2 * max_half_rows + 1):
            off = (w + 1) // 2
            r = row0 + (off if w % 2 == 1 else -off)
            if r < 0 or r >= n_rows or row_lo[r] > row_hi[r]:
                continue
            if angular and r != row0:
                gap_el = max(0.0, row_lo[r] - el, el - row_hi[r])
                lb = _angular_lower_bound_m(rng, gap_el)
                if lb * lb >= worst:
                    continue
            base = r * n_cols
            n_steps = n_cols if whole_row else 2 * max_half_cols + 1
            go_up = True
            go_down = True
            gap_limit = _azimuth_gap_limit(rng, worst, cos_min)
            for step in range(n_steps):
                d = (step + 1) // 2
                up = step % 2 == 1
                if step > 0 and ((up and not go_up) or (not up and not go_down)):
                    continue
                if whole_row and step > 0 and 2 * d > n_cols:
                    continue
                if whole_row and step > 0 and 2 * d == n_cols and not up:
                    continue  # the opposite column, visited once
                if angular and d > 0:
                    if (step & 7) == 0:
                        gap_limit = _azimuth_gap_limit(rng, worst, cos_min)
                    gap_az = (d - 1) * width + (width - az_in_cell if up else az_in_cell)
                    if gap_az >= gap_limit:
                        if up:
                            go_up = False
                        else:
                            go_down = False
                        continue
                c = (col0 + d) % n_cols if up else (col0 - d) % n_cols
                cell = base + c
                for b in range(cell_start[cell], cell_start[cell + 1]):
                    dx = xs[b] - px
                    dy = ys[b] - py
                    dz = zs[b] - pz
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 >= worst or b == a:
                        continue
                    best_d[worst_at] = d2
                    best_a[worst_at] = b
                    worst = best_d[0]
                    worst_at = 0
                    for j in range(1, k):
                        if best_d[j] > worst:
                            worst = best_d[j]
                            worst_at = j
            if angular and not whole_row:
                # the columns past the cap in each still-open direction must be out of reach
                gap_az = max_half_cols * width + min(width - az_in_cell, az_in_cell)
                ang = 2.0 * math.asin(min(1.0, cos_min * math.sin(0.5 * min(gap_az, math.pi))))
                lb = _angular_lower_bound_m(rng, ang)
                if (go_up or go_down) and lb * lb < worst:
                    proven = False
        if proven:
            # rows past the cap, on both sides, must be out of reach
            hi_row = row0 + max_half_rows
            lo_row = row0 - max_half_rows
            if hi_row + 1 < n_rows:
                gap_el = max(0.0, above_lo[hi_row + 1] - el)
                lb = _angular_lower_bound_m(rng, gap_el)
                if lb * lb < worst:
                    proven = False
            if lo_row - 1 >= 0:
                gap_el = max(0.0, el - below_hi[lo_row])
                lb = _angular_lower_bound_m(rng, gap_el)
                if lb * lb < worst:
                    proven = False
        exact_out[i] = proven and best_a[k - 1] >= 0 and worst < np.inf
        # insertion sort of the k found, nearest first (ties: lower original index first)
        for j in range(1, k):
            dj = best_d[j]
            bj = best_a[j]
            pos = j
            while pos > 0 and (
                best_d[pos - 1] > dj
                or (best_d[pos - 1] == dj and bj >= 0 and (best_a[pos - 1] < 0 or order[best_a[pos - 1]] > order[bj]))
            ):
                best_d[pos] = best_d[pos - 1]
                best_a[pos] = best_a[pos - 1]
                pos -= 1
            best_d[pos] = dj
            best_a[pos] = bj
        for j in range(k):
            neighbours_out[i, j] = order[best_a[j]] if best_a[j] >= 0 else -1


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module on tiny inputs."""
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    nbr = np.array([[0, 1, 2], [1, 0, 2], [2, 0, 1]], dtype=np.int64)
    normal_ray_angles(pts, nbr, 2, np.zeros(3), np.empty((3, 3)), np.empty(3))
    zeros = np.zeros(3, dtype=np.int64)
    angles = np.zeros(3)
    for angular in (True, False):
        grid_neighbours(pts, zeros, zeros, angles, angles - np.pi, 1, 1, 2, 1, 1, angular, np.zeros(3),
                        np.empty((3, 2), dtype=np.int64), np.empty(3, dtype=np.bool_))  # fmt: skip
