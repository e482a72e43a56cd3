"""Per-axis deviations of a calibration: which seeded runs score as well as the best, the translation's
sampling floor and the camera-axes change between two extrinsics."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fleetcal.stages.calibration.uncertainty import (
    AxisDeviations,
    camera_delta,
    curvature_deviation_m,
    reaching_initial_guess,
    sampling_floor,
    scores_alike,
)


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


def test_the_curvature_deviation_is_the_translation_that_costs_what_the_rotation_deviation_does() -> None:
    """A score falling quadratically, -a r^2 - b t^2 (r degrees, t metres): the profile of a 0.15 m move against a
    0.5 deg turn is b 0.15^2 / (a 0.5^2), and the translation whose loss equals that of a turn by the rotation's
    deviation is that deviation times sqrt(a / b)."""
    a, b = 0.04, np.array([2.0, 0.5, 0.02])  # score per deg^2; per m^2 along x, y, z
    profile = b * 0.15**2 / (a * 0.5**2)
    sigma_rotation = 0.12
    expected = sigma_rotation * np.sqrt(a / b)
    np.testing.assert_allclose(curvature_deviation_m(profile, sigma_rotation, 0.15, 0.5, box_m=10.0), expected,
                               rtol=1e-12)
    np.testing.assert_allclose(b * expected**2, a * sigma_rotation**2, rtol=1e-12)  # the same loss either way
    # never wider than a uniform spread over the box; as wide where the move costs nothing; NaN not measured
    capped = curvature_deviation_m(np.array([1e-6, 0.0, np.nan]), sigma_rotation, 0.15, 0.5, box_m=0.5)
    np.testing.assert_allclose(capped[:2], 0.5 / np.sqrt(3.0))
    assert np.isnan(capped[2])


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


def test_a_suspect_estimate_is_uncertain_up_to_its_initial_guess_on_every_axis() -> None:
    """Estimate 1.5 deg about the camera's y and 0.3 m along its z from the initial guess: those two axes widen to
    the distances, the others keep their deviations, and a translation the settings held stays NaN."""
    T_init = np.eye(4)
    T_init[:3, :3] = Rotation.from_euler("xyz", [-90, 0, -90], degrees=True).as_matrix()
    T_init[:3, 3] = [0.05, -0.3, 0.1]
    move = np.eye(4)
    move[:3, :3] = Rotation.from_rotvec([0.0, 1.5, 0.0], degrees=True).as_matrix()
    move[:3, 3] = [0.0, 0.0, 0.3]
    T = move @ T_init
    found = AxisDeviations(np.array([0.4, 0.2, 0.3]), np.array([0.05, 0.5, 0.02]), alike_runs=1)
    wide = reaching_initial_guess(found, T, T_init)
    shift = T[:3, 3] - T_init[:3, 3]
    np.testing.assert_allclose(wide.rotation_deg, [0.4, 1.5, 0.3], atol=1e-9)
    np.testing.assert_allclose(wide.translation_m, [max(0.05, abs(shift[0])), 0.5, max(0.02, abs(shift[2]))])
    assert wide.alike_runs == 1
    held = reaching_initial_guess(AxisDeviations(found.rotation_deg, np.full(3, np.nan), 0), T, T_init)
    assert np.all(np.isnan(held.translation_m))


def test_ring_alias_optima_are_polished_moves_along_the_lidar_axis_and_bound_the_deviation() -> None:
    """The estimate moved 1-3 ring spacings either way along the lidar's axis (moves outside the box
    skipped), each polished to a pose scoring at least as well as where it started; twice the deviation
    reaches the farthest alias optimum that scores as well as the estimate, axis by axis."""
    from fleetcal.stages.calibration import CalibrationProblem, SolverConfig
    from fleetcal.stages.calibration.uncertainty import (
        BANDS_PER_FRAME,
        axis_deviations,
        band_scores,
        ring_alias_optima,
    )
    from tests.test_calibration_synthetic import synthetic_frame, true_T_camera_lidar

    T_true = true_T_camera_lidar()
    problem = CalibrationProblem([synthetic_frame(0)], T_true, SolverConfig(search_deg=2.0, search_m=0.5))
    x_true, free = np.zeros(6), problem.free_parameters()
    aliases = ring_alias_optima(problem, x_true, free, ring_spacing_deg=0.5, range_m=10.0)
    assert len(aliases) == 6  # 8.7, 17 and 26 cm either way, all inside the 0.5 m box
    lidar_axis = T_true[:3, :3] @ np.array([0.0, 0.0, 1.0])
    for k, x in enumerate(aliases):
        rings, sign = 1 + k // 2, -1.0 if k % 2 == 0 else 1.0
        T_start = T_true.copy()
        T_start[:3, 3] += sign * rings * np.radians(0.5) * 10.0 * lidar_axis
        start_score = problem.evaluate(problem.x_of(T_start)[None])[0]
        assert problem.evaluate(x[None])[0] >= start_score
    scores = band_scores(problem, np.vstack([x_true, *aliases]), BANDS_PER_FRAME)
    alike = [x for k, x in enumerate(aliases, start=1) if scores_alike(scores[0] - scores[k])]
    deviations = axis_deviations(problem, x_true, [], np.zeros(6), free, aliases)
    assert deviations.alike_aliases == len(alike) >= 1
    farthest = np.max([np.abs(camera_delta(problem.T_camera_lidar(x), T_true)) for x in alike], axis=0)
    np.testing.assert_allclose(2 * deviations.rotation_deg, farthest[:3], rtol=1e-9)
    np.testing.assert_allclose(2 * deviations.translation_m, farthest[3:], rtol=1e-9)
    assert ring_alias_optima(problem, x_true, problem.free_parameters(hold_translation=True), 0.5, 10.0) == []
    assert ring_alias_optima(problem, x_true, free, float("nan"), 10.0) == []
    assert len(ring_alias_optima(problem, x_true, free, 2.0, 10.0)) == 2  # 35 cm in the box, 70 and 105 cm not


def test_a_held_translation_is_as_uncertain_as_the_six_dof_runs_it_replaced() -> None:
    """Held where the 6-DoF runs disagreed: each axis's deviation is the floor and those runs' root mean
    square distance from the held estimate in quadrature; held by the settings (nothing replaced), the
    translation has no deviation."""
    from fleetcal.stages.calibration import CalibrationProblem, SolverConfig
    from fleetcal.stages.calibration.uncertainty import axis_deviations
    from tests.test_calibration_synthetic import synthetic_frame, true_T_camera_lidar

    problem = CalibrationProblem([synthetic_frame(0)], true_T_camera_lidar(), SolverConfig(search_deg=2.0,
                                                                                           search_m=0.5))
    held = problem.free_parameters(hold_translation=True)
    x_held = np.zeros(6)
    x_runs = [np.array([0.4, 0.0, 0.0, 0.0, 0.12, 0.0]), np.array([0.0, -0.2, 0.0, 0.05, -0.06, 0.0])]
    floor = np.array([0.12, 0.12, 0.12, 0.01, 0.01, 0.03])
    deviations = axis_deviations(problem, x_held, [], floor, held, x_replaced=x_runs)
    T_held = problem.T_camera_lidar(x_held)
    deltas = np.array([camera_delta(problem.T_camera_lidar(x), T_held) for x in x_runs])
    expected = np.sqrt(floor ** 2 + np.mean(deltas ** 2, axis=0))
    np.testing.assert_allclose(deviations.rotation_deg, expected[:3], rtol=1e-9)
    np.testing.assert_allclose(deviations.translation_m, expected[3:], rtol=1e-9)
    assert deviations.translation_m[1] > 0.08  # the runs 12 and 6 cm apart along y: 9.5 cm
    by_settings = axis_deviations(problem, x_held, [], floor, held)
    assert np.all(np.isnan(by_settings.translation_m))
    np.testing.assert_allclose(by_settings.rotation_deg, floor[:3])


def test_runs_that_score_worse_count_only_where_no_run_confirms_the_best() -> None:
    """Two seeded runs 0.8 deg / 10 cm and 1.4 deg / 20 cm off the best score clearly worse over the image bands:
    they found local optima and say nothing of a confirmed estimate (the floor alone), but where no run confirms
    the best each axis's deviation reaches the farthest run along it, so twice it exceeds the agreement
    distance."""
    from fleetcal.stages.calibration import CalibrationProblem, SolverConfig
    from fleetcal.stages.calibration.uncertainty import BANDS_PER_FRAME, axis_deviations, band_scores
    from tests.test_calibration_synthetic import synthetic_frame, true_T_camera_lidar

    problem = CalibrationProblem([synthetic_frame(0)], true_T_camera_lidar(), SolverConfig(search_deg=2.0,
                                                                                           search_m=0.5))
    free, x_best = problem.free_parameters(), np.zeros(6)
    x_others = [np.array([0.0, 0.8, 0.0, 0.1, 0.0, 0.0]), np.array([1.0, 1.0, 0.0, 0.2, 0.0, 0.0])]
    scores = band_scores(problem, np.vstack([x_best, *x_others]), BANDS_PER_FRAME)
    assert not scores_alike(scores[0] - scores[1]) and not scores_alike(scores[0] - scores[2])
    floor = np.array([0.12, 0.12, 0.12, 0.01, 0.01, 0.03])
    confirmed = axis_deviations(problem, x_best, x_others, floor, free)
    np.testing.assert_allclose(np.r_[confirmed.rotation_deg, confirmed.translation_m], floor, rtol=1e-9)
    unconfirmed = axis_deviations(problem, x_best, x_others, floor, free, confirmed=False)
    T_best = problem.T_camera_lidar(x_best)
    deltas = np.array([camera_delta(problem.T_camera_lidar(x), T_best) for x in x_others])
    expected = np.sqrt(floor ** 2 + np.max(deltas ** 2, axis=0))
    np.testing.assert_allclose(np.r_[unconfirmed.rotation_deg, unconfirmed.translation_m], expected, rtol=1e-9)
    assert unconfirmed.alike_runs == 0 and 2 * np.max(unconfirmed.rotation_deg) > 0.5
