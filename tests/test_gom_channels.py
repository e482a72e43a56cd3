"""GOM channels scored in one pass equal the channels' own scorers."""

from __future__ import annotations

import numpy as np
import pytest

from fleetcal.pipeline.errors import ProcessingError
from fleetcal.stages.calibration import CalibrationProblem, SolverConfig
from fleetcal.stages.calibration.gom_channels import GomChannels
from fleetcal.stages.calibration.metrics import GomScorer, GradientPlanes
from tests.test_calibration_synthetic import perturb, synthetic_frame, true_T_camera_lidar


def _poses(n: int, seed: int) -> np.ndarray:
    return np.stack([perturb(true_T_camera_lidar(), 1.5, 0.1, seed + k) for k in range(n)])


def _channels(seed: int = 0) -> tuple[np.ndarray, list[GomScorer], GradientPlanes]:
    """Two channels keeping overlapping halves of one scan's points against one image."""
    frame = synthetic_frame(seed)
    rng = np.random.default_rng(seed)
    points = np.asarray(frame.points_xyz, dtype=np.float64)
    image = GradientPlanes.of_stacked(frame.gradients.gxy, frame.camera)
    selections = rng.random((2, points.shape[0])) < 0.5
    R = true_T_camera_lidar()[:3, :3]
    scorers = []
    for sel in selections:
        angle = rng.uniform(-np.pi, np.pi, int(sel.sum()))
        scorers.append(GomScorer(points[sel], np.cos(angle), np.sin(angle), rng.uniform(0.1, 1.0, angle.size),
                                 image, frame.camera, R))  # fmt: skip
    return selections, scorers, image


def test_channels_and_twins_in_one_pass_equal_their_own_scorers() -> None:
    selections, scorers, image = _channels()
    blurred = image.blurred(3.0)
    thinned = image.blurred_along(np.array([0.3, 1.0]), 9.0, thinned=True)  # 17 deg off v: kept at 1 x 3 pixels
    assert thinned.strides == (1, 3)
    T = _poses(16, 7)
    for chosen, channels, twin in ((selections, scorers, None), (selections, scorers, blurred),
                                   (selections[:1], scorers[:1], blurred), (selections, scorers, thinned),
                                   (selections[:1], scorers[:1], thinned)):  # fmt: skip
        together = GomChannels(chosen, channels, twin).score(T)
        alone = [s.score(T) for s in channels] + ([s.against(twin).score(T) for s in channels] if twin else [])
        assert len(together) == len(alone)
        for a, b in zip(together, alone, strict=True):
            np.testing.assert_array_equal(a.counts, b.counts)
            np.testing.assert_allclose(a.scores, b.scores, rtol=0, atol=1e-12)
            assert np.all(b.counts > 1000) and np.ptp(b.scores) > 0.01


def test_channels_against_other_planes_are_refused() -> None:
    selections, scorers, image = _channels()
    other = GomScorer(scorers[1].points, scorers[1].c2, scorers[1].s2, scorers[1].magnitude, image.blurred(2.0),
                      synthetic_frame(0).camera)  # fmt: skip
    with pytest.raises(ProcessingError, match="share"):
        GomChannels(selections, [scorers[0], other])


def test_problem_scores_two_features_in_one_pass_as_one_by_one() -> None:
    frame = synthetic_frame(1, feature="range")
    normals = synthetic_frame(1, feature="normals")
    both = type(frame)(frame.points_xyz, np.column_stack([frame.feature, normals.feature]), frame.camera,
                       frame.gradients, intensity=frame.intensity, label=frame.label)  # fmt: skip
    problem = CalibrationProblem([both], perturb(true_T_camera_lidar(), 1.0, 0.05, 3), SolverConfig())
    assert problem.together[0] is not None
    x = np.random.default_rng(0).uniform(problem.lower, problem.upper, (32, problem.lower.size))
    scores, counts = problem.frame_scores(x)
    problem.full.together[0] = None
    alone_scores, alone_counts = problem.frame_scores(x)
    np.testing.assert_array_equal(counts, alone_counts)
    np.testing.assert_allclose(scores, alone_scores, rtol=0, atol=1e-12)


def test_moved_points_are_scored_in_one_pass_too() -> None:
    """Points replaced in the frame's scorers (as ``timing`` moves them to the rows' times) are what the one-pass
    scoring and the swarm's views score after ``points_moved``."""
    frame = synthetic_frame(1, feature="range")
    normals = synthetic_frame(1, feature="normals")
    both = type(frame)(frame.points_xyz, np.column_stack([frame.feature, normals.feature]), frame.camera,
                       frame.gradients, intensity=frame.intensity, label=frame.label)  # fmt: skip
    problem = CalibrationProblem([both], perturb(true_T_camera_lidar(), 1.0, 0.05, 3), SolverConfig())
    x = np.random.default_rng(0).uniform(problem.lower, problem.upper, (16, problem.lower.size))
    before = problem.evaluate(x, problem.search_view(0))
    for j, scorer in enumerate(problem.scorers[0]):
        problem.scorers[0][j] = scorer.subset(np.arange(scorer.points.shape[0]))
        problem.scorers[0][j].points = scorer.points + np.array([0.05, -0.03, 0.02])
    problem.points_moved()
    moved = problem.frame_scores(x)[0]
    problem.full.together[0] = None
    np.testing.assert_allclose(moved, problem.frame_scores(x)[0], rtol=0, atol=1e-12)
    assert np.max(np.abs(problem.evaluate(x, problem.search_view(0)) - before)) > 1e-3
