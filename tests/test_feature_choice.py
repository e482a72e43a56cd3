"""The ``auto`` lidar feature: range+normals or intensity, whichever the log's images follow
(``SolverConfig.feature_groups``, ``frame.lidar_feature_stage``)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
from fleetcal.stages.calibration import CalibrationFrame, SolverConfig, calibrate, calibrator
from fleetcal.stages.calibration.feature_choice import sharper
from fleetcal.stages.calibration.frame import AUTO_FEATURE_GROUPS, lidar_feature_stage, usable_groups, with_columns
from fleetcal.stages.lidar_features import compute_lidar_feature
from tests.test_calibration_synthetic import make_scene, perturb, scan_lidar, synthetic_frame, true_T_camera_lidar

SMALL = SolverConfig(n_particles=60, max_iterations=40, repeats=1, search_deg=3.0, search_m=0.3,
                     feature_groups=AUTO_FEATURE_GROUPS)


def auto_frame(seed: int) -> CalibrationFrame:
    """A synthetic scene (its image painted with the lidar's reflectivity) with the ``auto`` columns."""
    frame = synthetic_frame(seed)  # feature: the scan's intensity
    points = np.asarray(frame.points_xyz)
    columns = [compute_lidar_feature(points, "range"), compute_lidar_feature(points, "normals"), frame.feature]
    return dataclasses.replace(frame, feature=np.stack(columns, axis=1))


@pytest.fixture(scope="module")
def auto_frames() -> list[CalibrationFrame]:
    return [auto_frame(seed) for seed in range(3)]


def _count_objectives(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, ...]]:
    """The feature columns of every objective the calibrations build from here on, in order."""
    built: list[tuple[int, ...]] = []
    prepared = calibrator._prepared

    def counted(frames: list[CalibrationFrame], *args: Any) -> Any:
        built.append(tuple(range(np.shape(frames[0].feature)[1])) if np.ndim(frames[0].feature) == 2 else (-1,))
        return prepared(frames, *args)

    monkeypatch.setattr(calibrator, "_prepared", counted)
    return built


def test_the_channel_the_images_follow_is_chosen_and_calibrates(auto_frames: list[CalibrationFrame],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The images show the surfaces' reflectivity, which the intensity column holds: its score falls
    further off alignment in every frame, so intensity is the objective and the estimate lands near the
    truth."""
    T_true = true_T_camera_lidar()
    runs_seen: set[int] = set()
    built = _count_objectives(monkeypatch)
    result = calibrate(auto_frames, perturb(T_true, 2.0, 0.1, seed=3), SMALL,
                       progress=lambda report: runs_seen.add(report.run))
    assert result.feature_columns == (2,)
    assert built == [(-1,), (0, 1), (-1,)]  # intensity, range+normals, and intensity again once it has won
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.3
    assert translation_error_m(result.T_camera_lidar, T_true) <= 0.05
    # chosen before the search: the seeded runs are those of a calibration told to use intensity, no more
    told_runs: set[int] = set()
    told = calibrate(with_columns(auto_frames, (2,)), perturb(T_true, 2.0, 0.1, seed=3),
                     dataclasses.replace(SMALL, feature_groups=()), progress=lambda report: told_runs.add(report.run))
    np.testing.assert_allclose(result.T_camera_lidar, told.T_camera_lidar, atol=1e-9)
    assert runs_seen == told_runs


def test_the_searched_objective_is_the_one_calibrate_chooses_and_searches(auto_frames: list[CalibrationFrame]) -> None:
    """``calibrator.searched_objective`` (what a benchmark of the objective builds, without a search) is the
    objective ``calibrate`` searched from the same start: the same feature columns, the same score at its
    estimate."""
    T_start = perturb(true_T_camera_lidar(), 2.0, 0.1, seed=3)
    result = calibrate(auto_frames, T_start, SMALL)
    problem, columns = calibrator.searched_objective(auto_frames, T_start, SMALL)
    assert columns == result.feature_columns == (2,)
    x_estimate = problem.x_of(result.T_camera_lidar)
    assert float(problem.evaluate(x_estimate[None])[0]) == pytest.approx(result.score, abs=1e-9)
    every_column, _ = calibrator.searched_objective(auto_frames, T_start, dataclasses.replace(SMALL, feature_groups=()))
    assert float(every_column.evaluate(x_estimate[None])[0]) != pytest.approx(result.score, abs=1e-3)


def test_an_intensity_that_the_images_do_not_show_is_not_chosen(auto_frames: list[CalibrationFrame],
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """The same scans with an intensity of noise: range and normals explain more of the images' edges."""
    rng = np.random.default_rng(0)
    noisy = []
    for frame in auto_frames:
        feature = np.asarray(frame.feature).copy()
        feature[:, 2] = rng.random(feature.shape[0])
        noisy.append(dataclasses.replace(frame, feature=feature))
    built = _count_objectives(monkeypatch)
    result = calibrate(noisy, perturb(true_T_camera_lidar(), 2.0, 0.1, seed=3), SMALL)
    assert result.feature_columns == (0, 1)
    assert built == [(-1,), (0, 1)]  # the first group, measured last, is still held: nothing is built again
    # and its objective is the one a calibration told to use range+normals searches
    told = calibrate(with_columns(noisy, (0, 1)), perturb(true_T_camera_lidar(), 2.0, 0.1, seed=3),
                     dataclasses.replace(SMALL, feature_groups=()))
    np.testing.assert_allclose(result.T_camera_lidar, told.T_camera_lidar, atol=1e-9)
    assert result.score == told.score


def test_one_frame_keeps_the_first_group(auto_frames: list[CalibrationFrame]) -> None:
    """One frame has no spread to test a difference against: the default columns, no extra search."""
    result = calibrate(auto_frames[:1], perturb(true_T_camera_lidar(), 2.0, 0.1, seed=3), SMALL)
    assert result.feature_columns == (0, 1)


def test_sharper_needs_the_frames_to_agree() -> None:
    """A difference is significant against its own spread over the frames (Student t, 2.3 % tail)."""
    base = np.array([0.03, 0.05, 0.04, 0.06, 0.05, 0.04])
    assert sharper(base + np.array([0.02, 0.03, 0.025, 0.02, 0.03, 0.025]), base)
    assert not sharper(base + np.array([0.10, -0.06, 0.08, -0.05, 0.06, -0.03]), base)  # mean +0.017, spread
    assert not sharper(base, base + 0.02)
    assert not sharper(base[:1] + 0.5, base[:1])  # one frame
    assert not sharper(np.array([0.10, 0.12]), np.zeros(2))  # two frames: a bound of 14 standard errors
    assert sharper(np.tile([0.10, 0.12], 3), np.zeros(6))  # the same differences on six frames: 2.6


def test_groups_are_those_every_frame_holds(auto_frames: list[CalibrationFrame]) -> None:
    auto_frame = auto_frames[0]
    geometric = with_columns([auto_frame], (0, 1))
    assert geometric[0].feature.shape == (auto_frame.feature.shape[0], 2)
    assert with_columns([auto_frame], (2,))[0].feature.ndim == 1
    assert usable_groups([auto_frame], AUTO_FEATURE_GROUPS) == [(0, 1), (2,)]
    assert usable_groups([auto_frame, *geometric], AUTO_FEATURE_GROUPS) == [(0, 1)]


@pytest.mark.parametrize(("intensity", "columns"), [("varied", 3), ("constant", 2), ("absent", 2)])
def test_auto_lidar_feature_adds_intensity_where_it_varies(intensity: str, columns: int) -> None:
    points, reflectivity = scan_lidar(make_scene(0), beams=16)
    channels = {"varied": {"intensity": reflectivity.astype(np.float32)},
                "constant": {"intensity": np.full(len(points), 7.0, dtype=np.float32)}, "absent": {}}[intensity]
    features = lidar_feature_stage(LidarFrame(0, "/points", "lidar", points, channels), "auto")
    assert features.feature.shape == (len(points), columns)
    np.testing.assert_array_equal(features.feature[:, 0], compute_lidar_feature(points, "range"))
