"""Where the calibration objective itself peaks: the local optimum nearest the truth, per real log and
simulated rig, without the search's luck.

For each case of ``bench_starts.py`` (its real logs and simulated rigs, loaded the same way) the objective is
the one ``calibrate`` searches from the truth (``calibrator.searched_objective``: lidar gradients taken there,
the search box centred there, the lidar feature chosen there as ``calibrate`` chooses it) and a pattern search climbs
from the truth over every free parameter (first steps 0.1 deg, 1 cm and a focal scale of 0.005, down to 2 %
of them). The climb ends at the objective's own optimum next to the truth: its distance from the truth is the
error no search can avoid on that log, whatever its starts and seeds, and a change to the objective (its
features, gradients, weights) can be judged by it in minutes and without the noise of a swarm, whose path a
small change to the score sends elsewhere. On the simulated rigs the truth is exact, so their figures are the
objective's bias alone; on real logs they include the error of the log's reference calibration.

    .venv/bin/python benchmarks/bench_objective_bias.py [--cases kitti sim-16 ...] [--solver KEY=VALUE ...] [--aliases]

``--aliases`` also moves each optimum 1-3 ring spacings either way along the lidar's axis and polishes there
(``uncertainty.ring_alias_optima``): the best alias's score minus the optimum's (above 0, the objective itself
prefers a pose a ring or more away, which no search from a drifted start can be expected to avoid) and its
distance from the truth.

``--solver KEY=VALUE`` changes a ``SolverConfig`` setting for every case (as in ``bench_starts.py``): the
alternatives of docs/accuracy.md "Alternatives measured on the objective's own optimum" were judged so.

Prints one row per case: the feature scored, rotation and translation error of the optimum, its per-axis errors
(camera frame: rotation vector degrees, translation cm), the score it gained over the truth and the evaluations
the climb took; then the median over the real logs and over the simulated rigs.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_starts import REAL, SIM, Case, load_case, per_axis_errors, solver_overrides
from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
from fleetcal.stages.calibration.calibrator import searched_objective
from fleetcal.stages.calibration.frame import AUTO_FEATURES
from fleetcal.stages.calibration.problem import CalibrationProblem, embed, evaluate_embedded
from fleetcal.stages.calibration.pso import pattern_search
from fleetcal.stages.calibration.uncertainty import LOCAL_POLISH_STEPS, ring_alias_optima

MIN_STEP_FRACTION = 0.02
"""The climb stops once its steps are this fraction of the first ones (0.002 deg, 0.2 mm)."""


@dataclass
class Optimum:
    """The objective's local optimum nearest the truth: its errors, the score it gained over the truth and the
    evaluations the climb took."""

    rot_deg: float
    trans_cm: float
    axes_deg: NDArray[np.float64]
    axes_cm: NDArray[np.float64]
    gain: float
    evaluations: int
    feature: str
    alias: tuple[float, float] | None = None
    """With ``--aliases``: ``best_alias`` (gain, distance from the truth cm; NaN where no move stays in the box)."""


def optimum_near_truth(case: Case, aliases: bool = False) -> Optimum:
    """The objective's local optimum nearest the truth of ``case``; with ``aliases``, also how much higher its best
    ring alias scores (``best_alias``)."""
    problem, columns = searched_objective(case.frames, case.T_true, case.config)
    evaluations_before_climb = problem.evaluations  # the feature choice's polishes
    x_truth = np.zeros(problem.lower.size)
    x_truth[6:] = 1.0  # a searched focal scale starts at 1
    free = problem.free_parameters()
    truth_score = float(problem.evaluate(x_truth[None])[0])
    fit = pattern_search(partial(evaluate_embedded, problem, base=x_truth, free=free), x_truth[free],
                         LOCAL_POLISH_STEPS[: x_truth.size][free], problem.lower[free], problem.upper[free],
                         min_step_fraction=MIN_STEP_FRACTION, score_at_x0=truth_score)
    x_best = embed(fit.best_x, x_truth, free)[0]
    T_best = problem.T_camera_lidar(x_best)
    axes_deg, axes_m = per_axis_errors(T_best, case.T_true)
    found = Optimum(rotation_error_deg(T_best, case.T_true), 100 * translation_error_m(T_best, case.T_true),
                    axes_deg, 100 * axes_m, fit.best_score - truth_score,
                    int(problem.evaluations - evaluations_before_climb), feature_name(columns))
    if aliases:
        found.alias = best_alias(problem, x_best, fit.best_score, case.T_true)
    return found


def best_alias(problem: CalibrationProblem, x_best: NDArray[np.float64], best_score: float,
               T_true: NDArray[np.float64]) -> tuple[float, float]:
    """(score of the best ring alias of the optimum ``x_best`` minus ``best_score``, its distance from the truth in
    cm): the optimum moved 1-3 ring spacings either way along the lidar's axis and polished
    (``uncertainty.ring_alias_optima``); above 0, the objective itself prefers an optimum that far away. NaN where no
    move stays in the box."""
    ring_deg = float(np.degrees(np.nanmedian(problem.ring_spacing_rad)))
    range_m, _ = problem.typical_range_and_off_axis()
    optima = ring_alias_optima(problem, x_best, problem.free_parameters(), ring_deg, range_m)
    if not optima:
        return float("nan"), float("nan")
    scores = problem.evaluate(np.vstack(optima))
    k = int(np.argmax(scores))
    return float(scores[k]) - best_score, 100 * translation_error_m(problem.T_camera_lidar(optima[k]), T_true)


def feature_name(columns: tuple[int, ...] | None) -> str:
    """The ``auto`` feature's columns the objective scores, by name (``frame.AUTO_FEATURES``; all: every one)."""
    return "all" if columns is None else "+".join(AUTO_FEATURES[c] for c in columns)


def row(name: str, found: Optimum) -> str:
    """One markdown table row."""
    axes_deg = " ".join(f"{v:+.3f}" for v in found.axes_deg)
    axes_cm = " ".join(f"{v:+.1f}" for v in found.axes_cm)
    alias = "" if found.alias is None else f" {found.alias[0]:+.4f} | {found.alias[1]:.1f} |"
    return (f"| {name} | {found.feature} | {found.rot_deg:.3f} | {found.trans_cm:.1f} | {axes_deg} | {axes_cm} | "
            f"{found.gain:.4f} | {found.evaluations} |{alias}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="*", default=[*REAL, *SIM], choices=[*REAL, *SIM])
    parser.add_argument("--solver", action="append", default=[], metavar="KEY=VALUE",
                        help="a SolverConfig setting for every case (repeatable), e.g. neighbours_by=angle")
    parser.add_argument("--aliases", action="store_true",
                        help="also score the optimum's ring aliases: the best one's gain and distance from the truth")
    args = parser.parse_args()
    try:
        overrides = solver_overrides(args.solver)
    except ValueError as exc:
        parser.error(str(exc))
    print("| case | feature | rotation deg | translation cm | about x y z (deg) | along x y z (cm) | score gained | "
          "evaluations |" + (" best alias gain | its distance cm |" if args.aliases else ""))
    print("|---|---|---|---|---|---|---|---|" + ("---|---|" if args.aliases else ""))
    found: dict[str, Optimum] = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fleetcal_bias_") as tmp:
        for name in args.cases:
            case = load_case(name, Path(tmp), False, overrides)
            if case is None:
                continue
            found[name] = optimum_near_truth(case, args.aliases)
            print(row(name, found[name]), flush=True)
    for label, group in (("real logs", REAL), ("simulated rigs", SIM)):
        names = [n for n in found if n in group]
        if names:
            rot = np.median([found[n].rot_deg for n in names])
            trans = np.median([found[n].trans_cm for n in names])
            print(f"| **median, {label}** | | {rot:.3f} | {trans:.1f} | | | | |" + (" | |" if args.aliases else ""))
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
