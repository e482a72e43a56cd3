"""Particle swarm and pattern search on test functions with known optima."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError
from fleetcal.stages.calibration import particle_swarm, pattern_search

OPTIMUM = np.array([1.5, -2.0, 0.25, 3.0, -0.5, 0.0])


def neg_rastrigin(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Negated Rastrigin shifted to OPTIMUM: maximum 0 there, many local maxima around it."""
    d = x - OPTIMUM
    return -np.sum(d * d - 2.0 * np.cos(2 * np.pi * d) + 2.0, axis=1)


def neg_sphere(x: NDArray[np.float64]) -> NDArray[np.float64]:
    return -np.sum((x - OPTIMUM) ** 2, axis=1)


BOX = (OPTIMUM - 4.0 + 0.7, OPTIMUM + 4.0 + 0.3)  # optimum off centre


def test_swarm_finds_global_optimum_of_multimodal_function() -> None:
    calls: list[int] = []

    def objective(x: NDArray[np.float64]) -> NDArray[np.float64]:
        calls.append(x.shape[0])
        assert np.all(x >= BOX[0]) and np.all(x <= BOX[1])
        return neg_rastrigin(x)

    result = particle_swarm(objective, *BOX, n_particles=200, max_iterations=200, seed=3)
    assert np.max(np.abs(result.best_x - OPTIMUM)) < 0.05
    assert result.best_score > -0.05
    assert all(n == 200 for n in calls)  # one batch per iteration
    assert result.evaluations == sum(calls)
    assert np.all(np.diff(result.history) >= 0)  # the global best never gets worse


def test_swarm_is_deterministic_per_seed_and_differs_across_seeds() -> None:
    a = particle_swarm(neg_rastrigin, *BOX, n_particles=50, max_iterations=30, seed=7)
    b = particle_swarm(neg_rastrigin, *BOX, n_particles=50, max_iterations=30, seed=7)
    c = particle_swarm(neg_rastrigin, *BOX, n_particles=50, max_iterations=30, seed=8)
    np.testing.assert_array_equal(a.best_x, b.best_x)
    assert a.history == b.history
    assert not np.array_equal(a.best_x, c.best_x)


def test_swarm_stops_when_converged() -> None:
    result = particle_swarm(neg_sphere, *BOX, n_particles=100, max_iterations=500, stall_iterations=10,
                            score_tolerance=1e-9, seed=0)
    assert result.converged
    assert result.iterations < 500
    assert np.max(np.abs(result.best_x - OPTIMUM)) < 1e-3


def test_initial_particle_is_kept_when_best() -> None:
    result = particle_swarm(neg_sphere, *BOX, n_particles=10, max_iterations=1, seed=0, x_initial=OPTIMUM)
    np.testing.assert_array_equal(result.best_x, OPTIMUM)
    assert result.best_score == 0.0


def test_pattern_search_polishes_to_optimum() -> None:
    start = OPTIMUM + np.array([0.3, -0.2, 0.1, 0.05, -0.3, 0.2])
    result = pattern_search(neg_sphere, start, np.full(6, 0.5), *BOX, min_step_fraction=1e-4)
    assert result.converged
    np.testing.assert_allclose(result.best_x, OPTIMUM, atol=1e-3)
    assert result.best_score >= float(neg_sphere(start[None])[0])


def test_bad_box_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="lower < upper"):
        particle_swarm(neg_sphere, np.zeros(6), np.zeros(6))
    with pytest.raises(ConfigError, match="particles"):
        particle_swarm(neg_sphere, *BOX, n_particles=1)


def neg_rastrigin10(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Standard Rastrigin (cosine amplitude 10) shifted to OPTIMUM and negated: local maxima at every
    integer offset, deep enough to trap a global-best swarm."""
    d = x - OPTIMUM
    return -np.sum(d * d - 10.0 * np.cos(2 * np.pi * d) + 10.0, axis=1)


def test_exploring_on_a_smooth_objective_escapes_local_maxima() -> None:
    """A swarm that first flies on the smooth envelope (``neg_sphere``) and then on the rugged function
    reaches its global maximum from every seed; the plain swarm is trapped one or more cells away in 6
    of these 8 seeds. The returned score is the rugged objective's, counted evaluations include the
    re-scoring at the switch."""
    box = (OPTIMUM - 5.0 + 0.7, OPTIMUM + 5.0 + 0.3)
    trapped = 0
    for seed in range(8):
        plain = particle_swarm(neg_rastrigin10, *box, n_particles=60, max_iterations=200, seed=seed)
        trapped += np.max(np.abs(plain.best_x - OPTIMUM)) > 0.5
        explored = particle_swarm(neg_rastrigin10, *box, n_particles=60, max_iterations=200, seed=seed,
                                  explore_objective=neg_sphere, explore_iterations=30)
        assert np.max(np.abs(explored.best_x - OPTIMUM)) < 0.01, f"seed {seed}"
        assert explored.best_score == pytest.approx(float(neg_rastrigin10(explored.best_x[None])[0]))
        assert explored.iterations >= 30  # the stopping rule counts from the switch
        assert explored.evaluations == 60 * (explored.iterations + 2)
    assert trapped >= 4


def test_explore_phase_must_end_before_the_iteration_limit() -> None:
    with pytest.raises(ConfigError, match="explore_iterations"):
        particle_swarm(neg_sphere, *BOX, max_iterations=20, explore_objective=neg_sphere, explore_iterations=20)


def test_a_screened_swarm_flies_as_the_plain_one() -> None:
    """Where the screened objective rules out exactly the rows below their floor, nothing else changes."""
    def screened(x: NDArray[np.float64], floor: NDArray[np.float64]) -> NDArray[np.float64]:
        f = neg_rastrigin(x)
        return np.where(f > floor, f, -np.inf)

    plain = particle_swarm(neg_rastrigin, *BOX, n_particles=50, max_iterations=40, seed=5)
    fast = particle_swarm(neg_rastrigin, *BOX, n_particles=50, max_iterations=40, seed=5, screened=screened)
    assert fast.iterations == plain.iterations and fast.best_score == plain.best_score
    np.testing.assert_array_equal(fast.best_x, plain.best_x)
    ruled_out = particle_swarm(neg_rastrigin, *BOX, n_particles=50, max_iterations=40, seed=5,
                               screened=lambda x, floor: np.full(x.shape[0], -np.inf))
    assert ruled_out.best_score == max(plain.history[0], ruled_out.history[0]) < plain.best_score
