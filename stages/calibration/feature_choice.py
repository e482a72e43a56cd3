"""Which of a frame's lidar feature channels its images follow: the per-frame sharpness of an objective at
its optimum and a paired test between two of them (``SolverConfig.feature_groups``)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr, stdtrit

from fleetcal.stages.calibration.problem import CalibrationProblem
from fleetcal.stages.calibration.uncertainty import SIGNIFICANCE

SHARPNESS_TURN_DEG = 1.0
"""The turn about each camera axis over which ``frame_sharpness`` measures the score's fall: several image
blurs on every rig measured (KITTI 12 px, a 1600 px 70 deg camera 22 px), so the turned poses score as
misaligned ones, and within the accuracy the calibration must reach."""


CHOICE_POLISH_MIN_STEP = 0.05
"""The choice's polishes from the initial guess stop once their steps are this fraction of their first ones (a
tenth of the box: 0.05 deg / 5 mm in the workflow's box): the sharpness compares the optimum's score with
turns of ``SHARPNESS_TURN_DEG``, twenty times that step."""


def frame_sharpness(problem: CalibrationProblem, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """(F,) how far each frame's score falls from the objective's optimum ``x`` (D,) when the pose is turned
    +-``SHARPNESS_TURN_DEG`` about each camera axis (the mean of the six): how much of the image's edges the
    lidar channels explain at alignment that they do not explain off it."""
    poses = np.repeat(np.asarray(x, dtype=np.float64)[None], 7, axis=0)
    poses[1 + np.arange(6), np.arange(6) % 3] += np.repeat([SHARPNESS_TURN_DEG, -SHARPNESS_TURN_DEG], 3)
    scores = problem.frame_scores(poses)[0]
    return np.asarray(scores[0] - scores[1:].mean(axis=0))


def sharper(sharpness: NDArray[np.float64], than: NDArray[np.float64]) -> bool:
    """Whether the per-frame sharpness ``sharpness`` exceeds ``than`` (same frames) significantly: the mean of
    the frames' differences above their standard error times the Student-t bound with the tail of
    ``uncertainty.SIGNIFICANCE`` normal standard errors (2: 2.3 %; a bound of 2.3 on 10 frames, 14 on 2)."""
    d = np.asarray(sharpness - than, dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size < 2:
        return False
    bound = float(stdtrit(d.size - 1, ndtr(SIGNIFICANCE)))  # scipy.special: scipy.stats takes 0.4 s to import
    return bool(np.mean(d) > bound * float(np.std(d, ddof=1)) / np.sqrt(d.size))
