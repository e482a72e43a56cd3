"""Pairwise registration: GICP, Multi-Channel GICP and Color-ICP on prepared ``PointSet`` scans.

All three minimise eq. 3 of Servos & Waslander, sum_i d_i^T (C_i^B + R C_i^A R^T)^-1 d_i with
d_i = b_i - T a_i, by Gauss-Newton (or Levenberg-Marquardt) over SE(3), re-finding correspondences
every iteration. They differ in the covariances (plane model; MC-GICP eq. 6-10; 0.5 I for
Color-ICP's point-to-point cost) and in the correspondence space (3-D for GICP; (3 + n)-D weighted
by alpha for MC-GICP and Color-ICP, Johnson & Kang).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import InputError, TransformError
from fleetcal.pipeline.transforms import exp_se3, is_rigid
from fleetcal.stages.registration.config import CHANNEL_MODES, RegistrationConfig
from fleetcal.stages.registration.gicp_kernels import (
    ROBUST_CAUCHY,
    ROBUST_HUBER,
    ROBUST_NONE,
    fitness_kernel,
    linearize_kernel,
    match_linearize_kernel,
)
from fleetcal.stages.registration.kdtree import in_threads, split_range, thread_count
from fleetcal.stages.registration.pointset import PointSet

ROBUST_KERNELS = {"none": ROBUST_NONE, "huber": ROBUST_HUBER, "cauchy": ROBUST_CAUCHY}
MIN_CORRESPONDENCES = 6
N_CHUNKS = 8
"""Partial sums of the linearisation per thread (blocked summation)."""


@dataclass
class RegistrationResult:
    """Outcome of one registration.

    Attributes:
        T_target_source: (4, 4) float64, source points into the target frame.
        fitness: fraction of source points with a correspondence within the maximum distance.
        rmse_m: RMS Euclidean distance of those correspondences, metres (inf when none).
        iterations: optimiser iterations run.
        converged: the update fell below the thresholds before ``max_iterations``; False for a
            failed pair (too few correspondences).
        hessian_eigenvalues: (6,) ascending eigenvalues of the Gauss-Newton Hessian at the solution
            (parameters: rotation vector rad, translation m, source frame).
        degenerate: the motion is poorly fixed along some direction: ``conditioning`` of the Hessian below
            ``RegistrationConfig.degeneracy_threshold``.
        n_correspondences: correspondences used in the last linearisation.
        cost_history: cost (eq. 3, robustified) at each iteration's linearisation.
    """

    T_target_source: NDArray[np.float64]
    fitness: float
    rmse_m: float
    iterations: int
    converged: bool
    hessian_eigenvalues: NDArray[np.float64]
    degenerate: bool
    n_correspondences: int = 0
    cost_history: list[float] = field(default_factory=list)


def channel_alpha_for(target: PointSet, config: RegistrationConfig) -> NDArray[np.float64]:
    """Kd-tree weights alpha (n,) of the descriptor channels (the target scan's variances set them)."""
    if config.channel_alpha is not None:
        return np.asarray(config.channel_alpha, dtype=np.float64)
    return config.channel_weight_m**2 / np.maximum(target.channel_variance, 1e-12)


class _Matcher:
    """Correspondences of transformed source points in the target (nearest neighbour in the target's
    kd-tree, 3-D or (3 + n)-D) and the linearisation at them, in one kernel pass per slice of the source.

    Each source point keeps where it was last searched and the two nearest target points found there,
    so that a later iteration searches again only the points that moved too far to keep their nearest
    (``match_linearize_kernel``). With several ``workers`` the source is cut into that many slices
    searched and linearised on threads (the kernel releases the GIL).
    """

    def __init__(self, source: PointSet, target: PointSet, config: RegistrationConfig) -> None:
        self.source = source
        self.target = target
        self.config = config
        if config.method in ("mcgicp", "color_icp"):
            alpha = channel_alpha_for(target, config)
            self.tree = target.feature_tree(alpha)
            self.source_features = np.ascontiguousarray(source.scaled_descriptors(alpha))
        else:
            self.tree = target.tree
            self.source_features = np.zeros((source.n_points, 0))
        self.searched_at = np.zeros((source.n_points, self.tree.dims))
        self.nearest = np.full(source.n_points, -1, dtype=np.int64)
        self.second = np.full(source.n_points, -1, dtype=np.int64)
        self.second_dist = np.full(source.n_points, -1.0)
        self.corr = np.full(source.n_points, -1, dtype=np.int64)
        self.slices = split_range(source.n_points, thread_count(config.workers))

    def match_linearize(
        self, T: NDArray[np.float64], robust: int, n_chunks: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], float, int]:
        """Correspondences at T into ``corr`` (target index per source point, -1 beyond the maximum
        correspondence distance); returns (H, g, cost, used) of ``linearize_kernel`` at them."""
        T = np.ascontiguousarray(T, dtype=np.float64)
        src, tgt = self.source, self.target
        max_d2 = self.config.max_correspondence_distance_m**2

        def run(lo: int, hi: int) -> tuple[NDArray[np.float64], NDArray[np.float64], float, int]:
            return match_linearize_kernel(  # type: ignore[no-any-return]
                *self.tree.arrays, src.points_xyz[lo:hi], self.source_features[lo:hi], src.covariances[lo:hi],
                tgt.points_xyz, tgt.covariances, T, max_d2, robust, self.config.robust_scale, n_chunks,
                self.searched_at[lo:hi], self.nearest[lo:hi], self.second[lo:hi], self.second_dist[lo:hi],
                self.corr[lo:hi],
            )  # fmt: skip

        parts = in_threads(run, self.slices)
        if len(parts) == 1:
            return parts[0]
        return (sum(p[0] for p in parts), sum(p[1] for p in parts),  # type: ignore[return-value]
                float(sum(p[2] for p in parts)), int(sum(p[3] for p in parts)))  # fmt: skip

    def fitness_rmse(self, T: NDArray[np.float64]) -> tuple[float, float]:
        """(fraction of source points whose correspondence lies within the max distance of them in 3-D at
        T, RMS distance of those, m; inf when none)."""
        inliers, total = fitness_kernel(self.source.points_xyz, self.target.points_xyz, self.corr,
                                        np.ascontiguousarray(T), self.config.max_correspondence_distance_m**2)
        if inliers == 0:
            return 0.0, float("inf")
        return inliers / self.source.n_points, float(np.sqrt(total / inliers))


def _check_inputs(
    source: PointSet, target: PointSet, T_init: NDArray[np.float64], config: RegistrationConfig
) -> None:
    for name, ps in (("source", source), ("target", target)):
        if ps.points_xyz.ndim != 2 or ps.points_xyz.shape[1] != 3:
            raise InputError(f"{name} points must be (N, 3), got {ps.points_xyz.shape}")
        if ps.covariances.shape != (ps.n_points, 3, 3):
            raise InputError(f"{name} covariances must be ({ps.n_points}, 3, 3), got {ps.covariances.shape}")
        if ps.n_points < MIN_CORRESPONDENCES:
            raise InputError(
                f"{name} scan has {ps.n_points} points; registration needs at least {MIN_CORRESPONDENCES}"
            )
    if config.method in ("mcgicp", "color_icp"):
        wanted = CHANNEL_MODES[config.channels]
        for name, ps in (("source", source), ("target", target)):
            if ps.channel_names != wanted:
                raise InputError(
                    f"{name} scan was prepared with channels {ps.channel_names}, config asks for {wanted}"
                )
    if not is_rigid(np.asarray(T_init, dtype=np.float64)):
        raise TransformError("initial T_target_source is not a finite 4x4 rigid transform")


def register(
    source: PointSet,
    target: PointSet,
    T_target_source_init: NDArray[np.float64] | None = None,
    config: RegistrationConfig | None = None,
) -> RegistrationResult:
    """Estimate T_target_source aligning ``source`` onto ``target``.

    Args:
        source: prepared source scan (``prepare_pointset``), points a_i.
        target: prepared target scan, points b_j.
        T_target_source_init: (4, 4) initial guess; identity when None.
        config: method and settings; default plain GICP.

    Returns:
        RegistrationResult. Scans without overlap give fitness 0 and converged False (no exception).

    Raises:
        InputError: malformed point sets or channels that do not match the config.
        TransformError: a non-rigid initial guess.
    """
    config = RegistrationConfig() if config is None else config
    T = np.eye(4) if T_target_source_init is None else np.array(T_target_source_init, dtype=np.float64)
    _check_inputs(source, target, T, config)
    matcher = _Matcher(source, target, config)
    robust = ROBUST_KERNELS[config.robust_kernel]
    rot_eps = np.radians(config.rotation_eps_deg)
    lm_lambda = config.lm_initial_lambda
    H = np.zeros((6, 6))
    converged = False
    iterations = 0
    used = 0
    history: list[float] = []

    def trial_cost(T_now: NDArray[np.float64]) -> float:
        """The cost at ``T_now`` with the correspondences fixed (a Levenberg-Marquardt trial step)."""
        return float(linearize_kernel(
            source.points_xyz, source.covariances, target.points_xyz, target.covariances, matcher.corr,
            np.ascontiguousarray(T_now), robust, config.robust_scale, N_CHUNKS,
        )[2])  # fmt: skip

    for iteration in range(config.max_iterations):
        H, g, cost, used = matcher.match_linearize(T, robust, N_CHUNKS)
        history.append(float(cost))
        if used < MIN_CORRESPONDENCES:
            break
        iterations = iteration + 1
        if config.optimizer == "gauss_newton":
            delta = _solve(H, g, 0.0)
            T = T @ exp_se3(delta)
        else:
            T, delta, lm_lambda = _levenberg_marquardt_step(T, H, g, cost, lm_lambda, trial_cost)
        if np.linalg.norm(delta[:3]) < rot_eps and np.linalg.norm(delta[3:]) < config.translation_eps_m:
            converged = True  # H, correspondences and fitness are those of the last linearisation
            break
    else:
        matcher.match_linearize(T, robust, N_CHUNKS)  # the correspondences of the final pose
    return _result(T, H, matcher, used, iterations, converged, history, config)


def _levenberg_marquardt_step(T: NDArray[np.float64], H: NDArray[np.float64], g: NDArray[np.float64], cost: float,
                              lm_lambda: float, trial_cost: Callable[[NDArray[np.float64]], float]
                              ) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """One damped step from ``T``: the damping raised tenfold until a step lowers the cost (at most 10 tries),
    lowered tenfold after it. The new pose, the step taken (zero where none lowered the cost) and the damping."""
    for _ in range(10):
        delta = _solve(H, g, lm_lambda)
        T_try = T @ exp_se3(delta)
        if trial_cost(T_try) <= cost:
            return T_try, delta, max(lm_lambda / 10.0, 1e-12)
        lm_lambda *= 10.0
    return T, np.zeros(6), lm_lambda


def _result(T: NDArray[np.float64], H: NDArray[np.float64], matcher: _Matcher, used: int, iterations: int,
            converged: bool, history: list[float], config: RegistrationConfig) -> RegistrationResult:
    """The registration's result at ``T``: fitness and RMSE of its correspondences, the Hessian's eigenvalues
    and conditioning; too few correspondences never converge (no overlap: fitness 0)."""
    fitness, rmse = matcher.fitness_rmse(T)
    if used < MIN_CORRESPONDENCES:
        converged = False
        fitness = 0.0 if used == 0 else fitness
    eig = np.asarray(np.linalg.eigvalsh(0.5 * (H + H.T)), dtype=np.float64)
    return RegistrationResult(
        T_target_source=T,
        fitness=fitness,
        rmse_m=rmse,
        iterations=iterations,
        converged=converged,
        hessian_eigenvalues=eig,
        degenerate=conditioning(H) < config.degeneracy_threshold,
        n_correspondences=int(used),
        cost_history=history,
    )


def conditioning(H: NDArray[np.float64]) -> float:
    """How evenly the Gauss-Newton Hessian H (6, 6; rotation rad, then translation m) fixes the motion: for the
    rotation and the translation each, the smallest over the largest eigenvalue of its information once the
    other is solved for (the Schur complement of the other block); the smaller of the two, 0 where H is
    singular. Each block is in one unit, so the ratio is the squared ratio of the best to the worst fixed
    direction's standard deviation, whatever the scene's size (the 6x6 ratio mixes radians with metres: a
    street 20-50 m across scores 4e-4 to 7e-4 on it however well it is fixed)."""
    H = np.asarray(H, dtype=np.float64)
    H = 0.5 * (H + H.T)
    ratios = []
    for keep, other in ((slice(0, 3), slice(3, 6)), (slice(3, 6), slice(0, 3))):
        try:
            block = H[keep, keep] - H[keep, other] @ np.linalg.solve(H[other, other], H[other, keep])
        except np.linalg.LinAlgError:
            return 0.0
        eig = np.linalg.eigvalsh(0.5 * (block + block.T))
        if not np.all(np.isfinite(eig)) or eig[-1] <= 0:
            return 0.0
        ratios.append(max(float(eig[0] / eig[-1]), 0.0))
    return min(ratios)


def _solve(H: NDArray[np.float64], g: NDArray[np.float64], damping: float) -> NDArray[np.float64]:
    """delta solving (H + damping * diag(H)) delta = -g (least squares when singular)."""
    A = H + damping * np.diag(np.diag(H)) if damping > 0 else H
    try:
        return np.asarray(np.linalg.solve(A, -g))
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(A, -g, rcond=None)[0])
