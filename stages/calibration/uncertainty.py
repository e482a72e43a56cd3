"""Per-axis standard deviations of a calibration estimate, in the (reference) camera's axes.

Its sources, added in quadrature:

- ambiguity: seeded runs that ended elsewhere yet score as well as the best run. "As well" is a test on
  the scene itself: every frame's points are cut into image bands (points are kept in image order), the
  score difference between the two poses is taken band by band, and the difference counts as real only
  where its mean exceeds twice its standard error over the bands. Runs that score clearly worse found
  local optima and say nothing about the estimate; runs that score as well are equally plausible answers,
  and their distance from the best is the uncertainty. Where no other run confirms the best (none ended
  within ``SolverConfig.agree_rotation_deg`` / ``agree_translation_m`` of it), every run counts, alike or
  not: the search found several optima and nothing says the best one is the scene's, so each axis's
  deviation is at least the farthest run's distance along it. A run that does not agree lies at least
  1/sqrt(3) of the agreement distance off along some axis, so twice the deviation then exceeds that distance
  (a root mean square over several runs that disagree on different axes could fall short of it).
- sampling (translation only): where a lidar point lands is known only to its sampling cell, the larger of
  the rings' spacing and a pixel's footprint; a uniform cell of width w has a deviation of w / sqrt(12). At
  the points' typical range that angle is a translation across the line of sight; along the optical axis a
  shift moves a point across the image only by its off-axis tangent, so that deviation is larger by its
  inverse. Sparse rings bias the translation by decimetres (32 beams: nuScenes 31 cm, simulated 22 cm) with
  every other measure confident, which this floor covers; the rotation averages the cell away over many
  edges (a simulated 16-beam street lands within 0.2 deg), so it gets no sampling floor.

- ring aliases: a lidar's rings are cones about its axis, so moving it along that axis by one ring spacing
  at a point's range puts the next ring where the last one was. With sparse rings an image edge matched by
  one ring is matched almost as well by its neighbour, and the score has further optima that far along the
  lidar's axis; the seeded runs tend to share one of them (a simulated 32-beam street: every run 28 cm off
  along the camera's vertical, with the truth's optimum 26 cm away scoring as well). The estimate is moved
  by 1, 2 and 3 ring spacings at the points' typical range either way and polished there
  (``ring_alias_optima``); an optimum found that scores as well is as plausible as the estimate, and twice
  the deviation reaches the farthest such optimum. Only rings sparser than
  ``SolverConfig.sparse_rings_above_deg`` are probed, the rigs measured 18-36 cm off: with finer rings the
  band test, which has little power on a frame or two, also calls poses 8-20 cm away alike where the
  estimate is within a few centimetres (a synthetic 64-beam scene, a simulated open yard and rosette, PJLab
  rig2), and KITTI's moves polish back to within 3 cm of its estimate.

- the objective's own bias (rotation only): the score's optimum next to the truth is not the truth. Climbing
  the objective from the truth itself (``benchmarks/bench_objective_bias.py``) ends 0.0-0.48 deg away over
  the real shared logs and simulated rigs, on simulated rigs too, whose truth is exact; no seeded run, alias
  or sampling cell sees this error, which is common to every part of the scene (a delete-a-band jackknife
  measured 0.02-0.06 deg on KITTI, whose estimates sit 0.15 deg off). Its spread over the rigs,
  ``OBJECTIVE_BIAS_DEG`` about each axis, is added to every rotation deviation, as the sampling cell is to
  the translation's.

- the runs a held translation replaced: where the seeded 6-DoF runs disagree and the runs with the translation
  held at the initial guess's agree, the held estimate is returned (``SolverConfig.translation`` ``auto``). The
  log did not fix the translation, and the 6-DoF runs' spread about the held estimate (their root mean square
  distance on each axis, rotation and translation) is how far it left open; without it a held translation had
  no deviation at all. A translation held by the settings (``hold``, a box 0 m wide) is an input, not an
  estimate, and keeps none (NaN).

- the objective's curvature (translation only): where the score fixes the translation loosely against the
  rotation (``observability.translation_profile`` below 1: a 15 cm move costs less than a 0.5 deg turn), a
  translation as uncertain as the rotation is wider than any of the sources above says
  (``curvature_deviation_m``). Each translation deviation is at least that: on a simulated 32-beam street
  (profile 0.14 along the camera's vertical) 9.6 cm instead of the sampling cell's 3.9 cm, for an estimate
  28 cm off. The larger of the two is kept, not their sum: both say how loosely the log fixes the same
  translation.

- an estimate the log does not confirm (verdict ``suspect``): nothing then says it lies nearer the truth than
  the initial guess it started from, which is one more unconfirmed alternative, so each axis's deviation is
  at least the estimate's distance from that guess (``reaching_initial_guess``), as it is at least the
  farthest run's where no run confirms the best. The verdict is taken before, from the sources above; this
  widens only what it already calls ``suspect``. Over the 72 runs of ``benchmarks/bench_starts.py`` the
  misses were all ``suspect`` estimates in another basin than the truth's (PJLab rig1 30-41 cm along the
  optical axis, nuScenes 0.4 deg and a ring alias away, the 16- and 32-beam streets' aliases), which no
  deviation measured at the estimate reaches.

What they leave out is the translation's share of that bias beyond the sampling cell (KITTI's estimate sits
3.8 cm off along the optical axis with every run agreeing) and a bias larger than the rigs measured. A
sandwich estimate over the image bands (the score's finite-difference curvature against the spread of the
bands' gradients) was measured and removed: GOM is rough at the scale of the steps, so the same KITTI estimate
got 0.01-0.17 deg about one axis with steps of 0.05-0.4 deg, and a simulated street's correct estimate (0.05
deg) got an infinite deviation where one curvature came out positive.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.stages.calibration.metrics import GomScorer
from fleetcal.stages.calibration.problem import CalibrationProblem, ScoringView, embed, evaluate_embedded
from fleetcal.stages.calibration.pso import pattern_search

BANDS_PER_FRAME = 8
"""Image bands per frame whose score differences test whether two poses score alike."""
SIGNIFICANCE = 2.0
"""A score difference is real above this many standard errors over the bands."""
OBJECTIVE_BIAS_DEG = 0.12
"""Standard deviation (degrees) of the objective's own optimum about the truth, about each camera axis: the
root mean square of the per-axis rotation errors of the optimum next to the truth
(``benchmarks/bench_objective_bias.py``, GOM with the workflow's settings) over the four real shared logs
and the eight simulated rigs of ``benchmarks/bench_starts.py``: 0.122 deg over their 36 axes (real logs
0.17, simulated rigs 0.09; the largest 0.40 deg, nuScenes about its optical axis)."""
ALIAS_RINGS = (1, 2, 3)
"""Ring spacings (at the points' typical range) the estimate is moved along the lidar's axis to look for the
optima of neighbouring rings (``ring_alias_optima``)."""
LOCAL_POLISH_STEPS = np.array([0.1, 0.1, 0.1, 0.01, 0.01, 0.01, 0.005])
"""First steps (rotation degrees, translation metres, focal scale) of a polish meant to stay on the optimum
nearest its start (``ring_alias_optima``; ``benchmarks/bench_objective_bias.py`` from the truth)."""


@dataclass
class AxisDeviations:
    """Standard deviations about / along the (reference) camera's x, y, z.

    Attributes:
        rotation_deg: (3,) degrees.
        translation_m: (3,) metres; NaN where the settings held the translation (an input, not an estimate).
        alike_runs: other seeded runs that score as well as the best (their spread is in the deviations).
        alike_aliases: ring-alias optima (``ring_alias_optima``) that score as well as the estimate.
    """

    rotation_deg: NDArray[np.float64]
    translation_m: NDArray[np.float64]
    alike_runs: int
    alike_aliases: int = 0


def camera_delta(T: NDArray[np.float64], T_ref: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6,) rotation vector (degrees) and translation change (metres), in the camera's axes, that take the
    extrinsic ``T_ref`` (camera <- lidar) to ``T``."""
    rotation = Rotation.from_matrix(T[:3, :3] @ T_ref[:3, :3].T).as_rotvec(degrees=True)
    return np.concatenate([rotation, T[:3, 3] - T_ref[:3, 3]])


def reaching_initial_guess(deviations: AxisDeviations, T: NDArray[np.float64],
                           T_init: NDArray[np.float64]) -> AxisDeviations:
    """``deviations`` of the estimate ``T`` raised on each axis to its distance from the initial guess ``T_init``
    (``camera_delta``): what a ``suspect`` estimate reports. A translation held by the settings stays NaN."""
    delta = np.abs(camera_delta(T, T_init))
    return replace(deviations, rotation_deg=np.maximum(deviations.rotation_deg, delta[:3]),
                   translation_m=np.maximum(deviations.translation_m, delta[3:]))


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


def curvature_deviation_m(profile: NDArray[np.float64], rotation_deg: float, step_m: float, step_deg: float,
                          box_m: float) -> NDArray[np.float64]:
    """(3,) deviations (metres) along the camera's axes of a translation as uncertain as the rotation
    (``rotation_deg``), at the exchange rate of the objective's own curvature: the translation profile
    (``observability.translation_profile``) says that moving ``step_m`` along an axis costs ``profile`` times the
    score a turn of ``step_deg`` does, so for a score that falls quadratically a move of
    ``rotation_deg * step_m / (step_deg * sqrt(profile))`` costs what a turn of ``rotation_deg`` does. At most the
    deviation of a uniform spread over the search box (``box_m / sqrt(3)``), which is also the deviation where the
    profile is 0 or below (the move costs nothing); NaN where it is NaN (not measured)."""
    p = np.asarray(profile, dtype=np.float64)
    cap = box_m / np.sqrt(3.0)
    positive = np.where(p > 0, p, 1.0)
    sigma = np.where(p > 0, np.minimum(rotation_deg * step_m / (step_deg * np.sqrt(positive)), cap), cap)
    return np.where(np.isfinite(p), sigma, np.nan)


def objective_floor() -> NDArray[np.float64]:
    """(6,) deviations of the objective's own bias: ``OBJECTIVE_BIAS_DEG`` about each camera axis, none along
    them (the translation's floor is ``sampling_floor``)."""
    return np.array([OBJECTIVE_BIAS_DEG] * 3 + [0.0] * 3)


def ring_alias_optima(problem: CalibrationProblem, x_best: NDArray[np.float64], free: NDArray[np.bool_],
                      ring_spacing_deg: float, range_m: float,
                      view: ScoringView | None = None) -> list[NDArray[np.float64]]:
    """Local optima near the estimate x_best (D,) moved ``ALIAS_RINGS`` ring spacings (``ring_spacing_deg``
    at ``range_m``) either way along the lidar's axis, each polished over the ``free`` parameters by a pattern
    search on ``view`` (None: every point; a seeded run's swarm frames bound the cost on a long log). Moves
    that leave the search box are skipped; none where the translation is held or the ring spacing or range is
    unknown."""
    spacing_m = float(np.radians(ring_spacing_deg) * range_m)
    if not np.any(free[3:6]) or not np.isfinite(spacing_m) or spacing_m <= 0:
        return []
    T_best = problem.T_camera_lidar(x_best)
    axis_camera = T_best[:3, :3] @ np.array([0.0, 0.0, 1.0])
    lower, upper = problem.lower[free], problem.upper[free]
    optima = []
    for rings in ALIAS_RINGS:
        for sign in (-1.0, 1.0):
            T_moved = T_best.copy()
            T_moved[:3, 3] += sign * rings * spacing_m * axis_camera
            x0 = np.asarray(x_best, dtype=np.float64).copy()
            x0[:6] = problem.x_of(T_moved)
            if np.any(x0[free] < lower) or np.any(x0[free] > upper):
                continue
            fit = pattern_search(partial(evaluate_embedded, problem, base=x0, free=free, view=view), x0[free],
                                 LOCAL_POLISH_STEPS[: x0.size][free], lower, upper, min_step_fraction=0.05)
            optima.append(embed(fit.best_x, x0, free)[0])
    return optima


def axis_deviations(problem: CalibrationProblem, x_best: NDArray[np.float64], x_others: list[NDArray[np.float64]],
                    floor: NDArray[np.float64], free: NDArray[np.bool_],
                    x_aliases: list[NDArray[np.float64]] | None = None,
                    x_replaced: list[NDArray[np.float64]] | None = None,
                    confirmed: bool = True) -> AxisDeviations:
    """Per-axis deviations of the estimate ``x_best`` (parameters ``free`` were searched), in quadrature: the
    other seeded runs' estimates ``x_others`` that score as well (``scores_alike``: their root mean square over
    all other runs) or, where no run ``confirmed`` the best, every run (the farthest one's distance on each axis:
    twice it then exceeds the distance of a run that does not agree, on the axis it differs most along), the
    ring-alias optima ``x_aliases`` that score as well (half the farthest one's distance on each axis), the 6-DoF
    runs ``x_replaced`` that a held translation replaced (their root mean square) and ``floor``
    (``sampling_floor``). The translation's are NaN where it was held and nothing was replaced."""
    replaced = list(x_replaced or [])
    translation_held = not np.any(free[3:6]) and not replaced
    variance = np.asarray(floor, dtype=np.float64) ** 2
    T_best = problem.T_camera_lidar(x_best)
    if replaced:
        variance = variance + np.mean([camera_delta(problem.T_camera_lidar(x), T_best) ** 2 for x in replaced], axis=0)
    others, aliases = list(x_others), list(x_aliases or [])
    alike = alike_aliases = 0
    if others or aliases:
        scores = band_scores(problem, np.vstack([x_best, *others, *aliases]), BANDS_PER_FRAME)
        squares, farthest_run, farthest_alias = np.zeros(6), np.zeros(6), np.zeros(6)
        for k, x in enumerate(others + aliases, start=1):
            is_alike = scores_alike(scores[0] - scores[k])
            delta2 = camera_delta(problem.T_camera_lidar(x), T_best) ** 2
            if k <= len(others):
                farthest_run = np.maximum(farthest_run, delta2)
                if is_alike:
                    alike += 1
                    squares += delta2
            elif is_alike:
                alike_aliases += 1
                farthest_alias = np.maximum(farthest_alias, delta2 / 4.0)
        run_variance = squares / max(len(others), 1) if confirmed else farthest_run
        variance = variance + run_variance + farthest_alias
    std = np.sqrt(variance)
    return AxisDeviations(std[:3], np.full(3, np.nan) if translation_held else std[3:], alike, alike_aliases)
