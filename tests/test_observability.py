"""Translation profiles and per-axis uncertainty (``stages.calibration.observability``) on objectives whose
answer is known."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.stages.calibration.observability import (
    axis_uncertainty,
    curvature_covariance,
    hessian,
    profile_drop,
    translation_profile,
    weak_axes,
)
from fleetcal.stages.calibration.problem import delta_transforms


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

    def evaluate(self, x: NDArray[np.floating]) -> NDArray[np.float64]:
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
    ratios = translation_profile(problem, problem.x_star, 0.8, 0.15, 0.5)  # type: ignore[arg-type]
    np.testing.assert_allclose(ratios, [0.45, 1.35, 9.0], rtol=1e-3)
    assert weak_axes(ratios, 1.0) == ["x"]
    assert weak_axes(ratios, 2.0) == ["x", "y"]


def test_a_shift_the_rotation_can_imitate_loses_nothing() -> None:
    """On the ridge, moving x 15 cm is fully made up by turning about y: the profile is flat along x."""
    problem = QuadraticProblem([1e-2, 1e-2, 1e-2, 0.0, 0.5, 0.5], ridge=4.0)  # 15 cm = 0.6 deg about y
    ratios = translation_profile(problem, problem.x_star, 0.8, 0.15, 0.5)  # type: ignore[arg-type]
    assert abs(ratios[0]) < 1e-3
    assert ratios[1] > 1.0 and ratios[2] > 1.0
    assert weak_axes(ratios, 1.0) == ["x"]


def test_no_turn_costs_anything_gives_nan() -> None:
    problem = QuadraticProblem([0.0, 0.0, 0.0, 0.5, 0.5, 0.5])
    ratios = translation_profile(problem, problem.x_star, 0.8, 0.15, 0.5)  # type: ignore[arg-type]
    assert np.all(np.isnan(ratios)) and weak_axes(ratios, 1.0) == []


class NoisyQuadratic:
    """A stand-in for ``CalibrationProblem`` whose U units (image bands) share ``(-0.5 d^T A d + g_u . d) / U``
    of the score, d = x - x*: the score's curvature is -A and its gradient noise the g_u's, so the estimate's
    covariance is known in closed form: ``A^-1 cov(g) A^-1 / U``."""

    def __init__(self, A: NDArray[np.float64], g: NDArray[np.float64]) -> None:
        self.A, self.g = A, g
        self.x_star = np.zeros(6)
        self.T_init = np.eye(4)

    def _d(self, x: NDArray[np.floating]) -> NDArray[np.float64]:
        return np.atleast_2d(np.asarray(x, dtype=np.float64)) - self.x_star

    def evaluate(self, x: NDArray[np.floating]) -> NDArray[np.float64]:
        return np.asarray(self.unit_scores(self.x_star, x, 0).sum(axis=1))

    def unit_scores(self, x_ref: NDArray[np.floating], x: NDArray[np.floating], blocks: int) -> NDArray[np.float64]:
        d = self._d(x)
        units = self.g.shape[0]
        return np.asarray((-0.5 * np.einsum("pi,ij,pj->p", d, self.A, d)[:, None] + d @ self.g.T) / units)

    def T_camera_lidar(self, x: NDArray[np.floating]) -> NDArray[np.float64]:
        return np.asarray(delta_transforms(np.asarray(x)[None])[0])


def noisy_quadratic(seed: int = 0) -> NoisyQuadratic:
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((6, 6))
    A = B @ B.T + 6.0 * np.eye(6)
    g = rng.standard_normal((16, 6)) * np.array([0.3, 0.2, 0.1, 0.5, 0.4, 0.2])
    g -= g.mean(axis=0)  # the optimum of the mean score stays at x*
    return NoisyQuadratic(A, g)


def test_hessian_of_a_quadratic_is_its_matrix() -> None:
    A = noisy_quadratic().A
    H = hessian(lambda x: -0.5 * np.einsum("pi,ij,pj->p", x, A, x), np.full(6, 0.3),
                np.array([0.05] * 3 + [0.005] * 3))
    np.testing.assert_allclose(H, -A, rtol=1e-6, atol=1e-6)


def test_curvature_covariance_is_the_sandwich_of_the_units_gradients() -> None:
    problem = noisy_quadratic()
    free = np.ones(6, dtype=bool)
    cov, peaked = curvature_covariance(problem, problem.x_star, free)  # type: ignore[arg-type]
    A_inv = np.linalg.inv(problem.A)
    expected = A_inv @ np.cov(problem.g, rowvar=False) @ A_inv / problem.g.shape[0]
    np.testing.assert_allclose(cov, expected, rtol=1e-5, atol=1e-12)
    assert peaked
    held = np.array([True] * 3 + [False] * 3)
    cov_held, _ = curvature_covariance(problem, problem.x_star, held)  # type: ignore[arg-type]
    A_rot_inv = np.linalg.inv(problem.A[:3, :3])
    np.testing.assert_allclose(cov_held[:3, :3], A_rot_inv @ np.cov(problem.g[:, :3], rowvar=False) @ A_rot_inv / 16,
                               rtol=1e-5, atol=1e-12)
    assert np.all(cov_held[3:, :] == 0)


def test_a_direction_the_score_does_not_fall_along_is_infinitely_uncertain() -> None:
    problem = noisy_quadratic()
    A = np.diag([4.0, 4.0, 4.0, 4.0, 4.0, 0.0])  # nothing fixes tz
    problem.A = A
    cov, peaked = curvature_covariance(problem, problem.x_star, np.ones(6, dtype=bool))  # type: ignore[arg-type]
    assert not peaked
    assert np.isinf(cov[5, 5]) and np.all(np.isfinite(np.diag(cov)[:5]))
    uncertainty = axis_uncertainty(problem, problem.x_star, np.ones(6, dtype=bool), [])  # type: ignore[arg-type]
    assert np.isinf(uncertainty.translation_m[2]) and np.all(np.isfinite(uncertainty.rotation_deg))


def test_axis_uncertainty_adds_the_spread_of_the_runs_in_quadrature() -> None:
    problem = noisy_quadratic()
    free = np.ones(6, dtype=bool)
    alone = axis_uncertainty(problem, problem.x_star, free, [])  # type: ignore[arg-type]
    cov, _ = curvature_covariance(problem, problem.x_star, free)  # type: ignore[arg-type]
    np.testing.assert_allclose(alone.rotation_deg, np.sqrt(np.diag(cov)[:3]), rtol=1e-3)
    np.testing.assert_allclose(alone.translation_m, np.sqrt(np.diag(cov)[3:]), rtol=1e-3)
    assert alone.peaked
    runs = [np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.02]), np.array([0.0, 0.0, -0.1, 0.0, 0.0, 0.0])]
    spread = axis_uncertainty(problem, problem.x_star, free, runs)  # type: ignore[arg-type]
    np.testing.assert_allclose(spread.rotation_deg[2] ** 2 - alone.rotation_deg[2] ** 2, 0.05, rtol=1e-3)
    np.testing.assert_allclose(spread.translation_m[2] ** 2 - alone.translation_m[2] ** 2, 2e-4, rtol=1e-3)
    np.testing.assert_allclose(spread.rotation_deg[:2], alone.rotation_deg[:2], rtol=1e-6)
