"""Particle swarm optimisation (GOM paper 3.6, Algorithm 2) and a batched pattern-search polish.

Both maximise an objective that scores a whole batch of candidates at once
(``objective(X (P, D)) -> (P,)``), so every iteration is one vectorised call.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError

BatchObjective = Callable[[NDArray[np.float64]], NDArray[np.float64]]
# scores of a batch given each row's floor: exact where a row may exceed its floor, -inf where it cannot
FlooredObjective = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


@dataclass
class SwarmResult:
    """Outcome of an optimisation.

    Attributes:
        best_x: (D,) best parameters found.
        best_score: objective at ``best_x``.
        iterations: swarm iterations (or pattern-search steps) run.
        evaluations: objective evaluations (candidates scored).
        converged: True when the stopping rule fired before the iteration limit.
        history: best score after each iteration.
    """

    best_x: NDArray[np.float64]
    best_score: float
    iterations: int
    evaluations: int
    converged: bool
    history: list[float] = field(default_factory=list)


def _check_box(lower: NDArray[np.float64], upper: NDArray[np.float64]) -> None:
    if lower.shape != upper.shape or lower.ndim != 1 or not np.all(upper > lower):
        raise ConfigError("search box needs lower < upper in every dimension")


def particle_swarm(objective: BatchObjective, lower: NDArray[np.floating], upper: NDArray[np.floating],
                   n_particles: int = 200, max_iterations: int = 100, stall_iterations: int = 15,
                   min_iterations: int = 20, score_tolerance: float = 1e-6, spread_tolerance: float = 1e-3,
                   seed: int = 0,
                   inertia: float = 0.7298, cognitive: float = 1.49618, social: float = 1.49618,
                   x_initial: NDArray[np.floating] | None = None,
                   explore_objective: BatchObjective | None = None, explore_iterations: int = 0,
                   on_iteration: Callable[[int, float], None] | None = None,
                   screened: FlooredObjective | None = None) -> SwarmResult:
    """Maximise ``objective`` in the box [lower, upper] with a global-best particle swarm.

    Particles start uniformly in the box (plus ``x_initial`` as particle 0 when given), velocities
    are ``w v + c1 phi1 (p_local - x) + c2 phi2 (p_global - x)`` (Algorithm 2, dt = 1) limited to
    half the box, positions are clipped to the box. Stops when the global best has not improved by
    ``score_tolerance`` for ``stall_iterations`` iterations, or when the swarm's spread (largest
    per-dimension std over box size) is below ``spread_tolerance`` (either only after
    ``min_iterations``), or after ``max_iterations``.
    With ``explore_objective`` the swarm first flies ``explore_iterations`` iterations on it (e.g. a
    smoother version of ``objective`` with wider basins), then every particle's best position is
    re-scored with ``objective`` and the swarm flies on; the stopping rule starts counting then.
    ``on_iteration(iteration, best score)`` is called after every iteration (progress reports).
    ``screened``, where given, scores the moved particles on ``objective`` against their own best scores
    (``FlooredObjective``): a particle it gives -inf keeps its best, as it would for any lower score.
    Deterministic for a given ``seed``.
    """
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    _check_box(lo, hi)
    if n_particles < 2 or max_iterations < 1:
        raise ConfigError("particle swarm needs at least 2 particles and 1 iteration")
    exploring = explore_objective is not None and explore_iterations > 0
    if exploring and explore_iterations >= max_iterations:
        raise ConfigError("explore_iterations must be below max_iterations")
    current = explore_objective if exploring and explore_objective is not None else objective
    first_counted = explore_iterations if exploring else 0  # the stopping rule starts here
    rng = np.random.default_rng(seed)
    swarm = _Swarm.start(current, lo, hi, n_particles, rng, x_initial)
    history = [swarm.g_f]
    stall = 0
    converged = False
    iterations = 0
    for _ in range(max_iterations):
        iterations += 1
        if exploring and iterations == explore_iterations:
            current = objective
            swarm.rescore(objective)
            stall = 0
        best_before = swarm.g_f
        swarm.fly(rng, (inertia, cognitive, social), current, screened if current is objective else None)
        stall = 0 if swarm.g_f > best_before + score_tolerance else stall + 1
        history.append(swarm.g_f)
        if on_iteration is not None:
            on_iteration(iterations, swarm.g_f)
        settled = stall >= stall_iterations or swarm.spread() < spread_tolerance
        if iterations >= max(min_iterations, first_counted) and settled:
            converged = True
            break
    return SwarmResult(swarm.g_x, swarm.g_f, iterations, swarm.evaluations, converged, history)


@dataclass
class _Swarm:
    """A particle swarm in the box [lo, hi]: positions and velocities (P, D), each particle's best position and
    score, the global best, and the objective evaluations so far."""

    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    x: NDArray[np.float64]
    v: NDArray[np.float64]
    p_best: NDArray[np.float64]
    f_best: NDArray[np.float64]
    g_x: NDArray[np.float64]
    g_f: float
    evaluations: int

    @classmethod
    def start(cls, objective: BatchObjective, lo: NDArray[np.float64], hi: NDArray[np.float64], n_particles: int,
              rng: np.random.Generator, x_initial: NDArray[np.floating] | None) -> _Swarm:
        """Particles uniform in the box (``x_initial`` as particle 0), velocities within a tenth of it."""
        span = hi - lo
        x = lo + rng.random((n_particles, lo.size)) * span
        if x_initial is not None:
            x[0] = np.clip(np.asarray(x_initial, dtype=np.float64), lo, hi)
        v = (rng.random((n_particles, lo.size)) - 0.5) * span * 0.2
        f = np.asarray(objective(x), dtype=np.float64)
        g = int(np.argmax(f))
        return cls(lo, hi, x, v, x.copy(), f.copy(), x[g].copy(), float(f[g]), n_particles)

    def rescore(self, objective: BatchObjective) -> None:
        """Every particle's best position scored again on ``objective``; the global best follows."""
        self.f_best = np.asarray(objective(self.p_best), dtype=np.float64)
        self.evaluations += self.x.shape[0]
        g = int(np.argmax(self.f_best))
        self.g_x, self.g_f = self.p_best[g].copy(), float(self.f_best[g])

    def fly(self, rng: np.random.Generator, coefficients: tuple[float, float, float], objective: BatchObjective,
            screened: FlooredObjective | None) -> None:
        """One iteration (Algorithm 2, dt = 1): velocities w v + c1 phi1 (p_local - x) + c2 phi2 (p_global - x)
        limited to half the box, positions clipped to it, scored (by ``screened`` against each particle's best
        where given), the bests kept."""
        inertia, cognitive, social = coefficients
        phi1 = rng.random(self.x.shape)
        phi2 = rng.random(self.x.shape)
        v_max = 0.5 * (self.hi - self.lo)
        v = inertia * self.v + cognitive * phi1 * (self.p_best - self.x) + social * phi2 * (self.g_x - self.x)
        self.v = np.clip(v, -v_max, v_max)
        self.x = np.clip(self.x + self.v, self.lo, self.hi)
        f = np.asarray(screened(self.x, self.f_best) if screened is not None else objective(self.x), dtype=np.float64)
        self.evaluations += self.x.shape[0]
        better = f > self.f_best
        self.p_best[better] = self.x[better]
        self.f_best[better] = f[better]
        g = int(np.argmax(self.f_best))
        if self.f_best[g] > self.g_f:
            self.g_x, self.g_f = self.p_best[g].copy(), float(self.f_best[g])

    def spread(self) -> float:
        """The swarm's largest per-dimension standard deviation over the box's size."""
        return float(np.max(np.std(self.x, axis=0) / (self.hi - self.lo)))


def pattern_search(objective: BatchObjective, x0: NDArray[np.floating], step: NDArray[np.floating],
                   lower: NDArray[np.floating], upper: NDArray[np.floating], min_step_fraction: float = 0.01,
                   max_iterations: int = 200, score_at_x0: float | None = None) -> SwarmResult:
    """Batched compass search from ``x0``: score x +- step along every axis (2 D candidates in one
    call), move to the best if it improves, otherwise halve the step; stop when every step is below
    ``min_step_fraction`` of its initial value. Positions stay inside the box."""
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    _check_box(lo, hi)
    x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    s = np.asarray(step, dtype=np.float64).copy()
    s_min = s * min_step_fraction
    dim = x.size
    f_x = float(objective(x[None])[0]) if score_at_x0 is None else float(score_at_x0)
    evaluations = 0 if score_at_x0 is not None else 1
    history = [f_x]
    iterations = 0
    converged = False
    eye = np.eye(dim)
    while iterations < max_iterations:
        iterations += 1
        cand = np.clip(np.concatenate([x + eye * s, x - eye * s]), lo, hi)
        f = np.asarray(objective(cand), dtype=np.float64)
        evaluations += cand.shape[0]
        i = int(np.argmax(f))
        if f[i] > f_x:
            x, f_x = cand[i].copy(), float(f[i])
        else:
            s *= 0.5
        history.append(f_x)
        if np.all(s < s_min):
            converged = True
            break
    return SwarmResult(x, f_x, iterations, evaluations, converged, history)
