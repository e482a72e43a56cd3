"""De-skewing scans for mapping (``stages.registration.deskew`` and ``run_odometry(deskew=...)``): exact
recovery under a known twist, per-voxel times, and a simulated street driven at 15 m/s whose lidar does
not de-skew."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import apply, invert, screw_apply, twist_of
from fleetcal.readers.decode.pointcloud2 import decode_pointcloud2
from fleetcal.readers.open import open_log
from fleetcal.stages.registration import RegistrationConfig
from fleetcal.stages.registration.deskew import deskew_points, deskew_pointset, sweep_twist, usable_times
from fleetcal.stages.registration.odometry import VoxelMap, relative_translation_drift, run_odometry
from fleetcal.stages.registration.pointset import prepare_pointset
from fleetcal.workflows.simulator.truth import load_truth, truth_path_for
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

Sequences = dict[str, tuple[list[LidarFrame], list[NDArray[np.float64]]]]
TWIST = np.array([12.0, 0.5, 0.0, 0.02, -0.01, 0.35])  # m/s and rad/s, lidar frame


def _fired(points_stamp: NDArray[np.float64], times_s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points given in the stamp's lidar frame, expressed in the lidar frame of their firing times."""
    out = np.empty_like(points_stamp)
    for i, (p, t) in enumerate(zip(points_stamp, times_s, strict=True)):
        T_stamp_fired = np.eye(4)
        T_stamp_fired[:3, :3] = Rotation.from_rotvec(TWIST[3:] * t).as_matrix()
        T_stamp_fired[:3, 3] = screw_apply(TWIST, np.array([t]), np.zeros((1, 3)))[0]
        out[i] = apply(invert(T_stamp_fired), p[None])[0]
    return out


def test_deskew_recovers_the_stamp_frame_points_for_sweeps_stamped_at_start_or_end() -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform([-30, -30, -2], [30, 30, 4], (500, 3))
    for times in (rng.uniform(0.0, 0.1, 500), rng.uniform(-0.1, 0.0, 500)):
        fired = _fired(points, times)
        assert np.abs(fired - points).max() > 0.5  # 12 m/s over up to 0.1 s: a real skew
        np.testing.assert_allclose(deskew_points(fired, times, TWIST), points, atol=1e-9)


def test_sweep_twist_inverts_the_motion_between_stamps() -> None:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(TWIST[3:] * 0.1).as_matrix()
    T[:3, 3] = screw_apply(TWIST, np.array([0.1]), np.zeros((1, 3)))[0]
    np.testing.assert_allclose(sweep_twist(T, 0.1), TWIST, atol=1e-9)
    np.testing.assert_allclose(twist_of(T, 0.1), TWIST, atol=1e-9)
    assert sweep_twist(T, 0.0) is None and sweep_twist(T, float("nan")) is None


def test_usable_times_accepts_one_sweep_only() -> None:
    sweep = np.linspace(0.0, 0.099, 100)
    assert usable_times(sweep, 0.1)
    assert usable_times(sweep - 0.099, 0.1)  # stamped at the sweep's end
    assert not usable_times(np.zeros(100), 0.1)  # de-skewed already (times zeroed)
    assert not usable_times(sweep + np.r_[np.zeros(99), 5.0], 0.1)  # spans 50 intervals
    assert not usable_times(sweep - 21_933_112.3, 0.1)  # a sweep's span, another clock (PJLab rig1)
    assert not usable_times(np.r_[sweep[:-1], np.nan], 0.1)
    assert not usable_times(sweep, 0.0) and not usable_times(None, 0.1)


def test_pointset_keeps_voxel_mean_times_and_deskew_turns_covariances() -> None:
    rng = np.random.default_rng(4)
    xy = rng.uniform(-5, 5, (4000, 2))
    points = np.c_[xy, np.zeros(len(xy))]  # a floor: normal +z
    times = (xy[:, 0] + 5) / 100  # 0..0.1 s across x
    times_with_nan = times.copy()
    points_with_nan = points.copy()
    points_with_nan[:10] = np.nan
    times_with_nan[:10] = np.nan  # no time where there is no point: still usable
    cfg = RegistrationConfig(voxel_size_m=0.5, k_neighbors=10)
    scan = prepare_pointset(points_with_nan, None, cfg, times_s=times_with_nan)
    assert scan.times_s is not None and scan.times_s.shape == (scan.n_points,)
    # each voxel's time is its points' mean time, which the floor's x fixes to within one voxel
    np.testing.assert_allclose(scan.times_s, (scan.points_xyz[:, 0] + 5) / 100, atol=0.5 / 100)
    assert prepare_pointset(points, None, cfg, times_s=np.full(len(points), np.nan)).times_s is None
    assert prepare_pointset(points, None, cfg).times_s is None

    roll = np.array([0.0, 0.0, 0.0, 2.0, 0.0, 0.0])  # 2 rad/s about x: the floor tilts by 0.2 rad at 0.1 s
    moved = deskew_pointset(scan, roll)
    normals = np.linalg.eigh(moved.covariances)[1][:, :, 0]
    expected = Rotation.from_rotvec(np.outer(scan.times_s, [2.0, 0.0, 0.0])).apply([0.0, 0.0, 1.0])
    assert np.abs(np.abs(np.einsum("ij,ij->i", normals, expected)) - 1).max() < 1e-6
    assert moved.points_xyz is not scan.points_xyz and moved.tree.n == scan.n_points


def _scans(log: Path) -> list[LidarFrame]:
    reader = open_log(log)
    try:
        return [decode_pointcloud2(reader.deserialize(m), "/lidar/points") for m in reader.messages(["/lidar/points"])]
    finally:
        reader.close()


@pytest.fixture(scope="module")
def fast_street(tmp_path_factory: pytest.TempPathFactory) -> Sequences:
    """The simulated street at 15 m/s (1.5 m between 10 Hz scans), 25 scans of 32 beams, recorded as a
    driver that does not de-skew reports them and as one that does; with the true poses."""
    out = tmp_path_factory.mktemp("fast_street")
    logs = {}
    for name, deskewed in (("skewed", False), ("deskewed", True)):
        log = out / f"{name}.mcap"
        simulate_log(log, SimulationOptions(frames=25, scene="street", beams=32, cameras=1, width=64, height=48,
                                            speed_m_s=15.0, deskew=deskewed))  # fmt: skip
        truth = load_truth(truth_path_for(log))
        poses = [np.asarray(s["T_map_lidar"], dtype=np.float64) for s in truth["trajectory"]]
        logs[name] = (_scans(log), [invert(poses[0]) @ T for T in poses])
    return logs


def _map(frames: list[LidarFrame], **kwargs: object) -> tuple[list[NDArray[np.float64]], NDArray[np.float64]]:
    voxel_map = VoxelMap(0.1)
    cfg = RegistrationConfig(method="mcgicp", channels="intensity", robust_kernel="cauchy", max_iterations=30)
    steps = run_odometry(frames, cfg, voxel_map=voxel_map, **kwargs)  # type: ignore[arg-type]
    return [s.T_map_lidar for s in steps], voxel_map.points()


def test_fast_street_is_mapped_sharper_when_deskewed(
    fast_street: Sequences,
) -> None:
    """Measured (25 scans, 32 beams): segment drift over 10 m 0.12 % as recorded -> 0.02 % de-skewed; map
    voxels more than 20 cm from the de-skewed log's map 18 % -> 2 %."""
    frames, truth = fast_street["skewed"]
    reference_poses, reference_map = _map(*fast_street["deskewed"][:1])
    assert relative_translation_drift(reference_poses, fast_street["deskewed"][1], 10.0) < 0.002
    tree = cKDTree(reference_map)
    drift, far = {}, {}
    for deskew in (True, False):
        poses, points = _map(frames, deskew=deskew)
        drift[deskew] = relative_translation_drift(poses, truth, 10.0)
        far[deskew] = float(np.mean(tree.query(points)[0] > 0.2))
    print(f"15 m/s street: segment drift {drift}, map voxels > 20 cm off {far}")
    assert drift[True] < 0.001 and drift[True] < 0.5 * drift[False]
    assert far[True] < 0.05 and far[True] < 0.3 * far[False]


def test_first_pair_without_odometry_escapes_the_zero_motion_minimum(
    fast_street: Sequences,
) -> None:
    frames, truth = fast_street["deskewed"]
    coarse, _ = _map(frames)
    trapped, _ = _map(frames, first_motion_max_m=0.0)
    first_step = np.linalg.norm(truth[1][:3, 3])
    assert first_step == pytest.approx(1.5, abs=0.05)
    assert abs(np.linalg.norm(coarse[1][:3, 3]) - first_step) < 0.02
    assert np.linalg.norm(trapped[1][:3, 3]) < 0.5  # the configured 1 m alone keeps the zero-motion minimum
    assert relative_translation_drift(coarse, truth, 10.0) < 0.002
    assert relative_translation_drift(trapped, truth, 10.0) > 0.1


def test_already_deskewed_scans_with_zero_times_are_left_alone(
    fast_street: Sequences,
) -> None:
    frames, _ = fast_street["deskewed"]
    voxel_map = VoxelMap(0.1)
    steps = run_odometry(frames[:4], RegistrationConfig(), voxel_map=voxel_map)
    assert not any(s.deskewed for s in steps)
    steps = run_odometry(fast_street["skewed"][0][:4], RegistrationConfig())
    assert all(s.deskewed for s in steps)


def test_real_points_timed_by_another_clock_are_not_deskewed(shared_data: Path) -> None:
    """PJLab rig1's points carry absolute times 21.9 million s away from their header stamps (the log was
    re-stamped): applying them would throw the points away; they are recognised and the scans mapped as
    recorded, as with ``deskew=False``."""
    log = shared_data / "logs" / "pjlab_road_rig1"
    reader = open_log(log)
    try:
        topic = "/top_center_lidar/points"
        frames = [decode_pointcloud2(reader.deserialize(m), topic) for m in reader.messages([topic])]
    finally:
        reader.close()
    assert abs(float(np.median(frames[0].channels["time"]))) > 1e6
    maps = {}
    for deskew in (True, False):
        voxel_map = VoxelMap(0.5)
        steps = run_odometry(frames, RegistrationConfig(voxel_size_m=0.5), voxel_map=voxel_map, deskew=deskew)
        assert not any(s.deskewed for s in steps)
        maps[deskew] = voxel_map.points()
    np.testing.assert_allclose(maps[True], maps[False])
    assert np.abs(maps[True]).max() < 300
