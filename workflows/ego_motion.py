"""Ego-motion between a lidar scan and a camera image, from the log's odometry on ``/tf``.

A scan's points are in the lidar frame at its stamp (or, for a driver that does not de-skew, at each
point's firing time: the ``time`` channel). A camera image is taken at its own stamp. Projecting the scan
into the image needs the points in the lidar frame at the image's stamp: the whole scan moved by the
odometry between the two stamps, or each point by the sweep's twist over its own time offset.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import TransformError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.point_times import PointTimes, classify_point_times
from fleetcal.pipeline.transforms import Mat4, TransformTree, invert, root_of, twist_of
from fleetcal.stages.calibration.frame import compensate_ego_motion

log = logging.getLogger(__name__)

def scan_motion(tree: TransformTree | None, lidar_frame: str, scan_ns: int, camera_ns: int) -> Mat4 | None:
    """``T_lidar(camera stamp)_lidar(scan stamp)`` from the tf tree's odometry, or None without it."""
    if tree is None or scan_ns == camera_ns or not has_odometry(tree, lidar_frame):
        return None
    world = root_of(tree, lidar_frame)
    try:
        T_world_scan = tree.lookup(world, lidar_frame, scan_ns)
        T_world_cam = tree.lookup(world, lidar_frame, camera_ns)
    except TransformError as err:
        log.warning("no ego-motion compensation for the scan at %d: %s", scan_ns, err)
        return None
    return invert(T_world_cam) @ T_world_scan


def sweep_motion(
    tree: TransformTree | None, lidar_frame: str, lidar: LidarFrame, camera_ns: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """Per-point capture time minus the camera stamp (N,), s, and the lidar's twist over the sweep (6,):
    velocity (m/s) and angular rate (rad/s) in the lidar frame, from the tf tree's odometry between the
    scan's first and last point times. None unless the scan's times are a sweep's
    (``pipeline.point_times``; NaN times count as the sweep's middle), or without odometry."""
    timed = _point_times(lidar) if tree is not None else None
    if timed is None:
        return None
    t, classified = timed
    if classified.kind == "foreign":
        log.warning("scan at %d: per-point times %.3f..%.3f s from its stamp are not a sweep; the scan moves "
                    "by its stamp", lidar.stamp_ns, classified.first_s, classified.last_s)
    if not classified.is_sweep:
        return None
    t_first, t_last = classified.first_s, classified.last_s
    # the sweep's motion T_lidar(first)_lidar(last): scan_motion from the last point time to the first
    T_first_last = scan_motion(tree, lidar_frame, lidar.stamp_ns + round(t_last * 1e9),
                               lidar.stamp_ns + round(t_first * 1e9))
    if T_first_last is None:
        return None
    return _sweep_offsets(t, classified, lidar.stamp_ns, camera_ns), twist_of(T_first_last, t_last - t_first)


def camera_twist(tree: TransformTree | None, lidar_frame: str, camera_ns: int,
                 half_window_ns: int = 25_000_000) -> NDArray[np.float64] | None:
    """The lidar's twist (6,) about ``camera_ns``: velocity (m/s) and angular rate (rad/s) in the lidar frame,
    from the tf tree's odometry over +-``half_window_ns``, cut to where the odometry was recorded; None without
    odometry over at least a millisecond there."""
    if tree is None or not has_odometry(tree, lidar_frame):
        return None
    world = root_of(tree, lidar_frame)
    span = tree.recorded_span(world, lidar_frame)
    if span is None:
        return None
    before, after = max(camera_ns - half_window_ns, span[0]), min(camera_ns + half_window_ns, span[1])
    if after - before < 1_000_000:
        return None
    T_before_after = scan_motion(tree, lidar_frame, after, before)
    return None if T_before_after is None else twist_of(T_before_after, (after - before) * 1e-9)


def _point_times(lidar: LidarFrame) -> tuple[NDArray[np.float64], PointTimes] | None:
    """The scan's per-point times (N,), s from its stamp, and their classification; None without a ``time``
    channel of one value per point."""
    times = lidar.channel("time")
    if times is None or lidar.n_points == 0:
        return None
    t = np.asarray(times, dtype=np.float64).ravel()
    return (t, classify_point_times(t)) if t.shape[0] == lidar.n_points else None


def _sweep_offsets(t: NDArray[np.float64], sweep: PointTimes, stamp_ns: int, camera_ns: int) -> NDArray[np.float64]:
    """Per-point capture time minus the camera stamp (N,), s, of a sweep's times ``t`` (s from the scan stamp
    ``stamp_ns``; NaN times count as the sweep's middle)."""
    return np.where(np.isfinite(t), t, 0.5 * (sweep.first_s + sweep.last_s)) + (stamp_ns - camera_ns) * 1e-9


def has_odometry(tree: TransformTree | None, lidar_frame: str) -> bool:
    """Whether the tf tree moves ``lidar_frame`` over time (odometry on ``/tf``)."""
    if tree is None:
        return False
    world = root_of(tree, lidar_frame)
    return world != lidar_frame and not tree.is_static_path(world, lidar_frame)


def twist_motion(lidar: LidarFrame, camera_ns: int, twist: NDArray[np.float64], point_times: bool = True) -> tuple[
        NDArray[np.float64], NDArray[np.float64]]:
    """Per-point time offsets to the camera stamp (N,), s, for a known lidar ``twist``: each point's own
    capture time where ``point_times`` and the scan carries a sweep's times (``pipeline.point_times``), else
    the scan stamp's; with the twist, the arguments of ``compensate_ego_motion``."""
    timed = _point_times(lidar) if point_times else None
    if timed is not None and timed[1].is_sweep:
        return _sweep_offsets(*timed, lidar.stamp_ns, camera_ns), twist
    return np.full(lidar.n_points, (lidar.stamp_ns - camera_ns) * 1e-9), twist


def points_at(tree: TransformTree | None, lidar: LidarFrame, camera_ns: int,
              point_times: bool = True) -> NDArray[np.float64] | None:
    """The scan's points (N, 3) in the lidar frame at ``camera_ns``, metres: each point moved by the sweep's
    twist over its own time offset (``point_times`` and a usable ``time`` channel), else the whole scan
    by the odometry between the stamps. None when the log has no odometry for it (nothing to move by)."""
    frame_id = lidar.frame_id.lstrip("/")
    sweep = sweep_motion(tree, frame_id, lidar, camera_ns) if point_times else None
    if sweep is not None:
        return compensate_ego_motion(lidar.points_xyz, point_time_offsets_s=sweep[0], twist_lidar=sweep[1])
    T_motion = scan_motion(tree, frame_id, lidar.stamp_ns, camera_ns)
    if T_motion is None:
        return None
    return compensate_ego_motion(lidar.points_xyz, T_lidar_motion=T_motion)


__all__ = ["camera_twist", "has_odometry", "points_at", "scan_motion", "sweep_motion", "twist_motion"]
