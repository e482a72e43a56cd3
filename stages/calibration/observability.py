"""How sharply a log's objective fixes each translation component of a calibration: a profile of the
score along each camera axis, the rotation re-fitted.

Sideways shift and yaw are the classic ridge of targetless calibration: where the scene is far, moving the
camera across the line of sight looks like turning it. The seeded runs' spread only sees such a ridge when
the runs happen to land apart on it; the profile measures it directly. It measures how well the score
fixes a component, not whether the score's optimum is biased (nuScenes' 23 cm along its camera's y is
firm by this measure).
"""

from __future__ import annotations

from functools import partial

import numpy as np
from numpy.typing import NDArray

from fleetcal.stages.calibration.problem import CalibrationProblem, ScoringView, evaluate_embedded
from fleetcal.stages.calibration.pso import pattern_search

AXES = ("x", "y", "z")

_REFIT_STEP_DEG = 0.25  # first pattern-search steps of the re-fit: rotation, degrees ...
_REFIT_STEP_M = 0.02  # ... and translation, metres
_REFIT_STEP_FOCAL = 0.005
_REFIT_MIN_STEP_FRACTION = 0.2
"""The re-fits stop at 0.05 deg / 4 mm: a profile compares score losses of 0.5 deg turns and 15 cm moves, and
stopping at 0.0125 deg / 1 mm instead took KITTI's profile 2.6 k evaluations instead of 1.4 k for the same weak
axes on KITTI, PJLab rig2 and the simulated 16-beam street (ratios within 0.04)."""


def profile_drop(problem: CalibrationProblem, x_best: NDArray[np.float64], best_score: float, index: int,
                 step: float, view: ScoringView | None = None) -> float:
    """Score lost when parameter ``index`` of the estimate ``x_best`` moves ``step`` (degrees or metres)
    either way and every other free parameter is re-fitted by a pattern search from the estimate: the
    smaller of the two losses (0 or below: that far along, the objective does not fix the parameter).
    ``view``: the objective on that view's points (``best_score`` then is its); None: every point."""
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
        objective = partial(evaluate_embedded, problem, base=x0, free=free, view=view)
        fit = pattern_search(objective, x0[free], steps[free], lower[free], upper[free],
                             min_step_fraction=_REFIT_MIN_STEP_FRACTION)
        drops.append(best_score - fit.best_score)
    return float(min(drops))


def translation_profile(problem: CalibrationProblem, x_best: NDArray[np.float64], step_m: float,
                        step_deg: float, view: ScoringView | None = None) -> NDArray[np.float64]:
    """How well the objective fixes each translation component of the estimate, against its rotation:
    the profile loss (``profile_drop``) of a ``step_m`` move along each axis of the (reference) camera,
    divided by the median profile loss of a ``step_deg`` turn about the camera's three axes. A ratio of
    the objective's own curvatures, it is measured on ``view`` where given (None: every point): a seeded run's
    swarm frames (``CalibrationProblem.search_view``) tell the same of a long log at a bounded cost.

    Returns:
        (3,) ratios for the camera's x, y, z: below 1, moving ``step_m`` there costs less than a typical
        ``step_deg`` turn; NaN where the turns cost nothing.
    """
    best_score = float(problem.evaluate(np.asarray(x_best, dtype=np.float64)[None], view)[0])
    turns = float(np.median([profile_drop(problem, x_best, best_score, i, step_deg, view) for i in range(3)]))
    if not turns > 0:
        return np.full(3, np.nan)
    return np.array([profile_drop(problem, x_best, best_score, 3 + i, step_m, view) / turns for i in range(3)])


def weak_axes(profile: NDArray[np.float64], ratio: float) -> list[str]:
    """The axes (of ``AXES``) whose ``translation_profile`` is below ``ratio``."""
    return [AXES[i] for i in range(3) if np.isfinite(profile[i]) and profile[i] < ratio]
