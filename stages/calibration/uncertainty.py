"""Per-axis standard deviations of a calibration estimate, in the (reference) camera's axes.

Two sources, added in quadrature:

- ambiguity: seeded runs that ended elsewhere yet score as well as the best run. "As well" is a test on
  the scene itself: every frame's points are cut into image bands (points are kept in image order), the
  score difference between the two poses is taken band by band, and the difference counts as real only
  where its mean exceeds twice its standard error over the bands. Runs that score clearly worse found
  local optima and say nothing about the estimate; runs that score as well are equally plausible answers,
  and their distance from the best is the uncertainty.
- sampling (translation only): where a lidar point lands is known only to its sampling cell, the larger of
  the rings' spacing and a pixel's footprint; a uniform cell of width w has a deviation of w / sqrt(12). At
  the points' typical range that angle is a translation across the line of sight; along the optical axis a
  shift moves a point across the image only by its off-axis tangent, so that deviation is larger by its
  inverse. Sparse rings bias the translation by decimetres (32 beams: nuScenes 31 cm, simulated 22 cm) with
  every other measure confident, which this floor covers; the rotation averages the cell away over many
  edges (a simulated 16-beam street lands within 0.2 deg), so it gets no floor.

What they leave out is a bias of the score itself (KITTI's estimate sits 3.8 cm off along the optical axis
with every run agreeing). A sandwich estimate over the image bands (the score's finite-difference curvature
against the spread of the bands' gradients) was measured and removed: GOM is rough at the scale of the
steps, so the same KITTI estimate got 0.01-0.17 deg about one axis with steps of 0.05-0.4 deg, and a
simulated street's correct estimate (0.05 deg) got an infinite deviation where one curvature came out
positive.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.stages.calibration.metrics import GomScorer
from fleetcal.stages.calibration.problem import CalibrationProblem

BANDS_PER_FRAME = 8
"""Image bands per frame whose score differences test whether two poses score alike."""
SIGNIFICANCE = 2.0
"""A score difference is real above this many standard errors over the bands."""


@dataclass
class AxisDeviations:
    """Standard deviations about / along the (reference) camera's x, y, z.

    Attributes:
        rotation_deg: (3,) degrees.
        translation_m: (3,) metres; NaN where the translation was held.
        alike_runs: other seeded runs that score as well as the best (their spread is in the deviations).
    """

    rotation_deg: NDArray[np.float64]
    translation_m: NDArray[np.float64]
    alike_runs: int


def camera_delta(T: NDArray[np.float64], T_ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6,) rotation vector (degrees) and translation change (metres), in the camera's axes, that take the
    extrinsic ``T_ref`` (camera <- lidar) to ``T``."""
    rotation = Rotation.from_matrix(T[:3, :3] @ T_ref[:3, :3].T).as_rotvec(degrees=True)
    return np.concatenate([rotation, T[:3, 3] - T_ref[:3, 3]])


def band_scores(problem: CalibrationProblem, x: NDArray[np.float64], bands: int) -> NDArray[np.float64]:
    """(P, U) scores of parameters x (P, D) on each unit: every frame's GOM points cut into ``bands`` image
    bands (other metrics: the whole frame is one unit)."""
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    T_c0 = problem.T_camera_lidar_batch(x)
    columns = []
    for scorers, T_c_c0 in zip(problem.scorers, problem.T_camera_camera0, strict=True):
        gom = [s for s in scorers if isinstance(s, GomScorer)]
        if not gom:
            columns.append(np.mean([s.score(T_c_c0 @ T_c0).scores for s in scorers], axis=0))
            continue
        for band in range(bands):
            parts = [s.subset(np.array_split(np.arange(s.points.shape[0]), bands)[band]) for s in gom]
            columns.append(np.mean([p.score(T_c_c0 @ T_c0).scores for p in parts], axis=0))
    return np.column_stack(columns)


def scores_alike(differences: NDArray[np.float64]) -> bool:
    """Whether band score differences (U,) are consistent with no difference: their mean within
    ``SIGNIFICANCE`` standard errors of zero."""
    d = np.asarray(differences, dtype=np.float64)
    d = d[np.isfinite(d)]
    if d.size < 2:
        return True
    standard_error = float(np.std(d, ddof=1)) / np.sqrt(d.size)
    return bool(abs(float(np.mean(d))) <= SIGNIFICANCE * standard_error)


def sampling_floor(ring_spacing_deg: float, pixel_deg: float, range_m: float,
                   off_axis: float) -> NDArray[np.float64]:
    """(6,) deviations (rotation degrees: 0, translation metres) of the scan's sampling cell (see the module's
    docstring); NaN inputs count as 0."""
    cell_deg = max(float(np.nan_to_num(ring_spacing_deg)), float(np.nan_to_num(pixel_deg)))
    angle_deg = cell_deg / np.sqrt(12.0)
    across_m = float(np.radians(angle_deg) * np.nan_to_num(range_m))
    along_m = across_m / max(float(np.nan_to_num(off_axis)), 0.1)
    return np.array([0.0, 0.0, 0.0, across_m, across_m, along_m])


def axis_deviations(problem: CalibrationProblem, x_best: NDArray[np.float64], x_others: list[NDArray[np.float64]],
                    floor: NDArray[np.float64], free: NDArray[np.bool_]) -> AxisDeviations:
    """Per-axis deviations of the estimate ``x_best`` (parameters ``free`` were searched): the other seeded
    runs' estimates ``x_others`` that score as well (``scores_alike``: their root mean square over all other
    runs) and ``floor`` (``sampling_floor``), in quadrature."""
    translation_held = not np.any(free[3:6])
    variance = np.asarray(floor, dtype=np.float64) ** 2
    alike = 0
    if x_others:
        scores = band_scores(problem, np.vstack([x_best, *x_others]), BANDS_PER_FRAME)
        T_best = problem.T_camera_lidar(x_best)
        squares = np.zeros(6)
        for k, x in enumerate(x_others, start=1):
            if scores_alike(scores[0] - scores[k]):
                alike += 1
                squares += camera_delta(problem.T_camera_lidar(x), T_best) ** 2
        variance = variance + squares / len(x_others)
    std = np.sqrt(variance)
    return AxisDeviations(std[:3], np.full(3, np.nan) if translation_held else std[3:], alike)
