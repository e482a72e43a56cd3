"""numba kernels for lidar gradients on the camera-centred sphere (GOM paper 3.3, Algorithm 1)."""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS


@njit(**NJIT_FLAGS)
def sphere_gradient_kernel(sphere_uv: np.ndarray, values: np.ndarray,
                           neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Algorithm 1 of the paper for every point.

    Args:
        sphere_uv: (N, 2) sphere angles (azimuth, polar) in radians, aligned with image (u, v).
        values: (N,) lidar feature.
        neighbours: (N, K) int64 indices of the K nearest neighbours on the sphere (self excluded).

    Returns:
        (gx, gy, magnitude) each (N,) float64: the paper's ``g = sum dv dx / K`` (dx the angle step to the
        neighbour, radians) and ``sum |dv| / K``.
    """
    n = sphere_uv.shape[0]
    k = neighbours.shape[1]
    gx = np.zeros(n)
    gy = np.zeros(n)
    mag = np.zeros(n)
    for i in range(n):
        sx = 0.0
        sy = 0.0
        sm = 0.0
        for j in range(k):
            nb = neighbours[i, j]
            dx = sphere_uv[i, 0] - sphere_uv[nb, 0]
            dy = sphere_uv[i, 1] - sphere_uv[nb, 1]
            dv = values[i] - values[nb]
            sx += dv * dx / k
            sy += dv * dy / k
            sm += abs(dv) / k
        gx[i] = sx
        gy[i] = sy
        mag[i] = sm
    return gx, gy, mag


@njit(**NJIT_FLAGS)
def depth_discontinuity_kernel(ranges_m: np.ndarray, neighbours: np.ndarray, min_jump_m: float,
                               gamma: float) -> np.ndarray:
    """Levinson & Thrun lidar weight: ``max(r_neighbour - r_i, 0) ** gamma`` over the sphere
    neighbours, zero where the largest jump is below ``min_jump_m`` (foreground edge points)."""
    n = ranges_m.shape[0]
    out = np.zeros(n)
    for i in range(n):
        best = 0.0
        for j in range(neighbours.shape[1]):
            d = ranges_m[neighbours[i, j]] - ranges_m[i]
            if d > best:
                best = d
        if best >= min_jump_m:
            out[i] = best ** gamma
    return out


@njit(**NJIT_FLAGS)
def sphere_gradient_lsq_kernel(sphere_uv: np.ndarray, values: np.ndarray,
                               neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares gradient per point: ``g = argmin sum_j (dv_j - g . dx_j)^2`` over its K sphere
    neighbours (dx in radians), which does not lean towards the densely sampled direction the way
    Algorithm 1's ``sum dv dx`` does when rings are further apart than columns. Magnitude is the
    paper's ``sum |dv| / K``. A ridge of 0.5 % of the trace of the normal matrix keeps the fit
    defined where every neighbour lies on one line (a sparse lidar's ring): the gradient along that
    line is fitted and the unobserved component shrinks to zero instead of taking any value."""
    n = sphere_uv.shape[0]
    k = neighbours.shape[1]
    gx = np.zeros(n)
    gy = np.zeros(n)
    mag = np.zeros(n)
    for i in range(n):
        a00 = 0.0
        a01 = 0.0
        a11 = 0.0
        b0 = 0.0
        b1 = 0.0
        sm = 0.0
        for j in range(k):
            nb = neighbours[i, j]
            dx = sphere_uv[nb, 0] - sphere_uv[i, 0]
            dy = sphere_uv[nb, 1] - sphere_uv[i, 1]
            dv = values[nb] - values[i]
            a00 += dx * dx
            a01 += dx * dy
            a11 += dy * dy
            b0 += dx * dv
            b1 += dy * dv
            sm += abs(dv)
        ridge = 0.005 * (a00 + a11)
        a00 += ridge
        a11 += ridge
        det = a00 * a11 - a01 * a01
        if det > 0.0:
            gx[i] = (a11 * b0 - a01 * b1) / det
            gy[i] = (a00 * b1 - a01 * b0) / det
        mag[i] = sm / k
    return gx, gy, mag
