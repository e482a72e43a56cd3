"""Targetless lidar-camera extrinsic calibration (GOM paper): one unknown ``T_camera_lidar`` found by a
particle swarm plus a pattern-search polish over the mean metric of all paired frames.

Parameters searched: ``x = (rx, ry, rz, tx, ty, tz[, focal_scale])``: a rotation vector in degrees
and a translation in metres applied in the (reference) camera frame,
``T_camera0_lidar(x) = T_delta(x) @ T_camera0_lidar_init``; frame k sees
``T_camera_k_lidar = T_camera_k_camera0 @ T_camera0_lidar(x)`` (joint multi-camera).

Large initial errors (KITTI, 2 frames, starts 5 deg / 0.5 m off on random axes, box 10 deg / 1 m):
with the paper's camera-centred sphere, linearised once at the initial guess (paper 3.3), 0 of 10
seeds came within 0.3 deg / 10 cm (errors 1-15 deg; range+normals, 3 repeats: 0.14-0.75 deg / 15-25
cm): the optimum of that fixed objective is not the truth far from it, and re-linearising at the
swarm's optimum does not cure it (two rounds: 0.60 deg / 22 cm -> 0.22 / 10.5 -> 0.38 / 12.5; 0.75 /
25 -> 0.71 / 31 -> 0.67 / 31), nor does linearising at the truth itself (box 2 deg / 0.2 m:
0.18 deg / 21 cm). Lidar gradients taken on the lidar's own sphere do not depend on the initial
translation; with the least-squares fit and neighbours across rings all 10 seeds land within the
bound; ``gradient_viewpoint='auto'`` takes them (see ``SolverConfig.gradient_viewpoint``). A
coarse-to-fine schedule (whole box against image gradients blurred 4x, then a 2 deg / 0.2 m box
re-linearised at its optimum) hurt every case measured (KITTI from tf 1.11 deg / 18 cm vs 0.14 / 8;
simulated street 640x360 intensity 0.53 deg / 8.3 cm vs 0.25 / 1.0) and was removed. What wide boxes
do get is a first swarm phase against blurred image gradients in the same box, with the same lidar
gradients (``SolverConfig.explore``).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
from fleetcal.stages.calibration.config import SolverConfig
from fleetcal.stages.calibration.feature_choice import CHOICE_POLISH_MIN_STEP, frame_sharpness, sharper
from fleetcal.stages.calibration.frame import CalibrationFrame, Mat4, fold_rectification, usable_groups, with_columns
from fleetcal.stages.calibration.observability import AXES, translation_profile, weak_axes
from fleetcal.stages.calibration.problem import (
    CalibrationProblem,
    ScoringView,
    SharedPreparation,
    embed,
    ring_slant_deg,
)
from fleetcal.stages.calibration.pso import pattern_search
from fleetcal.stages.calibration.sphere_gradients import cross_ring_neighbours, ring_spacing_rad, sphere_coordinates
from fleetcal.stages.calibration.timing import (
    TimeShift,
    TimeShiftField,
    TimingEstimate,
    estimate_timing,
    extrinsic_deviation,
)
from fleetcal.stages.calibration.uncertainty import (
    BANDS_PER_FRAME,
    SIGNIFICANCE,
    AxisDeviations,
    axis_deviations,
    band_scores,
    curvature_deviation_m,
    objective_floor,
    reaching_initial_guess,
    ring_alias_optima,
    sampling_floor,
    scores_alike,
)

Verdict = Literal["ok", "recalibrated", "suspect"]


def _more_evidence(frames_used: int) -> str:
    """What a user can do about an uncertain estimate (``frames_used``: the image-scan pairs it came from)."""
    return (f"use more image-scan pairs (--frames, or a longer recording where all were used; this used "
            f"{frames_used}) or a log with more structure near the camera")


@dataclass
class CalibrationResult:
    """Outcome of ``calibrate``.

    Attributes:
        T_camera_lidar: 4x4 estimate (reference camera optical frame <- lidar).
        T_camera_lidar_initial: the initial guess.
        score, initial_score: mean metric over frames at the estimate and at the initial guess.
        frame_scores, frame_initial_scores: (F,) per-frame metric at the estimate / initial guess.
        frames_used: frames in the objective.
        points_used: lidar points per frame after culling and subsampling.
        runtime_s: wall time of building the objective (its lidar gradients) and the optimisation (all repeats), not
            the preparation of frames.
        iterations: swarm iterations + polish steps of the returned run.
        evaluations: candidate poses scored over all repeats, as poses scored on every point of the frames they
            were scored on (a swarm's screening pass over a quarter of the points counts a quarter).
        verdict: ``ok`` (initial guess confirmed), ``recalibrated`` or ``suspect`` (``_suspect_reason``: GOM
            below ``gom_suspect_below``, a flat optimum, sparse rings slanted across the image, an estimate
            at the edge of the search box or on a frame's overlap limit, a single run in a
            ``SolverConfig.wide_box``, which nothing confirms; twice a per-axis standard deviation
            (``std_rotation_deg`` / ``std_translation_m``; where no other seeded run agrees with the returned
            one, at least the farthest run's distance along the axis; for a translation held where the 6-DoF
            runs disagreed, ``SolverConfig.translation``, those runs' spread) beyond ``agree_rotation_deg`` /
            ``agree_translation_m``; or the box's edge within twice those deviations).
        verdict_reason: why ``suspect`` (empty otherwise).
        flat: True when the optimum is not distinct from its neighbourhood.
        rotation_std_deg, translation_std_m: RMS deviation of the repeats from the returned estimate
            (NaN with one repeat).
        agreeing_repeats: other seeded runs within ``agree_rotation_deg`` / ``agree_translation_m`` of
            the returned estimate.
        focal_scale: estimated fx/fy scale (1.0 unless ``estimate_focal``).
        metric: metric name.
        gradient_viewpoint: viewpoint of the lidar gradients that was used (``auto`` resolved).
        ring_smoothing_px: largest across-ring smoothing of the image gradients over the frames, pixels
            (0: none; see ``SolverConfig.ring_smoothing``).
        translation_held: the translation was not estimated but kept at the initial guess's
            (``SolverConfig.translation``); ``translation_std_m`` is then NaN.
        translation_profile: (3,) how well the objective fixes the translation along the (reference)
            camera's x, y, z against its rotation (``observability.translation_profile``: profile loss of a
            ``SolverConfig.profile_translation_m`` move over the median loss of a ``profile_rotation_deg``
            turn); NaN where not measured (held translation, profile off).
        weak_translation_axes: the axes whose ratio is below ``SolverConfig.weak_translation_ratio``:
            the log fixes those components only roughly.
        ring_spacing_deg: median angle between the lidar's neighbouring rings over the frames, degrees
            (``sphere_gradients.ring_spacing_rad``; NaN where the scans do not tell).
        sparse_rings: ``ring_spacing_deg`` above ``SolverConfig.sparse_rings_above_deg``: the translation
            of such rigs is rough (biased by decimetres) even where the verdict is confident.
        ring_slant_deg: median over the frames of how far the lidar's rings cross the image slanted at the
            initial guess, degrees (``problem.ring_slant_deg``: 0 level, 90 upright; NaN where the rings circle
            the image). Sparse rings slanted more than ``SolverConfig.slanted_rings_above_deg`` make the
            verdict ``suspect``.
        std_rotation_deg, std_translation_m: (3,) standard deviations about / along the (reference) camera's
            x, y, z, degrees / metres (``uncertainty.axis_deviations``: seeded runs that score as well as the
            best, or the farthest of all where none confirms it, the scan's sampling cell for the translation and the
            objective's own bias, ``uncertainty.OBJECTIVE_BIAS_DEG``, for the rotation; a held translation's the
            spread of the 6-DoF runs it replaced); translation NaN where the settings held it (``translation =
            "hold"``). The verdict is ``suspect`` where twice a deviation exceeds ``agree_rotation_deg`` /
            ``agree_translation_m``; a ``suspect`` estimate's deviations then reach its initial guess on every
            axis (``uncertainty.reaching_initial_guess``).
        alike_runs: other seeded runs that score as well as the best.
        alike_aliases: optima one to three lidar rings away along the lidar's axis that score as well as the
            best (``uncertainty.ring_alias_optima``; probed on rings sparser than ``sparse_rings_above_deg``).
        time_offset_s, time_offset_std_s: the camera's clock minus the lidar's and its deviation, seconds
            (``SolverConfig.estimate_time_offset``); NaN where not estimated; where the log's motion does
            not constrain it, NaN with an infinite deviation (unobservable). An offset's deviation times the
            rig's mean velocity is part of ``std_translation_m``.
        feature_columns: the columns of the frames' lidar feature the objective used, where
            ``SolverConfig.feature_groups`` offered alternatives (None: every column).
        readout_s, readout_std_s: the rolling-shutter readout used (the frames' own, or estimated with
            ``estimate_readout``, then with its deviation; unobservable as for the offset), seconds.
    """

    T_camera_lidar: Mat4
    T_camera_lidar_initial: Mat4
    score: float
    initial_score: float
    frame_scores: NDArray[np.float64]
    frame_initial_scores: NDArray[np.float64]
    frames_used: int
    points_used: list[int]
    runtime_s: float
    iterations: int
    evaluations: int
    verdict: Verdict
    verdict_reason: str
    flat: bool
    rotation_std_deg: float
    translation_std_m: float
    agreeing_repeats: int
    focal_scale: float
    metric: str
    gradient_viewpoint: str
    ring_smoothing_px: float = 0.0
    translation_held: bool = False
    translation_profile: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    weak_translation_axes: list[str] = dataclasses.field(default_factory=list)
    ring_spacing_deg: float = float("nan")
    sparse_rings: bool = False
    ring_slant_deg: float = float("nan")
    std_rotation_deg: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    std_translation_m: NDArray[np.float64] = dataclasses.field(default_factory=lambda: np.full(3, np.nan))
    alike_runs: int = 0
    alike_aliases: int = 0
    time_offset_s: float = float("nan")
    time_offset_std_s: float = float("nan")
    readout_s: float = float("nan")
    readout_std_s: float = float("nan")
    feature_columns: tuple[int, ...] | None = None


PARAMETER_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz", "focal_scale")
PARAMETER_UNITS = (" deg", " deg", " deg", " m", " m", " m", "")  # as printed after the value


def box_edge(x: NDArray[np.float64], lower: NDArray[np.float64], upper: NDArray[np.float64],
             fraction: float, free: NDArray[np.bool_] | None = None,
             margin: NDArray[np.float64] | None = None) -> list[str]:
    """The parameters of x (of those ``free`` to move, default all) that lie within ``fraction`` of the
    box's half-width from its edge, or within ``margin`` (per parameter, in its units; NaN: none) of it,
    each described as ``"ty = -0.500 m (box -0.500..0.500)"``."""
    half = 0.5 * (upper - lower)
    centre = 0.5 * (upper + lower)
    reach = fraction * half
    if margin is not None:  # parameters beyond the margin's (a focal scale) keep the fraction
        given = np.nan_to_num(np.asarray(margin, dtype=np.float64))[: x.size]
        reach[: given.size] = np.maximum(reach[: given.size], given)
    at_edge = np.abs(x - centre) >= half - reach
    if free is not None:
        at_edge &= free
    return [f"{PARAMETER_NAMES[i]} = {x[i]:+.3f}{PARAMETER_UNITS[i]} (box {lower[i]:+.3f}..{upper[i]:+.3f})"
            for i in np.flatnonzero(at_edge)]


def _flat(problem: CalibrationProblem, x_best: NDArray[np.float64], best: float, chance: float) -> bool:
    cfg = problem.config
    probes = np.tile(x_best, (6, 1))
    for i in range(3):
        probes[2 * i, i] += cfg.flat_probe_deg
        probes[2 * i + 1, i] -= cfg.flat_probe_deg
    drop = best - float(np.mean(problem.evaluate(probes)))
    return drop < cfg.flat_fraction * max(abs(best - chance), 1e-12)


@dataclass(frozen=True)
class SearchProgress:
    """Where a running search stands, as reported to a ``calibrate(..., progress=...)`` callback.

    Attributes:
        run: the seeded run in flight (1-based).
        runs: the runs planned so far (confirmation and held-translation runs add to it).
        iteration: the swarm iteration just finished in that run.
        best_score: the best score of the run in flight so far.
        elapsed_s: seconds since the search began.
        fraction: estimated fraction of the search done, in [0, 1).
        eta_s: estimated seconds left (NaN before the first iteration).
    """

    run: int
    runs: int
    iteration: int
    best_score: float
    elapsed_s: float
    fraction: float
    eta_s: float


ProgressCallback = Callable[[SearchProgress], None]


class _SearchClock:
    """Turns swarm iterations into ``SearchProgress`` reports: a run is expected to take as many iterations as
    the finished runs took on average (half of ``max_iterations`` before the first has finished)."""

    def __init__(self, callback: ProgressCallback | None, runs: int, max_iterations: int) -> None:
        self.callback = callback
        self.runs = runs
        self.finished: list[int] = []
        self.max_iterations = max_iterations
        self.start = time.perf_counter()

    def iteration(self, iteration: int, best_score: float) -> None:
        if self.callback is None:
            return
        expected = float(np.mean(self.finished)) if self.finished else 0.5 * self.max_iterations
        done = len(self.finished) + min(iteration / max(expected, 1.0), 0.95)
        runs = max(self.runs, len(self.finished) + 1)
        fraction = min(done / runs, 0.99)
        elapsed = time.perf_counter() - self.start
        eta = elapsed * (1.0 - fraction) / fraction if fraction > 0 else float("nan")
        self.callback(SearchProgress(len(self.finished) + 1, runs, iteration, best_score, elapsed, fraction, eta))

    def run_done(self, iterations: int) -> None:
        self.finished.append(iterations)


@dataclass
class _Run:
    """One seeded swarm + polish run: its best score, parameters, extrinsic and iterations."""

    score: float
    x: NDArray[np.float64]
    T_camera_lidar: Mat4
    iterations: int


def _best_of(problem: CalibrationProblem, seed: int, hold_translation: bool, clock: _SearchClock) -> _Run:
    problem.on_iteration = clock.iteration
    swarm, polish = problem.optimise(seed, hold_translation)
    clock.run_done(swarm.iterations)
    best = polish if polish is not None else swarm
    return _Run(best.best_score, best.best_x, problem.T_camera_lidar(best.best_x),
                swarm.iterations + (polish.iterations if polish is not None else 0))


def agreeing_repeats(T_runs: list[Mat4], best: int, rotation_deg: float, translation_m: float) -> int:
    """How many of the runs' estimates other than ``T_runs[best]`` lie within ``rotation_deg`` and
    ``translation_m`` of it."""
    return sum(1 for i, T in enumerate(T_runs) if i != best
               and rotation_error_deg(T, T_runs[best]) <= rotation_deg
               and translation_error_m(T, T_runs[best]) <= translation_m)


def _agreeing(runs: list[_Run], best: int, cfg: SolverConfig) -> int:
    """Runs confirming ``runs[best]`` (``agreeing_repeats``)."""
    return agreeing_repeats([run.T_camera_lidar for run in runs], best, cfg.agree_rotation_deg,
                            cfg.agree_translation_m)


def _seeded_runs(problem: CalibrationProblem, cfg: SolverConfig, hold_translation: bool,
                 clock: _SearchClock, first: _Run | None = None) -> tuple[list[_Run], int]:
    """``repeats`` seeded runs (``first``: the first seed's, already run) and the index of the best, plus up to
    ``confirm_repeats`` more while no run confirms it. A further run replaces the best only where it scores
    clearly higher (``_clearly_better``): one that scores as well confirms nothing and does not move the
    estimate."""
    runs = [first if r == 0 and first is not None else _best_of(problem, cfg.seed + r, hold_translation, clock)
            for r in range(cfg.repeats)]
    best = int(np.argmax([run.score for run in runs]))
    while cfg.repeats > 1 and len(runs) < cfg.repeats + cfg.confirm_repeats and _agreeing(runs, best, cfg) == 0:
        clock.runs += 1
        runs.append(_best_of(problem, cfg.seed + len(runs), hold_translation, clock))
        if _clearly_better(problem, runs[-1], runs[best]):
            best = len(runs) - 1
    return runs, best


def _prepared(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4, cfg: SolverConfig,
              shared: SharedPreparation | None = None) -> tuple[CalibrationProblem, TimeShiftField | None]:
    """The objective of ``frames`` about the initial guess and its clock field, the points of cameras with a
    known rolling shutter moved to their rows' times (``shared``: what another feature's objective of the same
    frames measured, ``SharedPreparation``)."""
    problem = CalibrationProblem(frames, T_camera_lidar_init, cfg, shared)
    clock_field = _time_field(problem)
    if clock_field is not None and any(clock_field.readouts):
        clock_field.apply(TimeShift(), clock_field.row_fractions(problem.centre))
    return problem, clock_field


_Prepared = tuple[CalibrationProblem, TimeShiftField | None]


def _feature_problem(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4, cfg: SolverConfig, hold: bool,
                     clock: _SearchClock) -> tuple[_Prepared, tuple[int, ...] | None, _Run | None]:
    """The objective of the first feature group (``SolverConfig.feature_groups``), or of another whose score
    the frames show falling significantly further off its optimum (``frame_sharpness``, ``sharper``); that
    group's columns (None: no groups) and the first seeded run where one was searched to choose.

    Each group's sharpness is measured on every frame at its own optimum, polished from a trusted start (the
    initial guess) on the first seeded run's swarm frames (``search_view``), so the choice costs two polishes,
    not a search (``_chosen_from_start``); from a start the box's width says is not trusted
    (``SolverConfig.wide_box``), at the optimum polished over every frame from the first seeded run's estimate
    on the first group (``_chosen_from_first_run``)."""
    groups = usable_groups(frames, cfg.feature_groups) if cfg.metric == "gom" else []
    if not groups:
        return _prepared(frames, T_camera_lidar_init, cfg), None, None
    if len(groups) == 1 or len(frames) < 2:  # one frame: no spread to test a difference against
        return _prepared(with_columns(frames, groups[0]), T_camera_lidar_init, cfg), groups[0], None
    if cfg.wide_box:
        return _chosen_from_first_run(frames, T_camera_lidar_init, cfg, hold, clock, groups)
    prepared, chosen = _chosen_from_start(frames, T_camera_lidar_init, cfg, hold, groups)
    return prepared, chosen, None


def _chosen_from_start(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4, cfg: SolverConfig, hold: bool,
                       groups: list[tuple[int, ...]]) -> tuple[_Prepared, tuple[int, ...]]:
    """The chosen group's objective and columns, each group's sharpness measured at the optimum a polish from
    the initial guess reaches. One group's objective is held at a time (a log's lidar gradients and image twins
    for each): the groups are measured last to first, so the first, which most real logs keep, is still held at
    the end and only another that wins is built again."""
    sharpness: dict[tuple[int, ...], NDArray[np.float64]] = {}
    held: _Prepared | None = None
    shared = SharedPreparation()
    for group in reversed(groups):
        held = None  # freed before the next one is built
        held = _prepared(with_columns(frames, group), T_camera_lidar_init, cfg, shared)
        sharpness[group] = frame_sharpness(held[0], _polished(held[0], None, hold, cfg.seed))
    chosen = _sharpest(groups, sharpness)
    if chosen != groups[0] or held is None:
        held = None
        held = _prepared(with_columns(frames, chosen), T_camera_lidar_init, cfg, shared)
    return held, chosen


def _chosen_from_first_run(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4, cfg: SolverConfig, hold: bool,
                           clock: _SearchClock, groups: list[tuple[int, ...]]) -> tuple[
                               _Prepared, tuple[int, ...], _Run | None]:
    """``_feature_problem`` in a wide box: the first seeded run searches the first group's objective, and each
    group's sharpness is measured at the optimum a polish over every frame reaches from that run's estimate. The
    first group's objective is held while the others are measured, as its run is returned where it wins."""
    shared = SharedPreparation()
    first_prepared = _prepared(with_columns(frames, groups[0]), T_camera_lidar_init, cfg, shared)
    first = _best_of(first_prepared[0], cfg.seed, hold, clock)
    sharpness = {groups[0]: frame_sharpness(first_prepared[0], _polished(first_prepared[0], first, hold, cfg.seed))}
    kept = first_prepared
    for group in groups[1:]:
        other = _prepared(with_columns(frames, group), T_camera_lidar_init, cfg, shared)
        sharpness[group] = frame_sharpness(other[0], _polished(other[0], first, hold, cfg.seed))
        if _sharpest(groups, sharpness) == group:
            kept = other
        del other
    chosen = _sharpest(groups, sharpness)
    if chosen != groups[0]:  # every run on the chosen objective: the first run is searched again
        clock.runs += 1
        return kept, chosen, None
    return kept, chosen, first


def _sharpest(groups: list[tuple[int, ...]], sharpness: dict[tuple[int, ...], NDArray[np.float64]]) -> tuple[int, ...]:
    """The first of ``groups``, or a later one whose per-frame ``sharpness`` (of those measured) is significantly
    sharper (``sharper``) than the first's and than every group chosen over it before."""
    chosen = groups[0]
    for group in groups[1:]:
        if group in sharpness and sharper(sharpness[group], sharpness[chosen]):
            chosen = group
    return chosen


def _polished(problem: CalibrationProblem, run: _Run | None, hold: bool, seed: int) -> NDArray[np.float64]:
    """The parameters a polish on ``problem`` reaches over every frame from ``run``'s (another feature's
    estimate), or where ``run`` is None from the initial guess (the box's centre) on the seed's swarm frames."""
    if run is None:
        return problem.polish_on_view(problem.centre, hold, seed, CHOICE_POLISH_MIN_STEP).best_x
    return problem.polish_everywhere(run.x, hold, float(problem.evaluate(run.x[None])[0])).best_x


def _clearly_better(problem: CalibrationProblem, run: _Run, than: _Run) -> bool:
    """Whether ``run`` scores higher than ``than`` by more than the scene's own noise (the image-band test,
    ``uncertainty.scores_alike``)."""
    if run.score <= than.score:
        return False
    scores = band_scores(problem, np.vstack([run.x, than.x]), BANDS_PER_FRAME)
    return not scores_alike(scores[0] - scores[1])


def searched_objective(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4,
                       config: SolverConfig | None = None) -> tuple[CalibrationProblem, tuple[int, ...] | None]:
    """The objective ``calibrate`` searches from ``T_camera_lidar_init``: its ``auto`` rules resolved and its
    feature group chosen as there (``_feature_problem``); and that group's columns (None: every column)."""
    cfg = resolve_auto_rules(frames, T_camera_lidar_init, config or SolverConfig())
    clock = _SearchClock(None, cfg.repeats, cfg.max_iterations)
    (problem, _), columns, _ = _feature_problem(frames, T_camera_lidar_init, cfg, cfg.holds_translation, clock)
    return problem, columns


def resolve_auto_rules(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4,
                      config: SolverConfig) -> SolverConfig:
    """``config`` with the data part of the ``auto`` rules applied (GOM only):

    - for a scan whose rings are so sparse that its points have fewer than 2 of their ``sphere_k`` nearest
      neighbours on other rings (``cross_ring_neighbours`` on the first frame's lidar sphere), where the box
      alone would explore, exploration is left off (see ``SolverConfig.explore``);
    - for sparse rings slanted across the image (``slanted_sparse_rings``), ``neighbours_by`` is ``angle``:
      ``sampling`` stretches the sphere's polar angle, which assumes rings that run level across the image
      (see ``SolverConfig.slanted_rings_above_deg``).
    """
    if config.metric != "gom" or not frames:
        return config
    changes: dict[str, Any] = {}
    if config.neighbours_by == "auto" and _slanted_sparse_scans(frames, T_camera_lidar_init, config):
        changes["neighbours_by"] = "angle"
    if config.explore == "auto" and config.explores:
        points = np.asarray(frames[0].points_xyz, dtype=np.float64)
        points = points[np.all(np.isfinite(points), axis=1)]
        R = (np.asarray(fold_rectification(frames[0]).T_camera_camera0) @ np.asarray(T_camera_lidar_init))[:3, :3]
        if cross_ring_neighbours(sphere_coordinates(points @ R.T), config.sphere_k) < 2:
            changes["explore"] = "off"
    return dataclasses.replace(config, **changes) if changes else config


def _slanted_sparse_scans(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4,
                          config: SolverConfig) -> bool:
    """``slanted_sparse_rings`` of the frames' medians at the initial guess (the ring spacing, a k-d tree
    probe per frame, is measured only where the rings are slanted)."""
    T0 = np.asarray(T_camera_lidar_init, dtype=np.float64)
    folded = [fold_rectification(f) for f in frames]
    slant_deg = _finite_median([ring_slant_deg(f.camera, np.asarray(f.T_camera_camera0) @ T0) for f in folded])
    if not slant_deg > config.slanted_rings_above_deg:
        return False
    return slanted_sparse_rings(_finite_median([ring_spacing_rad(f.points_xyz) for f in folded], np.degrees),
                                slant_deg, config)


def slanted_sparse_rings(ring_deg: float, slant_deg: float, config: SolverConfig) -> bool:
    """Rings further apart than ``sparse_rings_above_deg`` that cross the image slanted more than
    ``slanted_rings_above_deg`` (False where either is NaN)."""
    return bool(ring_deg > config.sparse_rings_above_deg and slant_deg > config.slanted_rings_above_deg)


@dataclass
class _Searched:
    """The seeded runs ``calibrate`` returns the best of (``best``), whether their translation was held, the
    6-DoF runs a held translation replaced (their spread is its deviation) and how many runs confirm the best
    (``_agreeing``)."""

    runs: list[_Run]
    best: int
    hold: bool
    replaced: list[_Run]
    agreeing: int

    @property
    def confirmed(self) -> bool:
        """One run, or another seeded run within ``agree_rotation_deg`` / ``agree_translation_m`` of the best."""
        return len(self.runs) < 2 or self.agreeing > 0


def _searched(problem: CalibrationProblem, cfg: SolverConfig, hold: bool, clock: _SearchClock,
              first: _Run | None) -> _Searched:
    """The seeded runs (``_seeded_runs``); where no 6-DoF run confirms another from a trusted start (``auto``),
    runs with the translation held at the initial guess's, which replace them where they confirm one another
    and the best 6-DoF run does not score clearly higher (then the scene fixes the translation)."""
    runs, best = _seeded_runs(problem, cfg, hold, clock, first)
    agreeing = _agreeing(runs, best, cfg)
    if (cfg.translation == "auto" and not hold and not cfg.wide_box and cfg.repeats > 1
            and agreeing == 0):  # the translation may be what the runs disagree on
        clock.runs += cfg.repeats
        held_runs, held_best = _seeded_runs(problem, cfg, True, clock)
        held_agreeing = _agreeing(held_runs, held_best, cfg)
        if (held_agreeing > 0  # fewer unknowns, confirmed: preferred to an unconfirmed 6 DoF
                and not _clearly_better(problem, runs[best], held_runs[held_best])):  # unless the scene says not
            return _Searched(held_runs, held_best, True, runs, held_agreeing)
    return _Searched(runs, best, hold, [], agreeing)


@dataclass
class _Estimate:
    """The best run refined: its score, parameters (D,), iterations, the clock it was refined under (None: not
    estimated) and its translation profile (``observability.translation_profile``; NaN: not measured)."""

    score: float
    x: NDArray[np.float64]
    iterations: int
    timing: TimingEstimate | None
    profile: NDArray[np.float64]


def _refined(problem: CalibrationProblem, cfg: SolverConfig, searched: _Searched, clock_field: TimeShiftField | None,
             swarm_view: ScoringView) -> _Estimate:
    """The best run polished on every frame (where its swarm scored fewer), refined under the clock offset and
    readout asked for, and its translation profiled."""
    best = searched.runs[searched.best]
    score, x, iterations = best.score, best.x, best.iterations
    if cfg.polish and swarm_view is not problem.full:  # the runs were polished on their swarms' frames
        polished = problem.polish_everywhere(x, searched.hold, score)
        score, x, iterations = polished.best_score, polished.best_x, iterations + polished.iterations
    timing = _estimate_timing(problem, clock_field, x, searched.hold, cfg)
    if timing is not None:
        score, x = timing.score, timing.x
    profile = np.full(3, np.nan)
    if not searched.hold and cfg.profile_translation_m > 0:
        profile = translation_profile(problem, x, cfg.profile_translation_m, cfg.profile_rotation_deg, swarm_view)
    return _Estimate(score, x, iterations, timing, profile)


def _final_frame_scores(problem: CalibrationProblem, cfg: SolverConfig, x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-frame scores (F,) at ``x``.

    Raises:
        ProcessingError: the camera sees fewer than ``min_points`` lidar points there.
    """
    scores, counts = problem.frame_scores(x[None])
    if int(counts.sum()) < cfg.min_points:
        raise ProcessingError(
            f"the camera sees {int(counts.sum())} lidar points at the best pose in the search box "
            f"(+-{cfg.search_deg} deg, +-{cfg.search_m} m around the initial guess); need {cfg.min_points}")
    return np.asarray(scores[0])


def _estimate_T(problem: CalibrationProblem, estimate: _Estimate, clock_field: TimeShiftField | None) -> Mat4:
    """The estimate's extrinsic, with the mean ego-motion the searched extrinsic absorbed taken out where the
    frames move (``TimeShiftField.extrinsic_correction``)."""
    T_best = problem.T_camera_lidar(estimate.x)
    if clock_field is not None:
        shift = estimate.timing.shift if estimate.timing is not None else TimeShift()
        T_best = T_best @ clock_field.extrinsic_correction(shift, clock_field.row_fractions(estimate.x))
    return T_best


def _run_spread(searched: _Searched, T_best: Mat4) -> tuple[float, float]:
    """Root mean square rotation (deg) and translation (m) distance of the runs from ``T_best``; NaN with one run
    (the translation's also where it was held)."""
    if len(searched.runs) < 2:
        return float("nan"), float("nan")
    Ts = [run.T_camera_lidar for run in searched.runs]
    rotation = float(np.sqrt(np.mean([rotation_error_deg(T, T_best) ** 2 for T in Ts])))
    translation = (float("nan") if searched.hold
                   else float(np.sqrt(np.mean([translation_error_m(T, T_best) ** 2 for T in Ts]))))
    return rotation, translation


@dataclass
class _Rings:
    """A scan's rings over the frames (medians): their spacing and how far they cross the image slanted, degrees
    (NaN: untold)."""

    spacing_deg: float
    slant_deg: float


def _deviations(problem: CalibrationProblem, cfg: SolverConfig, searched: _Searched, estimate: _Estimate,
                rings: _Rings, clock_field: TimeShiftField | None, T_best: Mat4,
                swarm_view: ScoringView) -> tuple[AxisDeviations, list[str]]:
    """The estimate's per-axis deviations (``uncertainty.axis_deviations``: the other runs, ring aliases on
    sparse rings, the replaced runs and the sampling, clock and objective floors), each translation raised to
    the score's curvature (``_curvature_loosened``), and the axes that raising widened beyond the accuracy
    asked."""
    range_m, off_axis = problem.typical_range_and_off_axis()
    free = problem.free_parameters(searched.hold)
    aliases = (ring_alias_optima(problem, estimate.x, free, rings.spacing_deg, range_m, swarm_view)
               if cfg.metric == "gom" and rings.spacing_deg > cfg.sparse_rings_above_deg else [])  # GOM: image bands
    floor = np.linalg.norm([sampling_floor(rings.spacing_deg, problem.pixel_deg(), range_m, off_axis),
                            _timing_floor(clock_field, estimate.timing, cfg, T_best), objective_floor()], axis=0)
    others = [run.x for i, run in enumerate(searched.runs) if i != searched.best]
    deviations = axis_deviations(problem, estimate.x, others, floor, free, aliases,
                                 [run.x for run in searched.replaced], confirmed=searched.confirmed)
    return deviations, _curvature_loosened(deviations, estimate.profile, cfg)


def _suspect_reason(problem: CalibrationProblem, cfg: SolverConfig, searched: _Searched, estimate: _Estimate,
                    deviations: AxisDeviations, loose: list[str], rings: _Rings, flat: bool, auto_angle: bool,
                    frames_used: int) -> str:
    """Why the estimate is ``suspect``, with what the user can do; "" where nothing is wrong. The first that
    applies of: a score no better than chance, a flat optimum, sparse slanted rings, the box's edge, the
    overlap limit, one run in a wide box, deviations beyond the accuracy asked, the box's edge within twice
    the deviations."""
    x, free = estimate.x, problem.free_parameters(searched.hold)
    if cfg.metric == "gom" and estimate.score < cfg.gom_suspect_below:
        return (f"GOM {estimate.score:.3f} is below {cfg.gom_suspect_below}: the lidar's edges and the image's hardly "
                "line up anywhere in the search box; check that the topics see the same scene, the camera's "
                "intrinsics and the initial guess")
    if flat:
        return "flat optimum: turning the estimate 1 deg barely changes the score; " + _more_evidence(frames_used)
    if cfg.metric == "gom" and slanted_sparse_rings(rings.spacing_deg, rings.slant_deg, cfg):  # measured on GOM only
        return (f"the lidar's rings lie {rings.spacing_deg:.2f} deg apart and cross the image slanted "
                f"{rings.slant_deg:.0f} deg (sphere neighbours by angle{', auto' if auto_angle else ''}): rings this "
                "sparse and slanted leave the rotation uncertain by tenths of a degree or more; check the estimate "
                "against a reference before using it")
    if edge := box_edge(x, problem.lower, problem.upper, cfg.box_edge_fraction, free):
        return (f"the estimate is at the edge of the search box ({'; '.join(edge)}): the best pose may lie "
                "outside it; check the initial guess or widen --search-deg / --search-m")
    if on_limit := (problem.overlap_limited(x, cfg.box_edge_fraction) if cfg.min_overlap_fraction > 0 else []):
        return (f"the estimate sits on the overlap limit ({'; '.join(on_limit)}): fewer lidar points in view "
                "would have scored higher; check the initial guess")
    if len(searched.runs) == 1 and cfg.wide_box:
        return (f"one seeded run in a wide search box (+-{cfg.search_deg:g} deg, +-{cfg.search_m:g} m) with no "
                "other run to confirm it: far optima lie in such a box; set calibration.repeats to 2 or more")
    if uncertain := _uncertain_axes(deviations.rotation_deg, deviations.translation_m, cfg):
        return _uncertain_reason(cfg, searched, deviations, loose, uncertain, frames_used)
    near_edge = box_edge(x, problem.lower, problem.upper, cfg.box_edge_fraction, free,
                         SIGNIFICANCE * np.concatenate([deviations.rotation_deg, deviations.translation_m]))
    if near_edge:
        return (f"the search box's edge lies within twice the estimate's deviation ({'; '.join(near_edge)}): the "
                "truth may lie outside the box; check the initial guess or widen --search-deg / --search-m")
    return ""


def _uncertain_reason(cfg: SolverConfig, searched: _Searched, deviations: AxisDeviations, loose: list[str],
                      uncertain: list[str], frames_used: int) -> str:
    """The reason of an estimate whose two deviations exceed the accuracy asked on the ``uncertain`` axes:
    where they come from and what would narrow them."""
    why = ("the seeded 6-DoF runs disagree, so the translation was held at the initial guess's; their spread "
           "leaves the estimate" if searched.replaced else "the estimate is")
    unconfirmed = "" if searched.confirmed else f", none of the {len(searched.runs)} seeded runs confirms another"
    sources = ("" if searched.replaced else f"; {deviations.alike_runs} other seeded run(s) and "
               f"{deviations.alike_aliases} optima a few lidar rings away score as well{unconfirmed}")
    if loose:
        sources += f"; the score fixes the translation along {', '.join(loose)} loosely against the rotation"
    return (f"{why} uncertain beyond {cfg.agree_rotation_deg:g} deg / {100 * cfg.agree_translation_m:g} cm "
            f"(2 sigma: {', '.join(uncertain)}{sources}): " + _more_evidence(frames_used))


def calibrate(frames: list[CalibrationFrame], T_camera_lidar_init: Mat4,
              config: SolverConfig | None = None, progress: ProgressCallback | None = None) -> CalibrationResult:
    """Estimate ``T_camera_lidar`` from paired frames, starting at ``T_camera_lidar_init``: ``repeats``
    seeded swarm + polish runs over one objective; the best-scoring run is returned and the spread of
    the runs is the uncertainty. ``progress`` is called after every swarm iteration (``SearchProgress``).

    Raises:
        ProcessingError: no frames, or the camera sees (almost) no lidar points anywhere in the box.
        ConfigError: invalid settings.
    """
    config = config or SolverConfig()
    cfg = resolve_auto_rules(frames, T_camera_lidar_init, config)
    auto_angle = config.neighbours_by == "auto" and cfg.neighbours_by == "angle"
    start = time.perf_counter()
    clock = _SearchClock(progress, cfg.repeats, cfg.max_iterations)
    (problem, clock_field), columns, first = _feature_problem(frames, T_camera_lidar_init, cfg,
                                                              cfg.holds_translation, clock)
    init_scores, _ = problem.frame_scores(problem.centre[None])
    searched = _searched(problem, cfg, cfg.holds_translation, clock, first)
    swarm_view = problem.search_view(cfg.seed)  # the first run's swarm frames bound the checks' cost on long logs
    estimate = _refined(problem, cfg, searched, clock_field, swarm_view)
    runtime = time.perf_counter() - start
    final_scores = _final_frame_scores(problem, cfg, estimate.x)
    T_best = _estimate_T(problem, estimate, clock_field)
    rot_std, trans_std = _run_spread(searched, T_best)
    flat = _flat(problem, estimate.x, estimate.score, {"gom": 0.5, "nmi": 1.0, "levinson": 0.0}[cfg.metric])
    rings = _Rings(_finite_median(problem.ring_spacing_rad, np.degrees), _finite_median(problem.ring_slant_deg))
    deviations, loose = _deviations(problem, cfg, searched, estimate, rings, clock_field, T_best, swarm_view)
    reason = _suspect_reason(problem, cfg, searched, estimate, deviations, loose, rings, flat, auto_angle,
                             len(frames))
    initial_score = float(init_scores.mean())
    moved = (rotation_error_deg(T_best, problem.T_init) > cfg.ok_rotation_deg
             or translation_error_m(T_best, problem.T_init) > cfg.ok_translation_m)
    verdict: Verdict = "suspect" if reason else ("recalibrated" if moved and estimate.score > initial_score else "ok")
    if reason:
        deviations = reaching_initial_guess(deviations, T_best, problem.T_init)
    return CalibrationResult(
        T_camera_lidar=T_best, T_camera_lidar_initial=problem.T_init.copy(), score=float(estimate.score),
        initial_score=initial_score, frame_scores=final_scores, frame_initial_scores=init_scores[0],
        frames_used=len(frames), points_used=list(problem.points_used), runtime_s=runtime,
        iterations=estimate.iterations, evaluations=round(problem.evaluations), verdict=verdict,
        verdict_reason=reason, flat=flat, rotation_std_deg=rot_std, translation_std_m=trans_std,
        agreeing_repeats=searched.agreeing,
        focal_scale=float(estimate.x[6]) if estimate.x.size > 6 else 1.0, metric=cfg.metric,
        gradient_viewpoint=cfg.viewpoint, ring_smoothing_px=max(problem.ring_smoothing_px),
        translation_held=searched.hold, translation_profile=estimate.profile,
        weak_translation_axes=weak_axes(estimate.profile, cfg.weak_translation_ratio),
        ring_spacing_deg=rings.spacing_deg, sparse_rings=bool(rings.spacing_deg > cfg.sparse_rings_above_deg),
        ring_slant_deg=rings.slant_deg, std_rotation_deg=deviations.rotation_deg,
        std_translation_m=deviations.translation_m, alike_runs=deviations.alike_runs,
        alike_aliases=deviations.alike_aliases, feature_columns=columns,
        **_timing_fields(problem, estimate.timing, cfg))


def _time_field(problem: CalibrationProblem) -> TimeShiftField | None:
    """The points' motion in time (``timing.TimeShiftField``) where some frame moves; None otherwise."""
    field = TimeShiftField(problem, [f.twist_at_camera() for f in problem.frames],
                           [f.readout_s for f in problem.frames])
    return field if field.moving else None


def _estimate_timing(problem: CalibrationProblem, field: TimeShiftField | None, x: NDArray[np.float64], hold: bool,
                     cfg: SolverConfig) -> TimingEstimate | None:
    """The clock offset and readout found at the estimate x (D,) and the extrinsic refined under them; None
    where neither is asked for or no frame moves (nothing to find them from)."""
    if field is None or not (cfg.estimate_time_offset or cfg.estimate_readout):
        return None
    free = problem.free_parameters(hold)
    lower, upper = problem.lower[free], problem.upper[free]

    def refine(x0: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
        result = pattern_search(lambda z: problem.evaluate(embed(z, x0, free)), x0[free], 0.02 * (upper - lower),
                                lower, upper, min_step_fraction=0.02)
        return embed(result.best_x, x0, free)[0], result.best_score

    return estimate_timing(field, x, TimeShift(), cfg.estimate_time_offset, cfg.estimate_readout, cfg.time_range_s,
                           refine)


def _timing_floor(field: TimeShiftField | None, timing: TimingEstimate | None, cfg: SolverConfig,
                  T_best: Mat4) -> NDArray[np.float64]:
    """(6,) extrinsic deviations left by an estimated clock offset's own (``timing.extrinsic_deviation``);
    zeros where the offset was not estimated."""
    if field is None or timing is None or not cfg.estimate_time_offset:
        return np.zeros(6)
    R = np.asarray(T_best, dtype=np.float64)[:3, :3]
    return extrinsic_deviation(field, timing.offset_std_s, cfg.time_range_s, R)


def _timing_fields(problem: CalibrationProblem, timing: TimingEstimate | None,
                   cfg: SolverConfig) -> dict[str, float]:
    """``CalibrationResult``'s time fields (see there): NaN with an infinite deviation where a time asked for
    could not be found (no motion, or a profile that does not tell)."""
    out = {"readout_s": float(np.mean([f.readout_s for f in problem.frames]))}
    if cfg.estimate_time_offset:
        found = timing is not None and np.isfinite(timing.offset_std_s)
        out["time_offset_s"] = timing.shift.offset_s if found and timing is not None else float("nan")
        out["time_offset_std_s"] = timing.offset_std_s if found and timing is not None else float("inf")
    if cfg.estimate_readout:
        readout = timing.shift.readout_s if timing is not None and np.isfinite(timing.readout_std_s) else None
        out["readout_s"] = float("nan") if readout is None else readout
        out["readout_std_s"] = float("inf") if readout is None or timing is None else timing.readout_std_s
    return out


def _curvature_loosened(deviations: AxisDeviations, profile: NDArray[np.float64], cfg: SolverConfig) -> list[str]:
    """Raise each translation deviation to ``curvature_deviation_m`` of the translation profile and the median
    rotation deviation, in place; returns the camera axes (``"y"``) where that made the two standard deviations
    exceed ``agree_translation_m``."""
    along = curvature_deviation_m(profile, float(np.median(deviations.rotation_deg)), cfg.profile_translation_m,
                                  cfg.profile_rotation_deg, cfg.search_m)
    raised = np.fmax(deviations.translation_m, along)
    loose = [a for a, old, new in zip(AXES, deviations.translation_m, raised, strict=True)
             if new > old and 2 * new > cfg.agree_translation_m]
    deviations.translation_m = np.where(np.isnan(deviations.translation_m), np.nan, raised)
    return loose


def _uncertain_axes(std_rotation_deg: NDArray[np.float64], std_translation_m: NDArray[np.float64],
                    cfg: SolverConfig) -> list[str]:
    """The camera axes whose two standard deviations exceed ``agree_rotation_deg`` / ``agree_translation_m``
    (the distance within which two estimates are the same answer), each as ``"rz 0.62 deg"``."""
    out = [f"r{a} {2 * v:.2f} deg" for a, v in zip(AXES, std_rotation_deg, strict=True)
           if 2 * v > cfg.agree_rotation_deg]
    out += [f"t{a} {200 * v:.0f} cm" for a, v in zip(AXES, std_translation_m, strict=True)
            if np.isfinite(v) and 2 * v > cfg.agree_translation_m]
    return out


def _finite_median(values: list[float], convert: Callable[[float], float] = float) -> float:
    """``convert`` of the median of the finite ``values`` (per-frame measures); NaN where none is finite."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[np.isfinite(finite)]
    return float(convert(float(np.median(finite)))) if finite.size else float("nan")
