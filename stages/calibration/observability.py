"""How sharply a log's objective fixes each translation component of a calibration: a profile of the
score along each camera axis, the rotation re-fitted.

Sideways shift and yaw are the classic ridge of targetless calibration: where the scene is far, moving the
camera across the line of sight looks like turning it. The seeded runs' spread only sees such a ridge when
the runs happen to land apart on it; the profile measures it directly. It measures how well the score
fixes a component, not whether the score's optimum is biased (nuScenes' 23 cm along its camera's y is
firm by this measure).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.stages.calibration.problem import CalibrationProblem, embed
from fleetcal.stages.calibration.pso import pattern_search

AXES = ("x", "y", "z")

_REFIT_STEP_DEG = 0.25  # first pattern-search steps of the re-fit: rotation, degrees ...
_REFIT_STEP_M = 0.02  # ... and translation, metres
_REFIT_STEP_FOCAL = 0.005
_REFIT_MIN_STEP_FRACTION = 0.05  # down to 0.0125 deg / 1 mm


def _evaluate_embedded(problem: CalibrationProblem, z: NDArray[np.floating], base: NDArray[np.float64],
                       free: NDArray[np.bool_], stride: int = 1) -> NDArray[np.float64]:
    if stride > 1:
        return problem.evaluate(embed(z, base, free), stride=stride)
    return problem.evaluate(embed(z, base, free))


def profile_drop(problem: CalibrationProblem, x_best: NDArray[np.float64], best_score: float, index: int,
                 step: float, stride: int = 1) -> float:
    """Score lost when parameter ``index`` of the estimate ``x_best`` moves ``step`` (degrees or metres)
    either way and every other free parameter is re-fitted by a pattern search from the estimate: the
    smaller of the two losses (0 or below: that far along, the objective does not fix the parameter).
    ``stride``: on the thinned objective (``CalibrationProblem.evaluate``), whose score ``best_score`` is."""
    x_best = np.asarray(x_best, dtype=np.float64)
    dim = x_best.size
    steps = np.array([_REFIT_STEP_DEG] * 3 + [_REFIT_STEP_M] * 3 + [_REFIT_STEP_FOCAL] * (dim - 6))
    widen = np.zeros(dim)
    widen[index] = step  # the moved parameter may step out of the box
    lower, upper = problem.lower - widen, problem.upper + widen
    free = problem.free_parameters()
    free[index] = False
    drops = []
    for sign in (-1.0, 1.0):
        x0 = x_best.copy()
        x0[index] += sign * step
        objective = partial(_evaluate_embedded, problem, base=x0, free=free, stride=stride)
        fit = pattern_search(objective, x0[free], steps[free], lower[free], upper[free],
                             min_step_fraction=_REFIT_MIN_STEP_FRACTION)
        drops.append(best_score - fit.best_score)
    return float(min(drops))


def translation_profile(problem: CalibrationProblem, x_best: NDArray[np.float64], best_score: float,
                        step_m: float, step_deg: float, stride: int = 1) -> NDArray[np.float64]:
    """How well the objective fixes each translation component of the estimate, against its rotation:
    the profile loss (``profile_drop``) of a ``step_m`` move along each axis of the (reference) camera,
    divided by the median profile loss of a ``step_deg`` turn about the camera's three axes.

    Returns:
        (3,) ratios for the camera's x, y, z: below 1, moving ``step_m`` there costs less than a typical
        ``step_deg`` turn; NaN where the turns cost nothing.
    """
    turns = float(np.median([profile_drop(problem, x_best, best_score, i, step_deg, stride) for i in range(3)]))
    if not turns > 0:
        return np.full(3, np.nan)
    return np.array([profile_drop(problem, x_best, best_score, 3 + i, step_m, stride) / turns for i in range(3)])


def weak_axes(profile: NDArray[np.float64], ratio: float) -> list[str]:
    """The axes (of ``AXES``) whose ``translation_profile`` is below ``ratio``."""
    return [AXES[i] for i in range(3) if np.isfinite(profile[i]) and profile[i] < ratio]


ROTATION_STEP_DEG = 0.05  # finite-difference steps of the curvature and the block gradients: rotation, degrees ...
TRANSLATION_STEP_M = 0.005  # ... translation, metres
FOCAL_STEP = 0.0005
UNCERTAINTY_BLOCKS = 8  # image bands per frame whose gradients measure the score's noise


@dataclass
class AxisUncertainty:
    """Standard deviations of an estimate along the (reference) camera's axes.

    Attributes:
        rotation_deg: (3,) about the camera's x, y, z, degrees.
        translation_m: (3,) of the translation (``T_camera_lidar[:3, 3]``) along the camera's x, y, z, metres
            (NaN where the translation was held).
        peaked: False where the score does not fall away from the estimate in every free direction (its
            curvature is not negative definite): those directions get an infinite deviation.
    """

    rotation_deg: NDArray[np.float64]
    translation_m: NDArray[np.float64]
    peaked: bool


def finite_difference_steps(dim: int) -> NDArray[np.float64]:
    """(dim,) steps of the parameters (rotation deg, translation m, focal scale)."""
    return np.array([ROTATION_STEP_DEG] * 3 + [TRANSLATION_STEP_M] * 3 + [FOCAL_STEP] * (dim - 6))[:dim]


def hessian(objective: Callable[[NDArray[np.float64]], NDArray[np.float64]], x: NDArray[np.float64],
            steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """(D, D) central-difference second derivatives of a batched ``objective`` at x (D,), all probes in one
    call (1 + 2 D + 2 D (D - 1) candidates)."""
    dim = x.size
    probes = [x.copy()]
    for i in range(dim):
        for sign in (1.0, -1.0):
            p = x.copy()
            p[i] += sign * steps[i]
            probes.append(p)
    pairs = [(i, j) for i in range(dim) for j in range(i + 1, dim)]
    for i, j in pairs:
        for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            p = x.copy()
            p[i] += si * steps[i]
            p[j] += sj * steps[j]
            probes.append(p)
    f = np.asarray(objective(np.array(probes)), dtype=np.float64)
    H = np.zeros((dim, dim))
    for i in range(dim):
        H[i, i] = (f[1 + 2 * i] - 2.0 * f[0] + f[2 + 2 * i]) / steps[i] ** 2
    base = 1 + 2 * dim
    for k, (i, j) in enumerate(pairs):
        pp, pm, mp, mm = f[base + 4 * k: base + 4 * k + 4]
        H[i, j] = H[j, i] = (pp - pm - mp + mm) / (4.0 * steps[i] * steps[j])
    return H


def unit_gradients(problem: CalibrationProblem, x: NDArray[np.float64], free: NDArray[np.bool_],
                   steps: NDArray[np.float64], blocks: int) -> NDArray[np.float64]:
    """(U, F) central-difference gradients at x over the free parameters of each unit's share of the mean
    score (``CalibrationProblem.unit_scores``: every frame's points cut into ``blocks`` image bands); they
    sum to the mean score's gradient."""
    index = np.flatnonzero(free)
    probes = np.tile(x, (2 * index.size, 1))
    for k, i in enumerate(index):
        probes[2 * k, i] += steps[i]
        probes[2 * k + 1, i] -= steps[i]
    scores = problem.unit_scores(x, probes, blocks)  # (2F, U)
    return np.asarray(((scores[0::2] - scores[1::2]) / (2.0 * steps[index])[:, None]).T)


def curvature_covariance(problem: CalibrationProblem, x: NDArray[np.float64],
                         free: NDArray[np.bool_]) -> tuple[NDArray[np.float64], bool]:
    """Covariance (D, D) of the estimate x from the objective over all frames (sandwich estimate): with H the
    curvature of the mean score at x and S the covariance of the U units' shares of its gradient (each
    frame's points cut into image bands, ``unit_gradients``), ``H^-1 (U S) H^-1``: how far the optimum
    moves when the scene's image bands are resampled. Held parameters get 0; directions in which the score does
    not fall away get an infinite variance (and ``False``: not peaked)."""
    dim = x.size
    steps = finite_difference_steps(dim)
    index = np.flatnonzero(free)
    sub = index.size
    full = partial(_evaluate_embedded, problem, base=x, free=free)
    H = hessian(full, x[free], steps[free])
    grads = unit_gradients(problem, x, free, steps, UNCERTAINTY_BLOCKS)
    S = np.cov(grads, rowvar=False).reshape(sub, sub) * grads.shape[0]
    curvature, basis = np.linalg.eigh(-0.5 * (H + H.T))
    falls = curvature > 0
    pseudo_inverse = (basis[:, falls] / curvature[falls]) @ basis[:, falls].T
    cov_free = pseudo_inverse @ S @ pseudo_inverse
    flat = np.abs(basis[:, ~falls]).sum(axis=1) > 1e-6  # parameters a flat direction moves
    cov_free[flat, :] = np.inf
    cov_free[:, flat] = np.inf
    cov = np.zeros((dim, dim))
    cov[np.ix_(index, index)] = cov_free
    return cov, bool(np.all(falls))


def camera_axes(problem: CalibrationProblem, x: NDArray[np.float64], x_ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6,) the rotation (rotation vector, degrees) and translation change (metres) in the reference camera's
    frame that take the extrinsic of ``x_ref`` to that of x."""
    T = np.asarray(problem.T_camera_lidar(x))
    T_ref = np.asarray(problem.T_camera_lidar(x_ref))
    rotation = Rotation.from_matrix(T[:3, :3] @ T_ref[:3, :3].T).as_rotvec(degrees=True)
    return np.concatenate([rotation, T[:3, 3] - T_ref[:3, 3]])


def sampling_floor(ring_spacing_deg: float, pixel_deg: float, range_m: float,
                   off_axis: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Deviations (3,) (rotation degrees, translation metres, about / along the camera's x, y, z) that no
    number of points averages away: where a lidar point lands is known only to its sampling cell, the larger
    of the rings' spacing and a pixel's footprint (a uniform cell of width w has deviation w / sqrt(12)). An
    angle of that size at the points' typical range ``range_m`` is the translation's across the line of
    sight; along it (z) a shift moves a point across the image only by its off-axis tangent (``off_axis``,
    typical over the points), so z's is that much larger. NaN spacings count as 0."""
    cell_deg = max(float(np.nan_to_num(ring_spacing_deg)), float(np.nan_to_num(pixel_deg)))
    angle_deg = cell_deg / np.sqrt(12.0)
    across_m = float(np.radians(angle_deg) * np.nan_to_num(range_m))
    along_m = across_m / max(float(np.nan_to_num(off_axis)), 0.1)
    return np.full(3, angle_deg), np.array([across_m, across_m, along_m])


def axis_uncertainty(problem: CalibrationProblem, x_best: NDArray[np.float64], free: NDArray[np.bool_],
                     x_runs: list[NDArray[np.float64]],
                     floor: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None) -> AxisUncertainty:
    """Per-axis standard deviations of the estimate ``x_best`` in the camera's axes: the objective's
    curvature over all frames (``curvature_covariance``), carried into the camera's axes, combined with the
    spread about it of other seeded runs' estimates ``x_runs`` (root mean square) and a ``floor`` ((3,)
    rotation degrees, (3,) translation metres, ``sampling_floor``), all added in quadrature."""
    x_best = np.asarray(x_best, dtype=np.float64)
    cov, peaked = curvature_covariance(problem, x_best, free)
    dim = x_best.size
    steps = finite_difference_steps(dim)
    J = np.zeros((6, dim))  # d camera axes / d parameters
    for i in np.flatnonzero(free):
        up, down = x_best.copy(), x_best.copy()
        up[i] += steps[i]
        down[i] -= steps[i]
        J[:, i] = (camera_axes(problem, up, x_best) - camera_axes(problem, down, x_best)) / (2.0 * steps[i])
    with np.errstate(invalid="ignore"):
        finite = np.where(np.isfinite(cov), cov, 0.0)
        variance = np.einsum("ai,ij,aj->a", J, finite, J)
        infinite = (np.abs(J) @ (~np.isfinite(np.diag(cov))).astype(np.float64)) > 0
    variance = np.where(infinite, np.inf, np.maximum(variance, 0.0))
    if x_runs:
        deltas = np.array([camera_axes(problem, np.asarray(x, dtype=np.float64), x_best) for x in x_runs])
        variance = variance + np.mean(deltas ** 2, axis=0)
    if floor is not None:
        variance = variance + np.concatenate(floor) ** 2
    std = np.sqrt(variance)
    translation = std[3:] if np.any(free[3:6]) else np.full(3, np.nan)
    return AxisUncertainty(std[:3], translation, peaked)
