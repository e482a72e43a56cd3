"""Per-axis standard deviations of a calibration estimate, in the (reference) camera's axes.

Three sources, added in quadrature:

- the scene: how far the optimum would move if the scene's image bands were resampled (a sandwich
  estimate): with H the curvature of the mean score at the estimate and S the covariance over the U bands
  of each band's score gradient, ``H^-1 (S / U) H^-1``. Directions in which the score does not fall away
  from the estimate get an infinite deviation.

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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.stages.calibration.metrics import GomScorer
from fleetcal.stages.calibration.problem import CalibrationProblem

ROTATION_STEP_DEG = 0.05
"""Finite-difference step of the curvature and the band gradients: rotation, degrees ..."""
TRANSLATION_STEP_M = 0.005
"""... and translation, metres."""
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


def _steps(dim: int) -> NDArray[np.float64]:
    return np.array([ROTATION_STEP_DEG] * 3 + [TRANSLATION_STEP_M] * 3 + [5e-4] * (dim - 6))[:dim]


def _probes(x: NDArray[np.float64], index: NDArray[np.int64], steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """Central-difference probes of the mean score's Hessian over parameters ``index`` of x: x, then x +- step
    along each, then the four diagonal corners of each pair."""
    probes = [x.copy()]
    for i in index:
        for sign in (1.0, -1.0):
            p = x.copy()
            p[i] += sign * steps[i]
            probes.append(p)
    for a, i in enumerate(index):
        for j in index[a + 1:]:
            for si, sj in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                p = x.copy()
                p[i] += si * steps[i]
                p[j] += sj * steps[j]
                probes.append(p)
    return np.array(probes)


def hessian(f: NDArray[np.float64], index: NDArray[np.int64], steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """(F, F) second derivatives from the scores ``f`` of ``_probes`` over ``index``."""
    n = index.size
    H = np.zeros((n, n))
    for a, i in enumerate(index):
        H[a, a] = (f[1 + 2 * a] - 2.0 * f[0] + f[2 + 2 * a]) / steps[i] ** 2
    k = 1 + 2 * n
    for a in range(n):
        for b in range(a + 1, n):
            pp, pm, mp, mm = f[k:k + 4]
            H[a, b] = H[b, a] = (pp - pm - mp + mm) / (4.0 * steps[index[a]] * steps[index[b]])
            k += 4
    return H


def scene_covariance(problem: CalibrationProblem, x: NDArray[np.float64],
                     free: NDArray[np.bool_]) -> NDArray[np.float64]:
    """(6, 6) covariance in the camera's axes (rotation degrees, translation metres) of the estimate x from the
    scene (sandwich over image bands, see the module's docstring); held parameters contribute nothing,
    directions the score does not fix are infinite."""
    index = np.flatnonzero(free)
    steps = _steps(x.size)
    probes = _probes(x, index, steps)
    H = hessian(problem.evaluate(probes), index, steps)
    bands = band_scores(problem, probes[1:1 + 2 * index.size], BANDS_PER_FRAME)  # (2F, U)
    gradients = ((bands[0::2] - bands[1::2]) / (2.0 * steps[index])[:, None]).T  # (U, F)
    if gradients.shape[0] < 2:  # one unit (a single frame of a metric without bands): nothing to resample
        return np.zeros((6, 6))
    S = np.atleast_2d(np.cov(gradients, rowvar=False)) / gradients.shape[0]
    curvature, basis = np.linalg.eigh(-0.5 * (H + H.T))
    falls = curvature > 0
    inverse = (basis[:, falls] / curvature[falls]) @ basis[:, falls].T
    cov_free = inverse @ S @ inverse
    flat = np.abs(basis[:, ~falls]).sum(axis=1) > 1e-6  # parameters a flat direction moves
    J = _camera_jacobian(problem, x, index, steps)  # (6, F)
    cov = J @ cov_free @ J.T
    infinite = (np.abs(J) @ flat.astype(np.float64)) > 1e-9
    cov[infinite, :] = np.inf
    cov[:, infinite] = np.inf
    return np.asarray(cov)


def _camera_jacobian(problem: CalibrationProblem, x: NDArray[np.float64], index: NDArray[np.int64],
                     steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6, F) derivative of the camera-axes change (``camera_delta``) by the parameters ``index`` at x."""
    T_x = problem.T_camera_lidar(x)
    J = np.zeros((6, index.size))
    for a, i in enumerate(index):
        up, down = x.copy(), x.copy()
        up[i] += steps[i]
        down[i] -= steps[i]
        J[:, a] = (camera_delta(problem.T_camera_lidar(up), T_x)
                   - camera_delta(problem.T_camera_lidar(down), T_x)) / (2.0 * steps[i])
    return J


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
    """Per-axis deviations of the estimate ``x_best`` (parameters ``free`` were searched): the scene's
    (``scene_covariance``), the other seeded runs' estimates ``x_others`` that score as well
    (``scores_alike``: their root mean square over all other runs) and ``floor`` (``sampling_floor``), in
    quadrature."""
    translation_held = not np.any(free[3:6])
    with np.errstate(invalid="ignore"):
        variance = np.maximum(np.diag(scene_covariance(problem, x_best, free)), 0.0)
    variance = variance + np.asarray(floor, dtype=np.float64) ** 2
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
