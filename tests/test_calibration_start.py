"""Calibration without a guess: a simulated drive with no ``/tf_static`` (``fleetcal simulate --no-tf-static``)
gets its start from its motion (camera motion from consecutive images against fleetcal's own lidar
odometry), also for a camera mounted looking sideways and rolled 90 deg, and ``--initial auto`` overrides a
wrong tf."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
from fleetcal.readers.open import open_log
from fleetcal.workflows.calibrate import PairCalibration, run_calibration
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

LIDAR, CAMERA = "/lidar/points", "/camera_0/image_raw"


def _simulate(path: Path, **changes: object) -> np.ndarray:
    """A 60-scan street drive at 8 m/s that turns at its end; returns the true ``T_camera_lidar``."""
    options = SimulationOptions(frames=60, width=480, height=270, seed=2, tf_static=False)
    simulate_log(path, SimulationOptions(**{**options.__dict__, **changes}), quiet=True)
    truth = json.loads(path.with_name(path.stem + ".truth.json").read_text())
    return np.asarray(truth["pairs"][0]["T_camera_lidar"])


def _calibrate(path: Path, initial: str | None = None) -> PairCalibration:
    config = Config()
    config.calibration.frames = 12
    config.calibration.feature = "intensity"
    config.calibration.repeats = 2
    with open_log(path) as reader:
        return run_calibration(reader, LIDAR, [CAMERA], config, initial, quiet=True)[0]


def test_a_log_without_tf_static_starts_from_its_motion(tmp_path: Path) -> None:
    """A camera looking left out of the car, rolled 90 deg: its turns and travel still fix the rotation."""
    log = tmp_path / "street.mcap"
    T_true = _simulate(log, camera_yaw_deg=90.0, camera_roll_deg=90.0)
    pair = _calibrate(log)
    assert pair.initialisation == "motion" and pair.initial_candidates > 0
    start_deg = rotation_error_deg(pair.T_camera_lidar_initial, T_true)
    assert start_deg < 3.0, start_deg
    error_deg, error_m = rotation_error_deg(pair.T_camera_lidar, T_true), translation_error_m(pair.T_camera_lidar,
                                                                                               T_true)
    assert error_deg < 0.5 and error_m < 0.15, (error_deg, error_m, pair.result.verdict)
    row = pair.summary()
    assert row["initialisation"] == "motion" and row["motion_source"] == "odometry"
    np.testing.assert_array_equal(row["T_camera_lidar_initial"], pair.T_camera_lidar_initial)


def test_initial_auto_replaces_a_wrong_tf(tmp_path: Path) -> None:
    """A tf 30 deg / 0.5 m off, from which the search box (5 deg) cannot reach the truth: ``auto`` finds it
    from the motion (the log's /tf odometry), for a camera looking forward."""
    log = tmp_path / "street.mcap"
    T_true = _simulate(log, tf_static=True, perturb_deg=30.0, perturb_m=0.5)
    pair = _calibrate(log, "auto")
    assert pair.initialisation == "motion"
    assert rotation_error_deg(pair.T_camera_lidar, T_true) < 0.5
