"""The start search (``stages.calibration.initialisation``) on the synthetic scene of
``test_calibration_synthetic``: around a rotation from motion, and along the axis a straight drive leaves free;
the start's translation is zero, 0.38 m from the truth on a scene 4-8 m away."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.transforms import rotation_error_deg
from fleetcal.stages.calibration.config import SolverConfig
from fleetcal.stages.calibration.frame import CalibrationFrame
from fleetcal.stages.calibration.hand_eye import HandEyeRotation
from fleetcal.stages.calibration.initialisation import (
    axis_turns,
    fibonacci_directions,
    local_turns,
    looking_along,
    search_initial_guess,
)
from tests.test_calibration_synthetic import synthetic_frame, true_T_camera_lidar


@pytest.fixture(scope="module")
def frames() -> list[CalibrationFrame]:
    return [synthetic_frame(seed) for seed in (0, 1)]


def _motion(R: np.ndarray, free_axis: np.ndarray | None) -> HandEyeRotation:
    return HandEyeRotation(R, 10, 0.1, 0.5 if free_axis is None else 20.0, free_axis)


def test_a_start_around_a_rotation_from_motion(frames: list[CalibrationFrame]) -> None:
    T_true = true_T_camera_lidar()
    R_motion = Rotation.from_rotvec([2.0, -1.5, 1.0], degrees=True).as_matrix() @ T_true[:3, :3]
    guess = search_initial_guess(frames, SolverConfig(), _motion(R_motion, None))
    assert guess.source == "motion" and not guess.ambiguous
    assert rotation_error_deg(guess.T_camera_lidar, T_true) < 2.0 < rotation_error_deg(
        np.pad(R_motion, ((0, 1), (0, 1))) + np.diag([0, 0, 0, 1.0]), T_true)


def test_a_start_along_the_axis_a_straight_drive_leaves_free(frames: list[CalibrationFrame]) -> None:
    """Travel along lidar x fixes two angles; the roll about x is searched all around."""
    T_true = true_T_camera_lidar()
    R_start = T_true[:3, :3] @ Rotation.from_rotvec([130.0, 0.0, 0.0], degrees=True).as_matrix()
    guess = search_initial_guess(frames, SolverConfig(), _motion(R_start, np.array([1.0, 0.0, 0.0])))
    assert rotation_error_deg(guess.T_camera_lidar, T_true) < 2.0
    assert guess.candidates > 360 / 15


def test_candidate_grids() -> None:
    directions = fibonacci_directions(50)
    assert np.allclose(np.linalg.norm(directions, axis=1), 1.0)
    assert np.max(directions @ directions.T - 2 * np.eye(50)) < np.cos(np.radians(15.0))  # spread, none alike
    R = looking_along(np.array([0.0, 1.0, 0.0]))
    assert np.allclose(R @ R.T, np.eye(3)) and np.allclose(R[2], [0.0, 1.0, 0.0])
    turns = local_turns(3.0, 1.5, full_roll=False)
    assert turns.shape == (125, 3, 3)
    angles = Rotation.from_matrix(turns).magnitude()
    assert np.isclose(angles.min(), 0.0) and np.degrees(angles.max()) < 3.0 * np.sqrt(3) + 1e-6
    spins = axis_turns(np.array([0.0, 0.0, 1.0]), 7.5, 1.5)
    assert spins.shape == (11 * 9, 3, 3)
