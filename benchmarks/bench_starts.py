"""The accuracy benchmark of record: every real shared log and simulated rig, each from N drifted starts
and from the log's own tf.

Real logs (``../shared/data/logs``): KITTI, PJLab rig 1 and 2, nuScenes (six cameras, joint, ego-motion),
loaded as ``tests/test_calibration_real.py`` loads them (the workflow's feature and solver settings).
Simulated rigs (``fleetcal simulate``, street, the workflow's feature, written to a temporary folder): 16, 32,
64 and 128 beams with the pinhole camera, a rosette lidar, the equidistant fisheye, the wide-angle
plumb_bob lens whose model folds inside the image (``--wide-angle``, with a VLP-16-like 16 x 1800 lidar, as
sim-16) and the cylindrical panorama.
``--cases`` also takes the rigs of ``MORE_RIGS`` (indoor corridors, open yards, rolled or sideways mounts, a fast
drive), which the table of record leaves out; their rows pool with the simulated rigs.
Each case is calibrated from the log's tf (the simulator's /tf_static is itself drifted 2 deg / 12 cm)
and from ``--starts`` starts ``--deg`` / ``--m`` off the truth on random axes (seeded: the same starts
for every run of the benchmark).

Per case and over the real logs, the simulated rigs and everything it prints: median and 90th
percentile rotation / translation error, the share within 0.3 deg / 10 cm, the share confidently wrong
(outside 0.5 deg / 15 cm while not ``suspect``) and the 2-sigma coverage: the share of estimates whose
error on every axis (rotation deg and translation m, in the camera frame) lies within twice the per-axis
standard deviation the result reports (``CalibrationResult`` fields named ``std_*``, (3,) each); n/a
where the results carry none. ``--markdown PATH`` writes the tables at the head of that file
(docs/accuracy.md), keeping its ``## `` sections.

    .venv/bin/python benchmarks/bench_starts.py [--quick] [--cases kitti sim-16 ...] [--starts 5]
        [--sim-frames 10]
        [--deg 2] [--m 0.12] [--jobs N] [--markdown docs/accuracy.md] [--jsonl runs.jsonl]
        [--solver KEY=VALUE ...]

``--solver KEY=VALUE``: a ``SolverConfig`` setting changed for every case (repeatable), to judge an alternative
on the same runs as the defaults, e.g. ``--solver ring_smoothing=off``.

``--jobs N``: N calibrations at once, each (case, start) in a worker process on one numba thread (a case is
loaded, or simulated, once per worker): on a many-core machine the full benchmark takes minutes per 40 runs
instead of hours.

``--quick``: 1 drifted start + the tf, 2 frames per case, 640x360 simulated images and a cut-down solver
(60 particles, 40 iterations, one run, no confirmation runs; real logs keep their frames): 24
calibrations, 30 min on 2 cores shared with other jobs (load ~12; nuScenes's six cameras 5 min a run), a
smoke test of the benchmark, not the accuracy of the defaults.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.errors import ConfigError
from fleetcal.stages.calibration import CalibrationFrame, SolverConfig, calibrate
from fleetcal.workflows.calibrate import solver_config
from tests.test_calibration_synthetic import per_axis_errors, perturb

Mat4 = NDArray[np.float64]
REAL = {"kitti": ("kitti_2011_09_26.mcap", {}),
        "pjlab": ("pjlab_road_rig1", {}),
        "pjlab-rig2": ("pjlab_road_rig2", {}),
        "nuscenes": ("nuscenes_n015.bag", {"cameras": 6, "ego_motion": True})}
SIM: dict[str, dict[str, Any]] = {
    "sim-16": {"beams": 16, "columns": 1800},
    "sim-32": {"beams": 32, "columns": 1024},
    "sim-64": {"beams": 64, "columns": 1024},
    "sim-128": {"beams": 128, "columns": 1024},
    "sim-rosette": {"lidar": "rosette"},
    "sim-fisheye": {"beams": 64, "columns": 1024, "fisheye": True},
    "sim-wide-angle": {"beams": 16, "columns": 1800, "wide_angle": True},
    "sim-panorama": {"beams": 64, "columns": 1024, "panorama": True},
}
MORE_RIGS: dict[str, dict[str, Any]] = {
    "corridor-64": {"scene": "corridor", "beams": 64, "columns": 1024},
    "corridor-64-fisheye": {"scene": "corridor", "beams": 64, "columns": 1024, "fisheye": True, "organized": True},
    "corridor-16-wide-angle": {"scene": "corridor", "beams": 16, "columns": 1800, "wide_angle": True},
    "open-32": {"scene": "open", "beams": 32, "columns": 1024},
    "open-64-fisheye": {"scene": "open", "beams": 64, "columns": 1024, "fisheye": True},
    "street-128-wide-angle": {"beams": 128, "columns": 1024, "wide_angle": True},
    "street-64-lidar-roll-20": {"beams": 64, "columns": 1024, "lidar_roll_deg": 20.0},
    "street-32-lidar-roll-40": {"beams": 32, "columns": 1024, "lidar_roll_deg": 40.0},
    "street-64-15m-s": {"beams": 64, "columns": 1024, "speed_m_s": 15.0},
    "street-16-side-camera": {"beams": 16, "columns": 1800, "camera_yaw_deg": 90.0},
    "street-32-camera-roll-15": {"beams": 32, "columns": 1024, "camera_roll_deg": 15.0},
}
"""Rigs and scenes outside the table of record (``--cases`` names them; not run by default): indoor, open yards,
rolled or sideways mounts, a fast drive. Each is a ``fleetcal simulate`` log like ``SIM``'s."""
SIM_FRAMES = 10
"""Pairs in each simulated log of the table of record (``--sim-frames``; the calibration uses up to 40)."""
WITHIN_DEG, WITHIN_M = 0.3, 0.10
WRONG_DEG, WRONG_M = 0.5, 0.15


@dataclass
class Case:
    """Frames of one log, its truth, its own tf start and the solver settings it is calibrated with."""

    frames: list[CalibrationFrame]
    T_true: Mat4
    T_tf: Mat4
    config: SolverConfig


@dataclass
class Outcome:
    """One calibration: errors, verdict, the 2-sigma check (None: no per-axis deviations) and seconds; for
    ``--jsonl``, where it started, its per-axis errors and deviations (camera frame: rotation degrees,
    translation metres; NaN where the result has none), the verdict's reason and the translation profile
    (``CalibrationResult.translation_profile``)."""

    rot_deg: float
    trans_m: float
    suspect: bool
    covered: bool | None
    seconds: float
    start: str = ""
    axis_errors: list[float] = field(default_factory=list)
    axis_deviations: list[float] = field(default_factory=list)
    reason: str = ""
    feature_columns: list[int] = field(default_factory=list)
    translation_profile: list[float] = field(default_factory=list)


@dataclass
class Rows:
    outcomes: dict[str, list[Outcome]] = field(default_factory=dict)


def load_real(name: str, quick: bool) -> Case | None:
    from tests.test_calibration_real import LOGS, load_real_frames

    path, options = REAL[name]
    if not (LOGS / path).exists():
        print(f"{name}: {LOGS / path} not present, skipped", flush=True)
        return None
    problem = load_real_frames(path, **options)  # type: ignore[arg-type]
    config = solver_config(Config())
    return Case(problem.frames, problem.T_true, problem.T_init, _quick(config) if quick else config)


def load_sim(name: str, out: Path, quick: bool, frames: int = SIM_FRAMES) -> Case:
    """The simulated rig ``name`` (``SIM`` or ``MORE_RIGS``): a log of ``frames`` pairs (quick: 2) written into
    ``out``."""
    from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

    frames = 2 if quick else frames
    rig = {**SIM, **MORE_RIGS}[name]
    size = {"width": 1024, "height": 256} if rig.get("panorama") else (
        {"width": 640, "height": 360} if quick else {"width": 1280, "height": 720})
    log = out / f"{name}.mcap"
    simulate_log(log, SimulationOptions(frames=frames, perturb_deg=2.0, perturb_m=0.12, seed=1, **size,
                                        **rig), quiet=True)
    case = simulated_case(log, frames)
    return replace(case, config=_quick(case.config)) if quick else case


def simulated_case(log: Path, frames: int) -> Case:
    """The first camera's case of a simulated ``log`` (its truth file beside it) with ``frames`` of its pairs,
    chosen, prepared and started from the log's tf as ``fleetcal calibrate`` does."""
    from fleetcal.readers.frames import load_tf_tree
    from fleetcal.readers.open import open_log
    from fleetcal.workflows.calibrate import collect_frames, initial_guess
    from fleetcal.workflows.simulator.truth import load_truth, truth_path_for

    truth = load_truth(truth_path_for(log))
    pair = truth["pairs"][0]
    config = Config()
    config.calibration.frames = frames
    with open_log(log) as reader:
        tree = load_tf_tree(reader)
        col = collect_frames(reader, truth["lidar_topic"], pair["camera_topic"], config, tree)
        T_tf = initial_guess(tree, col.lidar_frame, col.camera_frame, None)
    return Case(col.frames, np.asarray(pair["T_camera_lidar"], dtype=np.float64), T_tf,
                solver_config(config))  # what ``fleetcal calibrate`` runs


def solver_overrides(pairs: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings as ``SolverConfig`` settings, each value converted to its default's type.

    Raises:
        ValueError: an unknown key, a value of the wrong type or one the settings refuse (one line).
    """
    defaults = SolverConfig()
    out: dict[str, Any] = {}
    for pair in pairs:
        key, _, text = pair.partition("=")
        if not hasattr(defaults, key) or not text:
            raise ValueError(f"--solver {pair!r}: expected KEY=VALUE with KEY a SolverConfig setting")
        default = getattr(defaults, key)
        try:
            if isinstance(default, bool):
                if text.lower() not in ("true", "false"):
                    raise ValueError(text)
                out[key] = text.lower() == "true"
            else:
                out[key] = type(default)(text) if default is not None else float(text)
        except ValueError:
            raise ValueError(f"--solver {pair!r}: {text!r} is not a {type(default).__name__}") from None
    try:
        replace(defaults, **out).validate()
    except ConfigError as exc:
        raise ValueError(f"--solver: {exc}") from None
    return out


def load_case(name: str, out: Path, quick: bool, overrides: dict[str, Any],
              sim_frames: int = SIM_FRAMES) -> Case | None:
    """The case ``name`` (a real log, or a rig simulated into ``out`` with ``sim_frames`` pairs) with
    ``overrides`` applied to its solver settings."""
    case = load_real(name, quick) if name in REAL else load_sim(name, out, quick, sim_frames)
    return case if case is None or not overrides else replace(case, config=replace(case.config, **overrides))


def _quick(config: SolverConfig) -> SolverConfig:
    return replace(config, n_particles=60, max_iterations=40, repeats=1, confirm_repeats=0)


def covered(result: Any, T_true: Mat4) -> bool | None:
    """True when the error on every axis is within 2 sigma of the result's per-axis deviations (its ``std_*``
    fields holding 3 values: rotation ones in deg, translation ones in m); None when it has none."""
    stds = {name: np.asarray(getattr(result, name), dtype=np.float64).ravel()
            for name in dir(result) if name.startswith("std_") and not callable(getattr(result, name))}
    rot = next((v for k, v in stds.items() if "rot" in k and v.size == 3), None)
    trans = next((v for k, v in stds.items() if "trans" in k and v.size == 3), None)
    if rot is None or trans is None:
        return None
    err_rot, err_trans = per_axis_errors(result.T_camera_lidar, T_true)
    return bool(np.all(np.abs(err_rot) <= 2 * rot) and np.all(np.abs(err_trans) <= 2 * trans))


def starts_of(case: Case, starts: int, deg: float, m: float) -> list[tuple[str, Mat4]]:
    """(label, T_camera_lidar start): the log's tf, then ``starts`` drifted starts (seeds 1001..)."""
    return [("tf", case.T_tf)] + [(f"start {s}", perturb(case.T_true, deg, m, seed=1000 + s))
                                  for s in range(1, starts + 1)]


def run_start(name: str, case: Case, label: str, T_start: Mat4) -> Outcome:
    """One calibration of the case from ``T_start``, printed as it ends."""
    from tests.test_calibration_real import errors

    t0 = time.perf_counter()
    result = calibrate(case.frames, T_start, case.config)
    seconds = time.perf_counter() - t0
    rot, trans = errors(result.T_camera_lidar, case.T_true)
    print(f"  {name} {label}: {rot:.3f} deg / {100 * trans:.1f} cm {result.verdict} "
          f"{result.verdict_reason} (feature columns {result.feature_columns}, {seconds:.0f} s)", flush=True)
    err_rot, err_trans = per_axis_errors(result.T_camera_lidar, case.T_true)
    deviations = [float(v) for name in ("std_rotation_deg", "std_translation_m")
                  for v in np.asarray(getattr(result, name, np.full(3, np.nan)), dtype=np.float64).ravel()]
    return Outcome(rot, trans, result.verdict == "suspect", covered(result, case.T_true), seconds, label,
                   [*map(float, err_rot), *map(float, err_trans)], deviations, result.verdict_reason,
                   list(result.feature_columns or []), [float(v) for v in result.translation_profile])


def run_case(name: str, case: Case, starts: int, deg: float, m: float) -> list[Outcome]:
    return [run_start(name, case, label, T) for label, T in starts_of(case, starts, deg, m)]


_CASES: dict[str, Case | None] = {}


def _parallel_job(name: str, index: int, args: argparse.Namespace, tmp: str) -> tuple[str, int, Outcome | None]:
    """Worker process: start ``index`` of case ``name`` on one numba thread (the case loaded once per process,
    a simulated log written to a folder of the process's own)."""
    import numba

    numba.set_num_threads(1)
    if name not in _CASES:
        folder = Path(tmp) / str(os.getpid())
        folder.mkdir(exist_ok=True)
        _CASES[name] = load_case(name, folder, args.quick, args.overrides, args.sim_frames)
    case = _CASES[name]
    if case is None:
        return name, index, None
    label, T_start = starts_of(case, args.starts, args.deg, args.m)[index]
    return name, index, run_start(name, case, label, T_start)


def run_parallel(args: argparse.Namespace, tmp: str) -> dict[str, list[Outcome]]:
    """Every (case, start) as its own job on ``args.jobs`` worker processes, longest cases first."""
    from concurrent.futures import ProcessPoolExecutor

    jobs = [(name, i) for i in range(args.starts + 1) for name in args.cases]
    found: dict[str, dict[int, Outcome]] = {name: {} for name in args.cases}
    with ProcessPoolExecutor(args.jobs) as pool:
        for future in [pool.submit(_parallel_job, name, i, args, tmp) for name, i in jobs]:
            name, index, outcome = future.result()
            if outcome is not None:
                found[name][index] = outcome
    return {name: [by_index[i] for i in sorted(by_index)] for name, by_index in found.items() if by_index}


def summary(outcomes: list[Outcome]) -> list[str]:
    rot = np.array([o.rot_deg for o in outcomes])
    trans = 100 * np.array([o.trans_m for o in outcomes])
    within = np.mean([o.rot_deg <= WITHIN_DEG and o.trans_m <= WITHIN_M for o in outcomes])
    wrong = np.mean([(o.rot_deg > WRONG_DEG or o.trans_m > WRONG_M) and not o.suspect for o in outcomes])
    checks = [o.covered for o in outcomes if o.covered is not None]
    coverage = f"{100 * np.mean(checks):.0f} %" if checks else "n/a"
    confident = [o.covered for o in outcomes if o.covered is not None and not o.suspect]
    return [str(len(outcomes)), f"{np.median(rot):.3f}", f"{np.percentile(rot, 90):.3f}",
            f"{np.median(trans):.1f}", f"{np.percentile(trans, 90):.1f}", f"{100 * within:.0f} %",
            f"{100 * wrong:.0f} %", coverage, f"{sum(confident)} of {len(confident)}",
            f"{np.mean([o.seconds for o in outcomes]):.0f}"]


HEADER = ["case", "n", "rot med deg", "rot p90 deg", "trans med cm", "trans p90 cm",
          f"within {WITHIN_DEG} deg / {100 * WITHIN_M:.0f} cm", "confidently wrong", "2-sigma coverage",
          "covered, not suspect", "s/run"]


def table(rows: dict[str, list[Outcome]]) -> list[list[str]]:
    groups: list[tuple[str, Callable[[str], bool]]] = [("all real logs", lambda n: n in REAL),
                                                       ("all simulated rigs", lambda n: n not in REAL),
                                                       ("everything", lambda n: True)]
    lines = [[name, *summary(out)] for name, out in rows.items()]
    for label, keep in groups:
        pooled = [o for name, out in rows.items() if keep(name) for o in out]
        if pooled:
            lines.append([f"**{label}**", *summary(pooled)])
    return lines


def markdown(lines: list[list[str]], args: argparse.Namespace, wall_s: float) -> str:
    mode = ("quick mode (1 drifted start + the log's tf, 2 frames per simulated rig at 640x360, solver cut to "
            "60 particles x 40 iterations, one run, no confirmation runs): a smoke test of the benchmark, "
            "NOT the accuracy of the defaults" if args.quick else "full mode (default solver settings)")
    text = [
        "# Calibration accuracy over real logs and simulated rigs",
        "",
        f"`benchmarks/bench_starts.py{' --quick' if args.quick else ''}`: each case from the log's own tf and "
        f"{args.starts} start(s) {args.deg:g} deg / {100 * args.m:g} cm off the truth on random axes (seeds "
        f"1001..{1000 + args.starts}); {mode}; simulated logs of {2 if args.quick else args.sim_frames} pairs. "
        f"Ran in {wall_s / 60:.0f} min on {platform.machine()} with "
        f"{os.cpu_count()} cores, {args.jobs} calibration(s) at once.",
        "",
        f"Within: rotation <= {WITHIN_DEG} deg and translation <= {100 * WITHIN_M:.0f} cm. Confidently wrong: "
        f"outside {WRONG_DEG} deg / {100 * WRONG_M:.0f} cm while the verdict is not `suspect`. 2-sigma "
        "coverage: the share whose error on every axis (camera frame) lies within twice the per-axis standard "
        "deviation the result reports (n/a: the results carry no per-axis deviations); a `suspect` result's "
        "deviations reach its initial guess, so the runs not `suspect` are also counted apart (covered of "
        "those with deviations).",
        "",
        "| " + " | ".join(HEADER) + " |",
        "|" + "|".join("---" for _ in HEADER) + "|",
        *("| " + " | ".join(line) + " |" for line in lines),
        "",
        *([f"Not run this time: {', '.join(missing)} (`--cases`).", ""] if (missing := [
            name for name in [*REAL, *SIM] if name not in args.cases]) else []),
        "Targets: median rotation <= 0.25 deg and translation <= 8 cm over the real logs, 90th percentile "
        "<= 0.5 deg / 15 cm, confidently wrong <= 5 %, 2-sigma coverage >= 90 %; wide-angle plumb_bob rig "
        "within 0.2 deg / 3 cm.",
        "",
        *([] if not args.quick else [
            "In quick mode one cut-down run cannot be checked against another, so estimates that the default "
            "settings would flag `suspect` (no agreeing seeded run) count as confidently wrong here; the "
            "numbers say that the benchmark runs on every rig, not how accurate the defaults are. The full "
            "mode (5 starts + tf, default solver, 10 frames at 1280x720 per simulated rig) takes hours on 2 "
            "cores.", ""]),
    ]
    return "\n".join(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="*", default=[*REAL, *SIM], choices=[*REAL, *SIM, *MORE_RIGS])
    parser.add_argument("--starts", type=int, default=None, help="drifted starts per case (default 5, quick 1)")
    parser.add_argument("--deg", type=float, default=2.0)
    parser.add_argument("--m", type=float, default=0.12)
    parser.add_argument("--quick", action="store_true", help="cut-down run for a few minutes on 2 cores")
    parser.add_argument("--sim-frames", type=int, default=SIM_FRAMES,
                        help=f"pairs in each simulated log (default {SIM_FRAMES}; the calibration uses up to 40)")
    parser.add_argument("--markdown", type=Path, default=None, help="write the table to this markdown file")
    parser.add_argument("--jsonl", type=Path, default=None,
                        help="also write every calibration (case, start, per-axis errors and deviations, verdict) "
                             "as a JSON line to this file")
    parser.add_argument("--jobs", type=int, default=1,
                        help="calibrations at once, each in its own process on one numba thread (e.g. the cores)")
    parser.add_argument("--solver", action="append", default=[], metavar="KEY=VALUE",
                        help="a SolverConfig setting for every case (repeatable), e.g. ring_smoothing=off")
    args = parser.parse_args()
    try:
        args.overrides = solver_overrides(args.solver)
    except ValueError as exc:
        parser.error(str(exc))
    args.starts = args.starts if args.starts is not None else (1 if args.quick else 5)
    rows: dict[str, list[Outcome]] = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fleetcal_starts_") as tmp:
        if args.jobs > 1:
            rows = run_parallel(args, tmp)
        else:
            for name in args.cases:
                case = load_case(name, Path(tmp), args.quick, args.overrides, args.sim_frames)
                if case is not None:
                    rows[name] = run_case(name, case, args.starts, args.deg, args.m)
    if args.jsonl is not None:
        args.jsonl.write_text("".join(json.dumps({"case": name, **asdict(o)}) + "\n"
                                      for name, out in rows.items() for o in out))
    lines = table(rows)
    widths = [max(len(h), *(len(line[i]) for line in lines)) for i, h in enumerate(HEADER)]
    print("  ".join(h.rjust(w) for h, w in zip(HEADER, widths, strict=True)))
    for line in lines:
        print("  ".join(v.rjust(w) for v, w in zip(line, widths, strict=True)))
    if args.markdown is not None:
        write_markdown(args.markdown, markdown(lines, args, time.perf_counter() - t0))
        print(f"wrote {args.markdown}")


def write_markdown(path: Path, text: str) -> None:
    """Write ``text`` as the head of ``path`` (up to its first ``## `` section), keeping those sections."""
    old = path.read_text() if path.exists() else ""
    cut = old.find("\n## ")
    path.write_text(text.rstrip() + "\n" + (old[cut:] if cut >= 0 else ""))


if __name__ == "__main__":
    main()
