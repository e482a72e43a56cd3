"""Per-axis deviations of a calibration: which seeded runs score as well as the best, the translation's
sampling floor and the camera-axes change between two extrinsics."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fleetcal.stages.calibration.uncertainty import camera_delta, sampling_floor, scores_alike


def test_a_difference_counts_only_beyond_two_standard_errors_over_the_bands() -> None:
    rng = np.random.default_rng(3)
    noise = rng.standard_normal(16)
    noise = (noise - noise.mean()) / noise.std(ddof=1)  # unit spread over 16 bands: standard error 0.25
    assert scores_alike(0.01 * noise + 0.004)  # mean 0.004, two standard errors 0.005
    assert not scores_alike(0.01 * noise + 0.006)
    assert not scores_alike(-(0.01 * noise + 0.006))  # either sign
    assert scores_alike(np.array([0.3]))  # one band: nothing to tell them apart with


def test_the_translation_floor_is_the_sampling_cell_at_the_typical_range() -> None:
    floor = sampling_floor(ring_spacing_deg=0.4, pixel_deg=0.08, range_m=10.0, off_axis=0.5)
    across = np.radians(0.4 / np.sqrt(12.0)) * 10.0  # 2.0 cm: the rings' cell, not the pixel's
    np.testing.assert_allclose(floor, [0, 0, 0, across, across, across / 0.5])
    np.testing.assert_allclose(sampling_floor(float("nan"), 0.08, 10.0, 0.01)[5],
                               np.radians(0.08 / np.sqrt(12.0)) * 10.0 / 0.1)  # pixel cell; tangent floor 0.1


def test_camera_delta_is_the_turn_and_shift_in_the_camera_axes() -> None:
    T_ref = np.eye(4)
    T_ref[:3, :3] = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    T_ref[:3, 3] = [0.1, -0.2, 0.3]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0.0, 0.0, 1.0], degrees=True).as_matrix()
    turn[:3, 3] = [0.0, 0.05, 0.0]
    T = turn @ T_ref
    delta = camera_delta(T, T_ref)
    np.testing.assert_allclose(delta[:3], [0.0, 0.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(delta[3:], T[:3, 3] - T_ref[:3, 3])
