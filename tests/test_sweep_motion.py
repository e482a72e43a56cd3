"""Motion during a lidar sweep: each point moved from its own firing time to the camera stamp with the
lidar's twist from the log's /tf odometry (``workflows.calibrate._sweep_motion``)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import TransformTree, apply, from_xyz_rpy, invert
from fleetcal.stages.calibration.frame import CalibrationFrame, compensate_ego_motion
from fleetcal.workflows.ego_motion import sweep_motion as _sweep_motion

STAMP_NS = 1_700_000_000_000_000_000
SPEED_M_S = 12.0
YAW_RATE_DEG_S = 20.0


def _T_odom_lidar(t_s: float) -> NDArray[np.float64]:
    """A vehicle on a circle: constant speed along its x axis, constant yaw rate (exact pose at t)."""
    yaw = np.radians(YAW_RATE_DEG_S) * t_s
    radius = SPEED_M_S / np.radians(YAW_RATE_DEG_S)
    return from_xyz_rpy(radius * np.sin(yaw), radius * (1 - np.cos(yaw)), 0.0, 0.0, 0.0, np.degrees(yaw))


def _tree() -> TransformTree:
    tree = TransformTree()
    for t in np.arange(-0.2, 0.3, 1 / 100):  # odometry at 100 Hz around the scan
        tree.add("odom", "lidar", _T_odom_lidar(float(t)), STAMP_NS + round(t * 1e9), static=False)
    return tree


def _skewed_scan(rng: np.random.Generator) -> tuple[LidarFrame, NDArray[np.float64]]:
    """Static world points seen during a 0.1 s sweep starting at the stamp, each in the lidar frame of its
    firing time (as a driver that does not de-skew reports them), and the same points in the odom frame."""
    world = rng.uniform([-40, -40, -2], [40, 40, 5], (20_000, 3))
    times = np.sort(rng.uniform(0.0, 0.1, world.shape[0]))
    points = np.empty_like(world)
    for i, t in enumerate(times):
        points[i] = apply(invert(_T_odom_lidar(float(t))), world[i][None])[0]
    frame = LidarFrame(stamp_ns=STAMP_NS, topic="/lidar", frame_id="lidar", points_xyz=points,
                       channels={"time": times})
    return frame, world


def test_points_move_from_their_firing_time_to_the_camera_stamp() -> None:
    """Against the exact lidar pose at the camera stamp (20 ms after the sweep's end; the vehicle turns
    at 20 deg/s): per-point times and the screw motion of the sweep's twist leave under a millimetre
    (measured 1e-5 m); moving the whole scan by its stamp leaves metres (up to 2.8 m at 40 m range)."""
    frame, world = _skewed_scan(np.random.default_rng(0))
    camera_ns = STAMP_NS + 120_000_000
    sweep = _sweep_motion(_tree(), "lidar", frame, camera_ns)
    assert sweep is not None
    offsets_s, twist = sweep
    np.testing.assert_allclose(offsets_s, np.asarray(frame.channels["time"]) - 0.12, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(twist[:3]), SPEED_M_S, rtol=0.01)
    np.testing.assert_allclose(twist[3:], [0, 0, np.radians(YAW_RATE_DEG_S)], atol=1e-6)
    at_camera = apply(invert(_T_odom_lidar(0.12)), world)
    moved = compensate_ego_motion(frame.points_xyz, None, offsets_s, twist)
    T_scan = invert(_T_odom_lidar(0.12)) @ _T_odom_lidar(0.0)
    by_stamp = apply(T_scan, frame.points_xyz)
    err = np.linalg.norm(moved - at_camera, axis=1)
    err_stamp = np.linalg.norm(by_stamp - at_camera, axis=1)
    assert err.max() < 1e-3, f"largest error {err.max():.4f} m"
    assert np.percentile(err_stamp, 99) > 2.0
    calib_frame = CalibrationFrame(frame.points_xyz, np.zeros(frame.n_points), None, None,  # type: ignore[arg-type]
                                   point_time_offsets_s=offsets_s, twist_lidar=twist)
    np.testing.assert_allclose(calib_frame.points_at_camera_stamp(), moved)
    R = calib_frame.motion_rotation()
    assert R is not None
    yaw_deg = np.degrees(np.arctan2(R[1, 0], R[0, 0]))  # capture (median 0.05 s) -> camera (0.12 s): -1.4 deg
    assert yaw_deg == pytest.approx(-YAW_RATE_DEG_S * (0.12 - np.median(frame.channels["time"])), abs=0.05)


def test_times_that_are_not_a_sweep_leave_the_scan_to_its_stamp(caplog: pytest.LogCaptureFixture) -> None:
    """A time field far from the stamp (a log whose stamps were rewritten) and a field with one time for
    every point give no per-point motion; neither does a scan without the field or a log without odometry."""
    frame, _ = _skewed_scan(np.random.default_rng(1))
    tree = _tree()
    far = LidarFrame(STAMP_NS, "/lidar", "lidar", frame.points_xyz,
                     {"time": np.asarray(frame.channels["time"]) - 2.19e7})
    with caplog.at_level(logging.WARNING):
        assert _sweep_motion(tree, "lidar", far, STAMP_NS) is None
    assert "not a sweep" in caplog.text
    one_time = LidarFrame(STAMP_NS, "/lidar", "lidar", frame.points_xyz, {"time": np.zeros(frame.n_points)})
    assert _sweep_motion(tree, "lidar", one_time, STAMP_NS) is None
    no_field = LidarFrame(STAMP_NS, "/lidar", "lidar", frame.points_xyz)
    assert _sweep_motion(tree, "lidar", no_field, STAMP_NS) is None
    assert _sweep_motion(None, "lidar", frame, STAMP_NS) is None
    static = TransformTree()
    static.add("base_link", "lidar", np.eye(4), 0, static=True)
    assert _sweep_motion(static, "lidar", frame, STAMP_NS) is None
