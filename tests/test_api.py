"""The scripting API (``from fleetcal import calibrate, map_log, process_log, open_log``) on a small simulated
street log with exact ground truth: the extrinsic and the trajectory come out close to the truth, and the
write-back holds every input message plus the trajectory.

Only the log and its truth file come from elsewhere (``fleetcal.workflows.simulator``, as ``fleetcal simulate``
writes them); the errors are computed here with NumPy. The log: 6 scans of a 64-beam, 512-column lidar and
640x360 images; its ``/tf_static`` holds the true extrinsic turned 2 deg (translation exact).
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal import calibrate, map_log, open_log, process_log
from fleetcal.workflows.simulator.truth import load_truth, truth_path_for
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

SCANS = 6
# Rotation only (the log's translation is exact), 4 frame pairs, a small swarm: ~10 s on 2 cores.
CALIBRATION = {"calibration.frames": 4, "calibration.feature": "intensity", "calibration.particles": 60,
               "calibration.iterations": 40, "calibration.search_m": 0.0, "calibration.search_deg": 3.0}  # fmt: skip
# Scan-to-scan registration only: the log's /tf odometry would give the trajectory away.
MAPPING = {"mapping.use_tf_odometry": False, "mapping.voxel_m": 0.4}


def rotation_deg(T_a: NDArray[np.float64], T_b: NDArray[np.float64]) -> float:
    """Angle of the rotation between the rotation parts of two 4x4 transforms, degrees."""
    cos = (np.trace(T_a[:3, :3].T @ T_b[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


@pytest.fixture(scope="module")
def street(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    log = tmp_path_factory.mktemp("api") / "street.mcap"
    simulate_log(log, SimulationOptions(frames=SCANS, beams=64, columns=512, width=640, height=360, seed=3,
                                        perturb_deg=2.0, perturb_m=0.0))  # fmt: skip
    return log, load_truth(truth_path_for(log))


def test_open_log_lists_the_sensors(street: tuple[Path, dict[str, Any]]) -> None:
    log, truth = street
    with open_log(log) as reader:
        assert reader.topics[truth["lidar_topic"]].count == SCANS
        assert reader.topics[truth["pairs"][0]["camera_topic"]].msgtype == "sensor_msgs/msg/Image"


def test_calibrate_recovers_the_extrinsic(street: tuple[Path, dict[str, Any]]) -> None:
    log, truth = street
    pair_truth = truth["pairs"][0]
    assert rotation_deg(pair_truth["T_camera_lidar_in_log"], pair_truth["T_camera_lidar"]) == pytest.approx(2.0)
    (pair,) = calibrate(log, settings=CALIBRATION)
    assert pair.camera_topic == pair_truth["camera_topic"]
    assert rotation_deg(pair.T_camera_lidar, pair_truth["T_camera_lidar"]) < 0.3  # measured 0.10 deg
    camera_centre_m = np.linalg.inv(pair.T_camera_lidar)[:3, 3]
    centre_in_log_m = np.linalg.inv(pair_truth["T_camera_lidar_in_log"])[:3, 3]
    np.testing.assert_allclose(camera_centre_m, centre_in_log_m, atol=1e-6)  # the translation is held
    assert np.linalg.norm(pair.T_camera_lidar[:3, 3] - pair_truth["T_camera_lidar"][:3, 3]) < 0.01


def test_map_log_follows_the_true_trajectory(street: tuple[Path, dict[str, Any]]) -> None:
    log, truth = street
    outcome = map_log(log, settings=MAPPING)
    assert not outcome.used_tf_odometry
    T_true = [entry["T_map_lidar"] for entry in truth["trajectory"]]
    assert len(outcome.steps) == len(T_true) == SCANS
    path_m = sum(float(np.linalg.norm(b[:3, 3] - a[:3, 3])) for a, b in itertools.pairwise(T_true))
    assert path_m > 3.0
    for step, T in zip(outcome.steps, T_true, strict=True):
        assert np.linalg.norm(step.T_map_lidar[:3, 3] - T[:3, 3]) < 0.01  # measured 1.0 mm at the end
        assert rotation_deg(step.T_map_lidar, T) < 0.1
    assert outcome.map_points_xyz.shape[0] > 1000


def test_process_log_writes_back_every_message_and_the_trajectory(
    street: tuple[Path, dict[str, Any]], tmp_path: Path
) -> None:
    log, truth = street
    cheapest = {**CALIBRATION, "calibration.frames": 1, "calibration.particles": 10, "calibration.iterations": 5,
                **MAPPING}  # fmt: skip
    result = process_log(log, tmp_path, settings=cheapest)
    assert result.mapping is not None and result.mapping["scans"] == SCANS
    assert result.writeback_path is not None
    with open_log(log) as original, open_log(result.writeback_path) as written:
        for topic, info in original.topics.items():  # /tf_static gains the calibrated pose
            assert written.topics[topic].count == info.count + (topic == "/tf_static")
        (raw,) = list(written.messages(["/fleetcal/trajectory"]))
        poses = written.deserialize(raw).poses
    assert len(poses) == SCANS
    for pose, entry in zip(poses, truth["trajectory"], strict=True):
        position = pose.pose.position
        assert np.linalg.norm([position.x, position.y, position.z] - entry["T_map_lidar"][:3, 3]) < 0.01
