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

from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.transforms import apply
from fleetcal.stages.calibration.sphere_kernels import (
    depth_discontinuity_kernel,
    sphere_gradient_kernel,
    sphere_gradient_lsq_kernel,
)


@dataclass
class LidarGradients:
    """Per-point lidar gradients on the camera sphere.

    Attributes:
        gx, gy: (N,) gradient along sphere azimuth (image u) and polar angle (image v).
        magnitude: (N,) the paper's gradient magnitude ``sum |dv| / k``.
        orientation: (N,) ``atan2(gy, gx)``, radians.
        sphere_uv: (N, 2) azimuth and polar angle of each point, radians.
        neighbours: (N, k) indices of the nearest neighbours on the sphere.
        polar_scale: the factor on the polar angles of the neighbour search (``sampling_aspect`` with
            ``neighbours_by = "sampling"``, 1 by angle); NaN where the neighbours were given, not searched.
    """

    gx: NDArray[np.float64]
    gy: NDArray[np.float64]
    magnitude: NDArray[np.float64]
    orientation: NDArray[np.float64]
    sphere_uv: NDArray[np.float64]
    neighbours: NDArray[np.int64]
    polar_scale: float = float("nan")


def sphere_coordinates(points_cam: NDArray[np.floating]) -> NDArray[np.float64]:
    """(N, 2) azimuth ``atan2(x, z)`` and polar angle from the up axis ``arccos(-y / r)``, radians,
    of optical-frame points (eq. 7-8 with the pole along the camera's up axis)."""
    p = np.asarray(points_cam, dtype=np.float64)
    r = np.linalg.norm(p, axis=1)
    r = np.where(r > 1e-12, r, 1e-12)
    azimuth = np.arctan2(p[:, 0], p[:, 2])
    polar = np.arccos(np.clip(-p[:, 1] / r, -1.0, 1.0))
    return np.ascontiguousarray(np.stack([azimuth, polar], axis=1))


def _probe_neighbours(sphere_uv: NDArray[np.float64], k: int, n_probe: int) -> tuple[
        NDArray[np.float64], NDArray[np.float64]]:
    """Distances (P, k) and offsets (P, k, 2) of the k nearest sphere neighbours (self excluded) of up
    to ``n_probe`` points drawn with a fixed seed."""
    probe = np.random.default_rng(0).choice(sphere_uv.shape[0], size=min(n_probe, sphere_uv.shape[0]), replace=False)
    dist, idx = cKDTree(sphere_uv).query(sphere_uv[probe], k=k + 1, workers=-1)
    offsets = sphere_uv[np.asarray(idx)[:, 1:]] - sphere_uv[probe][:, None, :]
    return np.asarray(dist)[:, 1:], offsets


def _column_and_ring_steps(sphere_uv: NDArray[np.float64], n_probe: int = 4000,
                           k_probe: int = 32) -> tuple[float, float]:
    """Median column spacing (distance to the nearest neighbour) and median ring spacing (per point, the
    smallest polar step to one of its ``k_probe`` neighbours lying more above / below than beside it) on
    the sphere, radians; NaN where too few points (or fewer than a quarter of the probes) tell."""
    n = sphere_uv.shape[0]
    if n <= k_probe + 1:
        return float("nan"), float("nan")
    dist, offsets = _probe_neighbours(sphere_uv, k_probe, n_probe)
    column = float(np.median(dist[:, 0]))
    d_az, d_polar = np.abs(offsets[..., 0]), np.abs(offsets[..., 1])
    vertical = np.where(d_polar > 2.0 * d_az, d_polar, np.inf).min(axis=1)
    vertical = vertical[np.isfinite(vertical)]
    if vertical.size < dist.shape[0] // 4:
        return column, float("nan")
    return column, float(np.median(vertical))


def sampling_aspect(sphere_uv: NDArray[np.float64], n_probe: int = 4000, k_probe: int = 32) -> float:
    """Ratio of the scan's column spacing to its ring spacing on the sphere, in (0, 1].

    Column spacing is the median distance to the nearest neighbour (on a spinning lidar with rings
    further apart than columns, the next column of the same ring); ring spacing is the median over
    points of the smallest polar step to a neighbour that lies more above / below than beside them. A
    32-beam lidar has rings ~1.3 deg apart and columns ~0.2-0.3 deg (0.25): its K nearest neighbours on
    the sphere all lie on the point's own ring, and the gradient across rings (horizontal edges) cannot
    be seen. Rings denser than columns already give two-dimensional neighbourhoods at K = 8 and give
    1.0 here (a symmetric estimate that stretched them instead cost the simulated street, 0.42 deg rings
    x 0.70 deg columns, 0.06 -> 6.4 deg); 1.0 also for isotropic sampling."""
    column, ring = _column_and_ring_steps(sphere_uv, n_probe, k_probe)
    if not (np.isfinite(column) and np.isfinite(ring)) or column <= 0:
        return 1.0
    return float(np.clip(column / ring, 0.05, 1.0))


def ring_spacing_rad(points_xyz: NDArray[np.floating], n_probe: int = 4000) -> float:
    """Median angle between neighbouring rings of a scan (lidar frame, metres), radians, measured on the
    lidar's own sphere (pole along its z axis, where a spinning lidar's rings are circles of constant
    polar angle): KITTI (HDL-64) 0.36 deg, nuScenes (HDL-32) 1.33 deg, PJLab 0.17 deg, a VLP-16 2.0 deg.
    For scans without rings (non-repetitive patterns) it is about the point spacing. NaN when too few
    points tell."""
    p = np.asarray(points_xyz, dtype=np.float64)
    p = p[np.all(np.isfinite(p), axis=1)]
    # optical-style axes (x right, y down, z forward) for sphere_coordinates, whose pole is -y: lidar z
    return _column_and_ring_steps(sphere_coordinates(np.column_stack([-p[:, 1], -p[:, 2], p[:, 0]])),
                                  n_probe)[1]


def cross_ring_neighbours(sphere_uv: NDArray[np.float64], k: int = 8, n_probe: int = 4000) -> float:
    """Median over points of how many of their k nearest neighbours on the sphere lie more above /
    below them than beside them (on other rings of a spinning lidar). Below 2 a gradient across the
    rings has no neighbour on one side or both: horizontal edges are invisible to Algorithm 1 there.
    Measured (k = 8, lidar sphere): KITTI 3, PJLab 4, simulator 3, nuScenes (32 beams) 1."""
    n = sphere_uv.shape[0]
    if n <= k + 1:
        return float(k)
    _, offsets = _probe_neighbours(sphere_uv, k, n_probe)
    return float(np.median((np.abs(offsets[..., 1]) > np.abs(offsets[..., 0])).sum(axis=1)))


def sphere_neighbours(sphere_uv: NDArray[np.float64], k: int = 8, polar_scale: float = 1.0) -> NDArray[np.int64]:
    """(N, k) indices of each point's k nearest neighbours on the sphere (cKDTree, self excluded), with
    polar angles multiplied by ``polar_scale`` for the search (``sampling_aspect``: neighbours as in
    the range image, from the rings above and below as well as the own ring)."""
    n = sphere_uv.shape[0]
    if n <= k:
        raise ProcessingError(f"{n} lidar points are too few for {k} sphere neighbours")
    search_uv = sphere_uv if polar_scale == 1.0 else sphere_uv * np.array([1.0, polar_scale])
    _, idx = cKDTree(search_uv).query(search_uv, k=k + 1, workers=-1)
    idx = np.asarray(idx, dtype=np.int64)
    own = idx[:, 0] == np.arange(n)
    out = np.where(own[:, None], idx[:, 1:], idx[:, :k])
    return np.ascontiguousarray(out)


def polar_scale_by(sphere_uv: NDArray[np.float64], neighbours_by: str) -> float:
    """The factor on the polar angles of a neighbour search ``by angle`` (1) or by ``sampling``
    (``sampling_aspect`` of the points on this sphere)."""
    return sampling_aspect(sphere_uv) if neighbours_by == "sampling" else 1.0


def _neighbours_by(sphere_uv: NDArray[np.float64], k: int, neighbours_by: str) -> NDArray[np.int64]:
    """``sphere_neighbours`` by ``angle`` or by ``sampling`` (polar angle scaled by ``sampling_aspect``)."""
    return sphere_neighbours(sphere_uv, k, polar_scale_by(sphere_uv, neighbours_by))


def camera_sphere_neighbours(points_xyz: NDArray[np.floating], T_camera_lidar: NDArray[np.float64],
                             k: int = 8, neighbours_by: str = "angle") -> NDArray[np.int64]:
    """(N, k) sphere neighbours of lidar points (lidar frame, metres) on the sphere centred at the camera
    of ``T_camera_lidar`` (``neighbours_by`` as in ``compute_sphere_gradients``); shared by every feature
    channel of a frame and by Levinson's depth jumps."""
    sphere_uv = sphere_coordinates(apply(T_camera_lidar, np.asarray(points_xyz, dtype=np.float64)))
    return _neighbours_by(sphere_uv, k, neighbours_by)


def compute_sphere_gradients(points_xyz: NDArray[np.floating], values: NDArray[np.floating],
                             T_camera_lidar: NDArray[np.float64], k: int = 8,
                             fit: str = "paper",
                             neighbours_by: str = "angle",
                             neighbours: NDArray[np.int64] | None = None,
                             polar_scale: float | None = None) -> LidarGradients:
    """Gradients of a per-point lidar feature as seen from the camera at ``T_camera_lidar``.

    Args:
        points_xyz: (N, 3) points in the lidar frame, metres.
        values: (N,) feature (e.g. histogram-equalised range or intensity in [0, 1]).
        T_camera_lidar: 4x4 estimate of the extrinsic; the sphere is centred at that camera.
        k: neighbours per point (the paper uses 8).
        fit: ``paper`` (Algorithm 1) or ``lsq`` (least-squares plane fit, ``sphere_gradient_lsq_kernel``).
        neighbours_by: ``angle`` (paper: nearest on the sphere) or ``sampling`` (polar angle scaled by
            ``sampling_aspect`` for the search, so sparse-ring lidars get neighbours across rings).
        neighbours: (N, k) precomputed ``camera_sphere_neighbours`` of the same points and pose (another
            feature channel's); None: searched here.
        polar_scale: where the neighbours are searched, the factor on the polar angles already measured for
            these points and pose (``LidarGradients.polar_scale`` of another feature's gradients); None: from
            ``neighbours_by`` (``polar_scale_by``).
    """
    pts = np.asarray(points_xyz, dtype=np.float64)
    vals = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if pts.ndim != 2 or pts.shape[1] != 3 or vals.shape[0] != pts.shape[0]:
        raise ProcessingError(f"points {pts.shape} and values {vals.shape} do not match")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(vals))):
        raise ProcessingError("lidar points or feature values contain NaN or infinity")
    sphere_uv = sphere_coordinates(apply(T_camera_lidar, pts))
    scale = float("nan")
    if neighbours is None:
        scale = polar_scale_by(sphere_uv, neighbours_by) if polar_scale is None else polar_scale
        neighbours = sphere_neighbours(sphere_uv, k, scale)
    elif neighbours.shape != (pts.shape[0], k):
        raise ProcessingError(f"neighbours {neighbours.shape} do not match {pts.shape[0]} points x k={k}")
    if fit == "lsq":
        gx, gy, mag = sphere_gradient_lsq_kernel(sphere_uv, vals, neighbours)
    else:
        gx, gy, mag = sphere_gradient_kernel(sphere_uv, vals, neighbours)
    return LidarGradients(gx, gy, mag, np.arctan2(gy, gx), sphere_uv, neighbours, scale)


def depth_discontinuities(points_xyz: NDArray[np.floating], neighbours: NDArray[np.int64],
                          min_jump_m: float = 0.3, gamma: float = 0.5) -> NDArray[np.float64]:
    """Levinson & Thrun per-point weight from range jumps to the sphere neighbours (points at the
    near side of a jump of at least ``min_jump_m`` get ``jump ** gamma``, the rest 0)."""
    ranges = np.ascontiguousarray(np.linalg.norm(np.asarray(points_xyz, dtype=np.float64), axis=1))
    return np.asarray(depth_discontinuity_kernel(ranges, np.ascontiguousarray(neighbours, dtype=np.int64),
                                                 float(min_jump_m), float(gamma)))


def _range_slope_along(sphere_uv: NDArray[np.float64], range_m: NDArray[np.float64],
                        neighbours: NDArray[np.int64], dir_az: NDArray[np.float64],
                        dir_polar: NDArray[np.float64], rel_tol: float = 0.05,
                        abs_tol_m: float = 0.1) -> NDArray[np.float64]:
    """(N,) slope of range (m per radian) along a sphere direction, from a least-squares plane of range
    over the neighbours on the same surface (range within ``rel_tol * r + abs_tol_m``): the step along
    an edge then stays on the surface that carries it (a line on the ground stays on the ground)."""
    d_uv = sphere_uv[neighbours] - sphere_uv[:, None, :]
    d_r = range_m[neighbours] - range_m[:, None]
    same = np.abs(d_r) <= rel_tol * range_m[:, None] + abs_tol_m
    dx, dy = d_uv[..., 0] * same, d_uv[..., 1] * same
    a00, a01, a11 = (dx * dx).sum(1), (dx * dy).sum(1), (dy * dy).sum(1)
    b0, b1 = (dx * d_r).sum(1), (dy * d_r).sum(1)
    ridge = 0.005 * (a00 + a11) + 1e-18
    a00, a11 = a00 + ridge, a11 + ridge
    det = a00 * a11 - a01 * a01
    slope_x = (a11 * b0 - a01 * b1) / det
    slope_y = (a00 * b1 - a01 * b0) / det
    return np.asarray(slope_x * dir_az + slope_y * dir_polar)


def lidar_view_gradients(raw_xyz: NDArray[np.floating], points_xyz: NDArray[np.floating],
                         values: NDArray[np.floating], T_camera_lidar: NDArray[np.float64],
                         R_motion: NDArray[np.float64] | None = None, k: int = 8,
                         fit: str = "lsq", step_rad: float = 1e-3, neighbours_by: str = "angle",
                         neighbours: NDArray[np.int64] | None = None,
                         polar_scale: float | None = None) -> LidarGradients:
    """Lidar gradients taken where the scan was captured and carried into the camera's view.

    On the camera-centred sphere (paper 3.3) a camera displaced from the lidar sees foreground and
    background points interleave at every depth edge (parallax of ``baseline / range``, much larger than
    the lidar's angular spacing), so neighbourhoods mix surfaces exactly at the edges that matter, and
    when the initial translation is off by decimetres the gradients are wrong before the search starts.
    Here neighbours and gradient come from the lidar's own sphere (its origin at capture, turned like the
    camera), where every direction holds one surface; each point's edge direction (perpendicular to its
    gradient) is then moved ``step_rad`` along that sphere, on the point's own surface (the range follows a
    plane fitted to the neighbours at similar range), both ends are taken to the camera at
    ``T_camera_lidar`` (with the ego-motion rotation ``R_motion`` between scan and camera stamp), and the
    gradient orientation is perpendicular to the edge as the camera sees it.

    Args:
        raw_xyz: (N, 3) points as captured, lidar frame, metres.
        points_xyz: (N, 3) the same points moved to the camera stamp (``compensate_ego_motion``).
        values: (N,) lidar feature.
        T_camera_lidar: 4x4 estimate of the extrinsic.
        R_motion: 3x3 rotation of the ego-motion from scan to camera stamp (None: none).
        k, fit, neighbours_by: neighbours and gradient fit (see ``compute_sphere_gradients``).
        neighbours: precomputed lidar-sphere neighbours (another channel's ``.neighbours``); None: searched.
        polar_scale: the lidar sphere's polar-angle factor for that search, already measured
            (``LidarGradients.polar_scale``); None: measured.

    Returns:
        gradients with ``gx, gy`` oriented in the camera's sphere, the paper's magnitude from the lidar's
        view, ``sphere_uv`` of the camera-centred sphere and the lidar-view ``neighbours``.
    """
    raw = np.asarray(raw_xyz, dtype=np.float64)
    pts = np.asarray(points_xyz, dtype=np.float64)
    T = np.asarray(T_camera_lidar, dtype=np.float64)
    R = T[:3, :3]
    T_turn = np.eye(4)
    T_turn[:3, :3] = R
    at_lidar = compute_sphere_gradients(raw, values, T_turn, k=k, fit=fit, neighbours_by=neighbours_by,
                                        neighbours=neighbours, polar_scale=polar_scale)
    norm = np.hypot(at_lidar.gx, at_lidar.gy)
    safe = np.where(norm > 0, norm, 1.0)
    edge_az, edge_polar = -at_lidar.gy / safe, at_lidar.gx / safe
    az = at_lidar.sphere_uv[:, 0] + step_rad * edge_az
    polar = at_lidar.sphere_uv[:, 1] + step_rad * edge_polar
    rng = np.linalg.norm(raw, axis=1)
    rng = rng + step_rad * _range_slope_along(at_lidar.sphere_uv, rng, at_lidar.neighbours, edge_az, edge_polar)
    turned = rng[:, None] * np.column_stack([np.sin(polar) * np.sin(az), -np.cos(polar),
                                             np.sin(polar) * np.cos(az)])
    step_lidar = turned @ R - raw  # back to the lidar frame: R^T q for each row q
    if R_motion is not None:
        step_lidar = step_lidar @ np.asarray(R_motion, dtype=np.float64).T
    uv = sphere_coordinates(apply(T, pts))
    uv_end = sphere_coordinates(apply(T, pts + step_lidar))
    d_az = np.angle(np.exp(1j * (uv_end[:, 0] - uv[:, 0])))
    d_polar = uv_end[:, 1] - uv[:, 1]
    d_norm = np.hypot(d_az, d_polar)
    d_safe = np.where(d_norm > 0, d_norm, 1.0)
    gx = np.where(norm > 0, d_polar / d_safe * norm, 0.0)
    gy = np.where(norm > 0, -d_az / d_safe * norm, 0.0)
    return LidarGradients(gx, gy, at_lidar.magnitude, np.arctan2(gy, gx), uv, at_lidar.neighbours,
                          at_lidar.polar_scale)

