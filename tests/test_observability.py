"""Translation profiles (``stages.calibration.observability``) on objectives whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.stages.calibration.observability import profile_drop, translation_profile, weak_axes


class QuadraticProblem:
    """A stand-in for ``CalibrationProblem``: score = 0.8 - sum_i k_i (x_i - x*_i)^2, plus an optional ridge on
    which a shift along x (parameter 3) is the same as a turn about y (parameter 1): (x_1 - r x_3)^2."""

    def __init__(self, curvature: list[float], ridge: float = 0.0) -> None:
        self.k = np.asarray(curvature, dtype=np.float64)
        self.x_star = np.array([0.3, -0.2, 0.1, 0.02, -0.05, 0.04])
        self.ridge = ridge
        self.lower = np.array([-5.0] * 3 + [-0.5] * 3)
        self.upper = -self.lower

    def free_parameters(self) -> NDArray[np.bool_]:
        return np.ones(6, dtype=bool)

    def evaluate(self, x: NDArray[np.floating], frames: list[int] | None = None) -> NDArray[np.float64]:
        d = np.atleast_2d(x) - self.x_star
        if self.ridge:
            d = d.copy()
            d[:, 1] -= self.ridge * d[:, 3]  # the turn that looks like the shift
            d[:, 3] = 0.0
        return np.asarray(0.8 - (self.k * d**2).sum(axis=1))


def test_profile_drop_of_a_separable_quadratic_is_its_curvature_times_the_step_squared() -> None:
    problem = QuadraticProblem([1e-3, 2e-3, 4e-3, 0.5, 2.0, 8.0])
    best = 0.8
    for i, step in [(0, 0.5), (2, 0.5), (3, 0.15), (5, 0.15)]:
        assert profile_drop(problem, problem.x_star, best, i, step) == pytest.approx(problem.k[i] * step**2, rel=1e-3)  # type: ignore[arg-type]


def test_translation_profile_is_the_shift_against_the_median_turn() -> None:
    """Shifts of 15 cm lose 0.01, 0.03, 0.2 x 0.15^2; the median turn of 0.5 deg loses 2e-3 x 0.5^2."""
    problem = QuadraticProblem([1e-3, 2e-3, 4e-3, 0.01, 0.03, 0.2])
    ratios = translation_profile(problem, problem.x_star, 0.15, 0.5)  # type: ignore[arg-type]
    np.testing.assert_allclose(ratios, [0.45, 1.35, 9.0], rtol=1e-3)
    assert weak_axes(ratios, 1.0) == ["x"]
    assert weak_axes(ratios, 2.0) == ["x", "y"]


def test_a_shift_the_rotation_can_imitate_loses_nothing() -> None:
    """On the ridge, moving x 15 cm is fully made up by turning about y: the profile is flat along x, to what
    the re-fit's last step (0.05 deg) leaves: a loss within 1 % of the median turn's."""
    problem = QuadraticProblem([1e-2, 1e-2, 1e-2, 0.0, 0.5, 0.5], ridge=4.0)  # 15 cm = 0.6 deg about y
    ratios = translation_profile(problem, problem.x_star, 0.15, 0.5)  # type: ignore[arg-type]
    assert abs(ratios[0]) < 0.01
    assert ratios[1] > 1.0 and ratios[2] > 1.0
    assert weak_axes(ratios, 1.0) == ["x"]


def test_no_turn_costs_anything_gives_nan() -> None:
    problem = QuadraticProblem([0.0, 0.0, 0.0, 0.5, 0.5, 0.5])
    ratios = translation_profile(problem, problem.x_star, 0.15, 0.5)  # type: ignore[arg-type]
    assert np.all(np.isnan(ratios)) and weak_axes(ratios, 1.0) == []


class TwoFrameProblem:
    """Frames whose objectives differ: frame f scores 0.8 - sum_i k_f,i (x_i - x*_i)^2; the objective of
    several frames is their mean."""

    def __init__(self, curvatures: list[list[float]]) -> None:
        self.k = np.asarray(curvatures, dtype=np.float64)
        self.x_star = np.array([0.3, -0.2, 0.1, 0.02, -0.05, 0.04])
        self.lower = np.array([-5.0] * 3 + [-0.5] * 3)
        self.upper = -self.lower

    def free_parameters(self) -> NDArray[np.bool_]:
        return np.ones(6, dtype=bool)

    def evaluate(self, x: NDArray[np.floating], view: list[int] | None = None) -> NDArray[np.float64]:
        """The mean of the frames' quadratic scores; ``view``: of those frames only."""
        d2 = (np.atleast_2d(x) - self.x_star) ** 2
        chosen = range(len(self.k)) if view is None else view
        return np.asarray(np.mean([0.8 - (d2 * self.k[f]).sum(axis=1) for f in chosen], axis=0))


def test_profile_on_a_view_measures_that_view() -> None:
    """Frame 0 fixes x weakly (ratio 0.45), frame 1 firmly (ratio 9): the profile on a view of frame 0 alone, of
    frame 1 alone and of both are each their own objective's."""
    problem = TwoFrameProblem([[1e-3, 2e-3, 4e-3, 0.01, 0.03, 0.2], [1e-3, 2e-3, 4e-3, 0.2, 0.03, 0.01]])
    alone_0 = translation_profile(problem, problem.x_star, 0.15, 0.5, view=[0])  # type: ignore[arg-type]
    alone_1 = translation_profile(problem, problem.x_star, 0.15, 0.5, view=[1])  # type: ignore[arg-type]
    both = translation_profile(problem, problem.x_star, 0.15, 0.5)  # type: ignore[arg-type]
    np.testing.assert_allclose(alone_0, [0.45, 1.35, 9.0], rtol=1e-3)
    np.testing.assert_allclose(alone_1, [9.0, 1.35, 0.45], rtol=1e-3)
    np.testing.assert_allclose(both, [4.725, 1.35, 4.725], rtol=1e-3)
