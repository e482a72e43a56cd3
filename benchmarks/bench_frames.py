"""How calibration accuracy grows with the frames it is given: simulated drives of 40 frames (4 s, street),
each calibrated with ``--frames`` N of them (spread over the drive, as ``fleetcal calibrate`` chooses them)
from the log's tf and two drifted starts, for every N asked.

The rigs are ``bench_starts.py``'s simulated ones (``--cases``), each drive simulated once per ``--seeds``
seed (the scene's drive and the tf's drift change with it). Every calibration runs the workflow's
settings (``solver_config``) with only the frames changed. Prints one line per calibration, then per N:
median and 90th percentile rotation / translation error, the share within 0.3 deg / 10 cm, the share
confidently wrong, the 2-sigma coverage and the mean seconds per run (one numba thread per job).

    .venv/bin/python benchmarks/bench_frames.py [--cases sim-16 sim-wide-angle ...] [--frames 10 20 40]
        [--seeds 1 2] [--jobs 2] [--jsonl runs.jsonl]

The default (4 rigs x 2 seeds x 3 frame counts x 3 starts, 72 calibrations) takes about an hour on 2 cores
with ``--jobs 2``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_starts import HEADER, SIM, Case, Outcome, run_start, simulated_case, starts_of, summary

DRIVE_FRAMES = 40
"""Scans (10 Hz) of each simulated drive."""
STARTS = 2
"""Drifted starts per calibration, besides the log's tf."""


def load_drive(name: str, seed: int, frames: int, folder: Path) -> Case:
    """Rig ``name``'s drive of ``DRIVE_FRAMES`` scans (simulated into ``folder`` once per seed) with ``frames`` of
    its pairs chosen as the workflow chooses them."""
    from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

    log = folder / f"{name}-seed{seed}.mcap"
    if not log.exists():
        size = {"width": 1024, "height": 256} if SIM[name].get("panorama") else {"width": 1280, "height": 720}
        simulate_log(log, SimulationOptions(frames=DRIVE_FRAMES, perturb_deg=2.0, perturb_m=0.12, seed=seed,
                                            **size, **SIM[name]), quiet=True)
    return simulated_case(log, frames)


def _job(name: str, seed: int, frames: int, index: int, folder: str) -> tuple[str, int, int, Outcome]:
    """Worker process: start ``index`` of the rig's drive calibrated on ``frames`` frames, one numba thread."""
    import numba

    numba.set_num_threads(1)
    case = load_drive(name, seed, frames, Path(folder))
    label, T_start = starts_of(case, STARTS, 2.0, 0.12)[index]
    return name, seed, frames, run_start(f"{name} seed {seed} frames {frames}", case, label, T_start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="*", default=["sim-16", "sim-wide-angle", "sim-32", "sim-64"],
                        choices=list(SIM))
    parser.add_argument("--frames", nargs="*", type=int, default=[10, 20, 40])
    parser.add_argument("--seeds", nargs="*", type=int, default=[1, 2])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--jsonl", type=Path, default=None, help="append one JSON line per calibration here")
    args = parser.parse_args()
    if any(not 1 <= n <= DRIVE_FRAMES for n in args.frames):
        parser.error(f"--frames: each between 1 and {DRIVE_FRAMES}")
    by_frames: dict[int, list[Outcome]] = {n: [] for n in args.frames}
    with tempfile.TemporaryDirectory() as folder:
        for name in args.cases:  # simulate each drive once, before the workers read it
            for seed in args.seeds:
                load_drive(name, seed, 1, Path(folder))
        jobs = [(name, seed, n, i) for n in args.frames for name in args.cases for seed in args.seeds
                for i in range(STARTS + 1)]
        with ProcessPoolExecutor(args.jobs) as pool:
            for name, seed, frames, outcome in pool.map(_job, *zip(*jobs, strict=True),
                                                        [folder] * len(jobs)):
                by_frames[frames].append(outcome)
                if args.jsonl is not None:
                    with args.jsonl.open("a") as out:
                        out.write(json.dumps({"case": name, "seed": seed, "frames": frames, **asdict(outcome)}) + "\n")
    print("| frames | " + " | ".join(HEADER[1:]) + " |")
    print("|---" * len(HEADER) + "|")
    for frames, outcomes in by_frames.items():
        print(f"| {frames} | " + " | ".join(summary(outcomes)) + " |")


if __name__ == "__main__":
    main()
