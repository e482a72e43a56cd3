"""Score slices around an optimum (the paper's Figure 9): rotation about the camera x/y axes
(pitch/yaw of the optical frame; "roll/pitch" slices in the report) and translation along x/y."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError
from fleetcal.stages.calibration.problem import CalibrationProblem


@dataclass
class ScoreLandscape:
    """A 2-D slice of the objective around ``x_centre``.

    Attributes:
        axes: the two parameter indices varied (0-2 rotation vector deg, 3-5 translation m).
        names: their names, e.g. ``("rx_deg", "ry_deg")``.
        offsets_a, offsets_b: (A,), (B,) offsets from the centre along each axis (deg or m).
        scores: (B, A) mean metric over frames (row = offset b, column = offset a).
        centre_score: score at the centre.
    """

    axes: tuple[int, int]
    names: tuple[str, str]
    offsets_a: NDArray[np.float64]
    offsets_b: NDArray[np.float64]
    scores: NDArray[np.float64]
    centre_score: float

    def argmax_offsets(self) -> tuple[float, float]:
        """Offsets (a, b) of the best grid cell."""
        j, i = np.unravel_index(int(np.argmax(self.scores)), self.scores.shape)
        return float(self.offsets_a[i]), float(self.offsets_b[j])


PARAM_NAMES = ("rx_deg", "ry_deg", "rz_deg", "tx_m", "ty_m", "tz_m", "focal_scale")


def score_landscape(problem: CalibrationProblem, x_centre: NDArray[np.floating],
                    axes: tuple[int, int] = (0, 1), half_width: tuple[float, float] = (2.0, 2.0),
                    steps: int = 21) -> ScoreLandscape:
    """Evaluate a ``steps`` x ``steps`` grid over two parameters around ``x_centre`` (one batch call).

    Typical slices: ``axes=(0, 1), half_width=(2, 2)`` (rotation, deg) and ``axes=(3, 4),
    half_width=(0.2, 0.2)`` (translation, m).
    """
    x0 = np.asarray(x_centre, dtype=np.float64).ravel()
    if x0.size != problem.dim or len(set(axes)) != 2 or not all(0 <= a < problem.dim for a in axes):
        raise ConfigError(f"landscape axes {axes} do not fit a {problem.dim}-parameter problem")
    if steps < 2:
        raise ConfigError("landscape needs at least 2 steps per axis")
    off_a = np.linspace(-half_width[0], half_width[0], steps)
    off_b = np.linspace(-half_width[1], half_width[1], steps)
    grid = np.tile(x0, (steps * steps, 1))
    bb, aa = np.meshgrid(off_b, off_a, indexing="ij")
    grid[:, axes[0]] += aa.ravel()
    grid[:, axes[1]] += bb.ravel()
    scores = problem.evaluate(grid).reshape(steps, steps)
    centre = float(problem.evaluate(x0[None])[0])
    return ScoreLandscape(axes, (PARAM_NAMES[axes[0]], PARAM_NAMES[axes[1]]), off_a, off_b, scores, centre)
