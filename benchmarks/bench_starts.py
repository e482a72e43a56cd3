"""Drifted-start robustness: each log calibrated from several random starts of one size.

A log's own ``/tf_static`` is one drifted start; a fleet's logs each drift their own way. This runs the
workflow's calibration (``solver_config``, default feature) on each log from ``--starts`` starts
``--deg`` / ``--m`` off the reference on random axes (seeded, the same starts for every setting; real
logs also from their own tf), and
prints per log and setting the median and worst rotation / translation error, how many estimates are
within 0.5 deg / 15 cm, how many are outside yet not ``suspect`` (confidently wrong), and the time per
calibration.

    .venv/bin/python benchmarks/bench_starts.py [--logs kitti pjlab pjlab-rig2 nuscenes sim-street sim-open]
        [--starts 5] [--deg 2] [--m 0.12] [--settings default camera lidar] [--features range+normals range ...]

Settings: ``default`` (the shipped configuration), ``camera`` / ``lidar`` (``gradient_viewpoint`` forced).
``--features``: calibrate with each of these lidar features in turn (default: the workflow's for real logs,
``intensity`` for simulated ones); the frames are loaded again for each.
Real logs need ``../shared/data``; simulated ones are written to a temporary folder (intensity feature,
10 frames, 64 beams, as in ``tests/test_calibration_sim.py``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_gom import CASES  # the GOM table's cases, beside this script

from fleetcal.pipeline.config import Config
from fleetcal.stages.calibration import CalibrationConfig, calibrate
from fleetcal.workflows.calibrate import solver_config
from tests.test_calibration_real import LOGS, errors, load_real_frames
from tests.test_calibration_synthetic import perturb

REAL = {name: CASES[name] for name in ("kitti", "pjlab", "pjlab-rig2", "nuscenes")}  # the GOM table's logs
SIM = {"sim-street": "street", "sim-open": "open"}
SETTINGS = {"default": {}, "camera": {"gradient_viewpoint": "camera"}, "lidar": {"gradient_viewpoint": "lidar"}}


def load(name: str, sim_dir: Path, feature: str | None = None) -> tuple[  # type: ignore[type-arg]
        list, np.ndarray, np.ndarray | None, CalibrationConfig] | None:
    """(frames, T_true, the log's own tf start (real logs), base config) with lidar ``feature`` (None: the
    case's own); None when a real log is absent."""
    if name in SIM:
        from tests.test_calibration_sim import simulated_frames

        frames, _, T_true = simulated_frames(sim_dir, SIM[name], feature or "intensity", 10)
        return frames, T_true, None, CalibrationConfig()
    path, options = REAL[name]
    if not (LOGS / path).exists():
        print(f"{name}: {LOGS / path} not present, skipped")
        return None
    if feature is not None:
        options = {**options, "feature": feature}
    problem = load_real_frames(path, **options)  # type: ignore[arg-type]
    return problem.frames, problem.T_true, problem.T_init, solver_config(Config())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", default=[*REAL, *SIM], choices=[*REAL, *SIM])
    parser.add_argument("--starts", type=int, default=5)
    parser.add_argument("--deg", type=float, default=2.0)
    parser.add_argument("--m", type=float, default=0.12)
    parser.add_argument("--settings", nargs="*", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--features", nargs="*", default=[None], help="lidar features to compare (default: the case's)")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="fleetcal_starts_") as tmp:
        for name, feature in [(n, f) for n in args.logs for f in args.features]:
            loaded = load(name, Path(tmp), feature)
            if loaded is None:
                continue
            frames, T_true, T_tf, base = loaded
            starts = [perturb(T_true, args.deg, args.m, seed=1000 + s) for s in range(1, args.starts + 1)]
            if T_tf is not None:
                starts.insert(0, T_tf)
            for setting_name in args.settings:
                config = replace(base, **SETTINGS[setting_name])  # type: ignore[arg-type]
                setting = setting_name if feature is None else f"{setting_name}/{feature}"
                rot, trans, wrong, seconds = [], [], 0, []
                for k, T_start in enumerate(starts, start=0 if T_tf is not None else 1):
                    t0 = time.perf_counter()
                    result = calibrate(frames, T_start, config)
                    seconds.append(time.perf_counter() - t0)
                    r, t = errors(result.T_camera_lidar, T_true)
                    rot.append(r)
                    trans.append(t)
                    within = r <= 0.5 and t <= 0.15
                    wrong += int(not within and result.verdict != "suspect")
                    label = "tf" if k == 0 else f"start {k}"
                    print(f"  {name} {setting} {label}: {r:.3f} deg / {100 * t:.1f} cm {result.verdict} "
                          f"held={result.translation_held} {result.verdict_reason} ({seconds[-1]:.0f} s)", flush=True)
                within_n = sum(r <= 0.5 and t <= 0.15 for r, t in zip(rot, trans, strict=True))
                rows.append((name, setting, len(starts), np.median(rot), max(rot), 100 * np.median(trans),
                             100 * max(trans), within_n, wrong, float(np.mean(seconds))))
    print(f"\nstarts {args.deg:g} deg / {100 * args.m:g} cm off on random axes (seeds 1001..{1000 + args.starts}), "
          "and for real logs also the log's own tf")
    print(f"{'log':<12} {'setting':<24} {'n':>2} {'rot med':>8} {'rot max':>8} {'cm med':>7} {'cm max':>7} "
          f"{'within':>6} {'wrong':>5} {'s/run':>6}")
    for name, setting, n, rmed, rmax, tmed, tmax, within_n, wrong, sec in rows:
        print(f"{name:<12} {setting:<24} {n:>2} {rmed:>8.3f} {rmax:>8.3f} {tmed:>7.1f} {tmax:>7.1f} "
              f"{within_n:>6} {wrong:>5} {sec:>6.1f}")
    print("within: 0.5 deg and 15 cm of the reference; wrong: outside that yet not 'suspect'")


if __name__ == "__main__":
    main()
