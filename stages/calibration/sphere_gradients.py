"""Lidar-feature gradients seen from the camera (GOM paper 3.3, eq. 7-8 and Algorithm 1).

The points are put on a unit sphere centred at the estimated camera position. The sphere's pole is
the camera's up axis (-y of the optical frame), so its azimuth grows with image u and its polar angle
with image v, and the gradient orientations line up with those of the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from pipeline.errors import ProcessingError
from pipeline.transforms import apply
from stages.calibration.sphere_kernels import depth_discontinuity_kernel, sphere_gradient_kernel


@dataclass
class LidarGradients:
    """Per-point lidar gradients on the camera sphere.

    Attributes:
        gx, gy: (N,) gradient along sphere azimuth (image u) and polar angle (image v).
        magnitude: (N,) the paper's gradient magnitude ``sum |dv| / k``.
        orientation: (N,) ``atan2(gy, gx)``, radians.
        sphere_uv: (N, 2) azimuth and polar angle of each point, radians.
        neighbours: (N, k) indices of the nearest neighbours on the sphere.
    """

    gx: NDArray[np.float64]
    gy: NDArray[np.float64]
    magnitude: NDArray[np.float64]
    orientation: NDArray[np.float64]
    sphere_uv: NDArray[np.float64]
    neighbours: NDArray[np.int64]


def sphere_coordinates(points_cam: NDArray[np.floating]) -> NDArray[np.float64]:
    """(N, 2) azimuth ``atan2(x, z)`` and polar angle from the up axis ``arccos(-y / r)``, radians,
    of optical-frame points (eq. 7-8 with the pole along the camera's up axis)."""
    p = np.asarray(points_cam, dtype=np.float64)
    r = np.linalg.norm(p, axis=1)
    r = np.where(r > 1e-12, r, 1e-12)
    azimuth = np.arctan2(p[:, 0], p[:, 2])
    polar = np.arccos(np.clip(-p[:, 1] / r, -1.0, 1.0))
    return np.ascontiguousarray(np.stack([azimuth, polar], axis=1))


def sphere_neighbours(sphere_uv: NDArray[np.float64], k: int = 8) -> NDArray[np.int64]:
    """(N, k) indices of each point's k nearest neighbours on the sphere (cKDTree, self excluded)."""
    n = sphere_uv.shape[0]
    if n <= k:
        raise ProcessingError(f"{n} lidar points are too few for {k} sphere neighbours")
    _, idx = cKDTree(sphere_uv).query(sphere_uv, k=k + 1, workers=-1)
    idx = np.asarray(idx, dtype=np.int64)
    own = idx[:, 0] == np.arange(n)
    out = np.where(own[:, None], idx[:, 1:], idx[:, :k])
    return np.ascontiguousarray(out)


def compute_sphere_gradients(points_xyz: NDArray[np.floating], values: NDArray[np.floating],
                             T_camera_lidar: NDArray[np.float64], k: int = 8,
                             normalise: bool = False) -> LidarGradients:
    """Gradients of a per-point lidar feature as seen from the camera at ``T_camera_lidar``.

    Args:
        points_xyz: (N, 3) points in the lidar frame, metres.
        values: (N,) feature (e.g. histogram-equalised range or intensity in [0, 1]).
        T_camera_lidar: 4x4 estimate of the extrinsic; the sphere is centred at that camera.
        k: neighbours per point (the paper uses 8).
        normalise: use unit neighbour directions instead of raw angle differences (see kernel).
    """
    pts = np.asarray(points_xyz, dtype=np.float64)
    vals = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if pts.ndim != 2 or pts.shape[1] != 3 or vals.shape[0] != pts.shape[0]:
        raise ProcessingError(f"points {pts.shape} and values {vals.shape} do not match")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(vals))):
        raise ProcessingError("lidar points or feature values contain NaN or infinity")
    sphere_uv = sphere_coordinates(apply(T_camera_lidar, pts))
    neighbours = sphere_neighbours(sphere_uv, k)
    gx, gy, mag = sphere_gradient_kernel(sphere_uv, vals, neighbours, normalise)
    return LidarGradients(gx, gy, mag, np.arctan2(gy, gx), sphere_uv, neighbours)


def depth_discontinuities(points_xyz: NDArray[np.floating], neighbours: NDArray[np.int64],
                          min_jump_m: float = 0.3, gamma: float = 0.5) -> NDArray[np.float64]:
    """Levinson & Thrun per-point weight from range jumps to the sphere neighbours (points at the
    near side of a jump of at least ``min_jump_m`` get ``jump ** gamma``, the rest 0)."""
    ranges = np.ascontiguousarray(np.linalg.norm(np.asarray(points_xyz, dtype=np.float64), axis=1))
    return np.asarray(depth_discontinuity_kernel(ranges, np.ascontiguousarray(neighbours, dtype=np.int64),
                                                 float(min_jump_m), float(gamma)))
