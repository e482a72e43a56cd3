"""Calibration without a guess: ``fleetcal calibrate --initial auto`` on simulated drives without
``/tf_static`` and on the real shared logs, each judged against its truth file.

Simulated (``fleetcal simulate --frames 60 --image-size 960x540 --no-tf-static --seed S``: a street at 8 m/s
whose last ~10 scans turn a corner; calibrated from 20 frames): ``street`` (camera looking forward) and
``sideways-rolled`` (``--camera-yaw 90 --camera-roll 90``), seeds 1..``--seeds``. Real (``../shared/data/logs``):
KITTI, PJLab rig 2 and nuScenes (``--joint``), each with ``--initial auto`` (their lidar-camera tf ignored;
nuScenes keeps its camera-camera tf). Per run: the initialisation used and its candidates, the start's and
the result's rotation / translation error, the verdict and the wall time.

    .venv/bin/python benchmarks/bench_initial.py [--cases street sideways-rolled kitti pjlab-rig2 nuscenes]
        [--seeds 5] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "logs"
FLEETCAL = [sys.executable, "-m", "fleetcal.workflows.cli"]
SIMULATED = {"street": [], "sideways-rolled": ["--camera-yaw", "90", "--camera-roll", "90"]}
REAL = {"kitti": ("kitti_2011_09_26.mcap", []), "pjlab-rig2": ("pjlab_road_rig2", []),
        "nuscenes": ("nuscenes_n015.bag", ["--joint"])}


def truth_of(log: Path) -> dict[str, np.ndarray]:
    """Camera topic -> true ``T_camera_lidar`` from the log's truth file."""
    name = log.name[: -len(log.suffix)] if log.suffix in (".mcap", ".bag") else log.name
    truth = json.loads(log.with_name(name + ".truth.json").read_text())
    return {p["camera_topic"]: np.asarray(p["T_camera_lidar"]) for p in truth["pairs"]}


def calibrate(label: str, log: Path, out: Path, extra: list[str]) -> list[str]:
    """One ``--initial auto`` run; a table row per camera."""
    start = time.perf_counter()
    done = subprocess.run([*FLEETCAL, "calibrate", str(log), "--out", str(out), "--initial", "auto", "--json", "-q",
                           "--no-report", *extra], capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        return [f"| {label} | error: {done.stderr.strip().splitlines()[-1]} | | | | | {wall:.0f} |"]
    result, truth = json.loads(done.stdout), truth_of(log)
    rows = []
    for pair in result["pairs"]:
        T_true = truth[pair["camera_topic"]]
        start_T, final_T = np.asarray(pair["T_camera_lidar_initial"]), np.asarray(pair["T_camera_lidar"])
        rows.append(f"| {label} {pair['camera_topic']} | {pair['initialisation']} | {pair['initial_candidates']} | "
                    f"{rotation_error_deg(start_T, T_true):.1f}° | {rotation_error_deg(final_T, T_true):.3f}° / "
                    f"{100 * translation_error_m(final_T, T_true):.1f} cm | `{pair['verdict']}` | {wall:.0f} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=[*SIMULATED, *REAL], choices=[*SIMULATED, *REAL])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--workdir", type=Path, default=None, help="keep the simulated logs and outputs here")
    args = parser.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="fleetcal-initial-"))
    work.mkdir(parents=True, exist_ok=True)
    print("| log | initialisation | candidates | start error | result error | verdict | wall s |")
    print("|---|---|---|---|---|---|---|")
    for case in args.cases:
        if case in REAL:
            name, extra = REAL[case]
            if not (DATA / name).exists():
                print(f"| {case} | skipped: {DATA / name} not found | | | | | |")
                continue
            print("\n".join(calibrate(case, DATA / name, work / f"{case}-out", extra)), flush=True)
            continue
        for seed in range(1, args.seeds + 1):
            log = work / f"{case}-{seed}.mcap"
            if not log.exists():
                subprocess.run([*FLEETCAL, "simulate", str(log), "--frames", "60", "--image-size", "960x540",
                                "--no-tf-static", "--seed", str(seed), "-q", *SIMULATED[case]], check=True,
                               stdout=subprocess.DEVNULL)
            print("\n".join(calibrate(f"{case} seed {seed}", log, work / f"{case}-{seed}-out", ["--frames", "20"])),
                  flush=True)


if __name__ == "__main__":
    main()
