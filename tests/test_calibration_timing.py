"""Camera clock offset and rolling-shutter readout estimated with the extrinsic (``stages.calibration.timing``).

Frames of the synthetic textured scene are given a lidar twist about the camera stamp; their points are then
moved back by what a clock offset and a rolling shutter would have done (``p - tau (v + w x p)``, ``tau =
offset - readout * row / (H - 1)``, rows at the true extrinsic), so that only the right timing puts them back
on the image's edges.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.transforms import apply, rotation_error_deg, screw_apply, translation_error_m
from fleetcal.stages.calibration import CalibrationFrame, SolverConfig, calibrate
from fleetcal.stages.calibration.problem import CalibrationProblem
from fleetcal.stages.calibration.timing import TimeShift, TimeShiftField
from tests.test_calibration_synthetic import perturb, synthetic_frame, true_T_camera_lidar

# lidar twists (vx, vy, vz m/s, wx, wy, wz rad/s) of the frames: straights, turns both ways, a slower turn
TWISTS = [np.array([10.0, 0, 0, 0, 0, 0.6]), np.array([10.0, 0, 0, 0, 0, -0.6]),
          np.array([10.0, 0, 0, 0, 0, 0.0]), np.array([6.0, 0, 0, 0, 0, 0.3])]


@pytest.fixture(scope="module")
def scenes() -> list[CalibrationFrame]:
    return [synthetic_frame(seed) for seed in range(len(TWISTS))]


def timed_frames(scenes: list[CalibrationFrame], offset_s: float, readout_s: float, known_readout_s: float = 0.0,
                 twist_scale: float = 1.0) -> list[CalibrationFrame]:
    """The scenes as a camera with that clock offset and readout records them while the rig moves."""
    T = true_T_camera_lidar()
    frames = []
    for frame, twist in zip(scenes, TWISTS, strict=True):
        tw = twist * twist_scale
        p = np.asarray(frame.points_xyz, dtype=np.float64)
        uv, valid = frame.camera.project(apply(T, p))
        rows = np.where(valid, np.clip(uv[:, 1] / (frame.camera.height - 1), 0.0, 1.0), 0.5)
        tau = offset_s - readout_s * rows
        velocity = tw[:3][None, :] + np.cross(tw[3:][None, :], p)
        frames.append(dataclasses.replace(frame, points_xyz=p - tau[:, None] * velocity, camera_twist_lidar=tw,
                                          readout_s=known_readout_s))
    return frames


def errors(T: NDArray[np.float64]) -> tuple[float, float]:
    return rotation_error_deg(T, true_T_camera_lidar()), translation_error_m(T, true_T_camera_lidar())


CONFIG = SolverConfig(search_deg=2.0, search_m=0.4, repeats=1, n_particles=60, max_iterations=40,
                           profile_translation_m=0.0)  # the weak-axis profile is not what these tests are about
START = perturb(true_T_camera_lidar(), 1.0, 0.05, 3)


def test_clock_offset_is_found_and_the_extrinsic_with_it(scenes: list[CalibrationFrame]) -> None:
    frames = timed_frames(scenes, 0.030, 0.0)
    found = calibrate(frames, START, dataclasses.replace(CONFIG, estimate_time_offset=True))
    ignored = calibrate(frames, START, CONFIG)
    assert found.time_offset_s == pytest.approx(0.030, abs=0.002)
    assert 0 < found.time_offset_std_s < 0.005
    rot, trans = errors(found.T_camera_lidar)
    assert rot < 0.25 and trans < 0.03
    assert errors(ignored.T_camera_lidar)[1] > 0.15  # 30 ms at 9 m/s: the translation absorbs ~27 cm
    assert np.isnan(ignored.time_offset_s)


def test_offset_of_a_standing_rig_is_unobservable_and_the_extrinsic_unchanged(
        scenes: list[CalibrationFrame]) -> None:
    frames = timed_frames(scenes, 0.030, 0.0, twist_scale=0.0)
    quick = dataclasses.replace(CONFIG, n_particles=20, max_iterations=10)  # the same search either way
    found = calibrate(frames, START, dataclasses.replace(quick, estimate_time_offset=True))
    fixed = calibrate(frames, START, quick)
    assert np.isnan(found.time_offset_s) and np.isinf(found.time_offset_std_s)
    np.testing.assert_allclose(found.T_camera_lidar, fixed.T_camera_lidar, atol=1e-12)


def test_rolling_shutter_readout_known_or_found_beats_ignoring_it(scenes: list[CalibrationFrame]) -> None:
    known = calibrate(timed_frames(scenes, 0.0, 0.030, known_readout_s=0.030), START, CONFIG)
    found = calibrate(timed_frames(scenes, 0.0, 0.030), START, dataclasses.replace(CONFIG, estimate_readout=True))
    ignored = calibrate(timed_frames(scenes, 0.0, 0.030), START, CONFIG)
    assert found.readout_s == pytest.approx(0.030, abs=0.003)
    assert known.readout_s == 0.030
    for result in (known, found):
        rot, trans = errors(result.T_camera_lidar)
        assert rot < 0.25 and trans < 0.03
    assert errors(ignored.T_camera_lidar)[1] > 0.1


def test_field_moves_points_as_the_screw_motion_does_to_first_order(scenes: list[CalibrationFrame]) -> None:
    """Against ``screw_apply``: a frame's points move by the deviation of its twist from the frames' mean times
    the mean shift, plus each point's own rest times its full twist; the extrinsic correction gives back the
    mean motion the search absorbs."""
    frames = [dataclasses.replace(f, camera_twist_lidar=tw, readout_s=0.02) for f, tw in zip(scenes[:2], TWISTS[:2],
                                                                                               strict=True)]
    problem = CalibrationProblem(frames, true_T_camera_lidar(), CONFIG)
    field = TimeShiftField(problem, [f.camera_twist_lidar for f in frames], [0.02, 0.02])
    x = np.zeros(problem.dim)
    fractions = field.row_fractions(x)
    shift = TimeShift(offset_s=0.01)
    field.apply(shift, fractions)
    mean_row = field.mean_fraction(fractions)
    m = 0.01 - 0.02 * mean_row
    shared_twist = np.median(TWISTS[:2], axis=0)
    for k, tw in enumerate(TWISTS[:2]):
        p = field.base_points[0][k][0]
        tau = m - 0.02 * (fractions[0][k][0] - mean_row)
        # full motion by tau, less the mean motion by m: screw motions to first order (h small)
        h = 1e-4
        full = (screw_apply(tw, np.full(p.shape[0], h), p) - p) / h * tau[:, None]
        mean = (screw_apply(shared_twist, np.full(p.shape[0], h), p) - p) / h * m
        np.testing.assert_allclose(problem.scorers[k][0].points, p + full - mean, atol=1e-5)
    C = field.extrinsic_correction(shift, fractions)
    p = field.base_points[0][0][0][:50]
    moved_by_mean = screw_apply(shared_twist, np.full(p.shape[0], m), p)
    np.testing.assert_allclose(apply(C, moved_by_mean), p, atol=1e-3)


def test_no_shift_leaves_the_scorers_and_their_one_pass_as_they_are(scenes: list[CalibrationFrame]) -> None:
    """Moving frames seen by global shutters (readout 0) under no clock offset: nothing moves, so the scorers
    keep their own point arrays and their one-pass scorers are not rebuilt (no copy of every point); after a
    shift, no shift gives back the unshifted arrays themselves."""
    frames = [dataclasses.replace(f, camera_twist_lidar=tw, readout_s=0.0) for f, tw in zip(scenes[:2], TWISTS[:2],
                                                                                              strict=True)]
    problem = CalibrationProblem(frames, true_T_camera_lidar(), CONFIG)
    field = TimeShiftField(problem, [f.camera_twist_lidar for f in frames], [0.0, 0.0])
    fractions = field.row_fractions(np.zeros(problem.dim))
    scorers, together = [list(frame) for frame in problem.scorers], list(problem.together)
    field.apply(TimeShift(), fractions)
    assert all(a is b for frame, old in zip(problem.scorers, scorers, strict=True)
               for a, b in zip(frame, old, strict=True))
    assert all(a is b for a, b in zip(problem.together, together, strict=True))
    field.apply(TimeShift(offset_s=0.01), fractions)
    assert not np.array_equal(problem.scorers[0][0].points, field.base_points[0][0][0])
    field.apply(TimeShift(), fractions)
    assert all(s.points is p for frame, base in zip(problem.scorers, field.base_points[0], strict=True)
               for s, p in zip(frame, base, strict=True))
