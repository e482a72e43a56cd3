"""A swarm's screened objective: split views add up to the whole, a screened score is exact or ruled out."""

from __future__ import annotations

import numpy as np
import pytest

import fleetcal.stages.calibration.problem as problem_module
from fleetcal.stages.calibration import CalibrationProblem, SolverConfig
from fleetcal.stages.calibration.problem import ScreenedObjective
from tests.test_calibration_synthetic import perturb, synthetic_frame, true_T_camera_lidar


def _two_feature_problem(seed: int) -> CalibrationProblem:
    frame = synthetic_frame(seed, feature="range")
    normals = synthetic_frame(seed, feature="normals")
    both = type(frame)(frame.points_xyz, np.column_stack([frame.feature, normals.feature]), frame.camera,
                       frame.gradients, intensity=frame.intensity, label=frame.label)  # fmt: skip
    return CalibrationProblem([both, synthetic_frame(seed + 1)], perturb(true_T_camera_lidar(), 1.0, 0.05, 3),
                              SolverConfig())  # fmt: skip


@pytest.mark.parametrize("one_pass", [True, False])
def test_split_views_add_up_to_the_whole_view(one_pass: bool) -> None:
    problem = _two_feature_problem(1)
    if not one_pass:
        problem.full.together[0] = None
    x = np.random.default_rng(0).uniform(problem.lower, problem.upper, (24, problem.lower.size))
    whole, whole_counts = problem.frame_scores(x)
    for stride in (2, 4):
        thinned, rest = problem.full.split(stride)
        merged = [[a.plus(b) for a, b in zip(fa, fb, strict=True)]
                  for fa, fb in zip(problem.metric_batches(x, thinned), problem.metric_batches(x, rest), strict=True)]
        scores, counts = problem.scores_of(merged, problem.full)
        np.testing.assert_array_equal(counts, whole_counts)
        np.testing.assert_allclose(scores, whole, rtol=0, atol=1e-12)
        estimate = problem.scores_of(problem.metric_batches(x, thinned), thinned)[0]
        assert 0 < np.max(np.abs(estimate - whole)) < 0.1  # a thinned score is near, not equal
        assert (thinned.share, rest.share) == (1 / stride, 1 - 1 / stride)


def test_a_screened_score_is_exact_or_below_its_floor() -> None:
    problem = _two_feature_problem(2)
    free = problem.free_parameters()
    screened = ScreenedObjective(problem, problem.full, problem.centre, free)
    rng = np.random.default_rng(1)
    z = rng.uniform(problem.lower, problem.upper, (64, problem.lower.size))
    exact = problem.evaluate(z)
    np.testing.assert_allclose(screened(z), exact, rtol=0, atol=1e-12)  # no floor: every row in full
    z = rng.uniform(problem.lower, problem.upper, (64, problem.lower.size))
    exact = problem.evaluate(z)
    floor = np.where(np.arange(64) % 2 == 0, exact - 0.002, exact + 0.05)
    before = problem.evaluations
    scores = screened(z, floor)
    kept = np.isfinite(scores)
    np.testing.assert_allclose(scores[kept], exact[kept], rtol=0, atol=1e-12)
    assert np.all(scores[~kept] == -np.inf) and np.all(exact[~kept] < floor[~kept])
    assert np.all(kept[::2])  # a row that beats its floor is never ruled out here
    assert np.mean(~kept[1::2]) > 0.5  # most rows 0.05 below their floor are ruled out by the thinned pass
    assert problem.evaluations - before < 0.8 * 64  # and cost a quarter of a full scoring


def test_screening_leaves_the_swarm_where_it_would_be(monkeypatch: pytest.MonkeyPatch) -> None:
    problem = _two_feature_problem(3)
    problem.evaluations = 0.0
    swarm, polish = problem.optimise(0)
    screened_cost = problem.evaluations
    monkeypatch.setattr(problem_module, "SCREEN_SIGMAS", 1e9)  # no row ruled out
    problem.evaluations = 0.0
    plain, plain_polish = problem.optimise(0)
    assert swarm.iterations == plain.iterations
    np.testing.assert_allclose(swarm.best_x, plain.best_x, rtol=0, atol=1e-9)
    assert polish is not None and plain_polish is not None
    assert polish.best_score == pytest.approx(plain_polish.best_score, abs=1e-12)
    assert screened_cost < 0.85 * problem.evaluations
