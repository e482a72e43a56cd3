"""De-skewing a spinning lidar's scan: each point back into the lidar frame at the scan stamp.

A driver that does not de-skew reports each point in the lidar frame of its own firing time ``t_i``
(seconds relative to the scan stamp, the ``time`` channel; negative when the stamp is the sweep's end).
With the sensor moving at a constant body twist ``xi`` (vx, vy, vz m/s, wx, wy, wz rad/s, lidar frame)
over the sweep, the pose of the firing-time frame in the stamp frame is ``exp(xi t_i)``, so the point in
the stamp frame is ``exp(xi t_i) p_i`` (``pipeline.transforms.screw_apply``) and its covariance turns by
the rotation part, ``R_i C_i R_i^T``. The twist comes from the motion between two scan stamps
(``sweep_twist``): the odometry's constant-velocity guess before registration, its estimate after.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.point_times import PointTimes, classify_point_times
from fleetcal.pipeline.transforms import screw_apply, twist_of
from fleetcal.stages.registration.pointset import PointSet


def sweep_twist(T_prev_curr: NDArray[np.floating], interval_s: float) -> NDArray[np.float64] | None:
    """The constant body twist (6,) that moves the lidar by ``T_prev_curr`` (previous -> current scan
    stamp) in ``interval_s`` seconds; None when the interval is not positive and finite."""
    if not (np.isfinite(interval_s) and interval_s > 0):
        return None
    return twist_of(np.asarray(T_prev_curr, dtype=np.float64), interval_s)


def usable_times(times_s: NDArray[np.floating] | None, interval_s: float) -> bool:
    """True when ``times_s`` (point time minus stamp, s) are one sweep's firing times
    (``pipeline.point_times``, with the scan interval known), every one finite."""
    return sweep_usable(classify_point_times(times_s, interval_s), interval_s)


def sweep_usable(times: PointTimes, interval_s: float) -> bool:
    """``usable_times`` for times already classified with ``interval_s``."""
    return bool(np.isfinite(interval_s) and interval_s > 0) and times.is_sweep and times.all_finite


def deskew_points(points_xyz: NDArray[np.floating], times_s: NDArray[np.floating],
                  twist: NDArray[np.floating]) -> NDArray[np.float64]:
    """(N, 3) points from their firing-time lidar frames into the stamp's lidar frame, metres."""
    return screw_apply(twist, times_s, points_xyz)


def deskew_pointset(scan: PointSet, twist: NDArray[np.floating]) -> PointSet:
    """``scan`` with points and covariances moved into the stamp's lidar frame (descriptors, times and
    stamp kept; kd-trees rebuilt on use). ``scan.times_s`` must be set."""
    if scan.times_s is None:
        raise ValueError("deskew_pointset needs a scan with per-point times")
    points = deskew_points(scan.points_xyz, scan.times_s, twist)
    from scipy.spatial.transform import Rotation  # imported on first use: scipy.spatial is slow to import

    rotations = Rotation.from_rotvec(np.asarray(twist, dtype=np.float64)[3:][None, :] * scan.times_s[:, None])
    R = rotations.as_matrix()
    covariances = np.einsum("nij,njk,nlk->nil", R, scan.covariances, R)
    return dataclasses.replace(scan, points_xyz=np.ascontiguousarray(points), covariances=covariances)


__all__ = ["deskew_points", "deskew_pointset", "sweep_twist", "sweep_usable", "usable_times"]
