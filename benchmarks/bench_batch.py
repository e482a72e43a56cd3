"""``fleetcal batch`` throughput: logs per hour on simulated 64-beam, one-camera logs, and where the time goes.

Run: ``.venv/bin/python benchmarks/bench_batch.py [--frames 12 24] [--workers 2] [--config TOML]``

Simulating and processing a 60 s log (600 scans, ~1.8 GB) takes far longer than a benchmark should, so
this simulates logs of a few lengths (``--frames``, 10 Hz, street scene, 1280x720 rgb8 camera), runs
them through ``workflows.batch.run_batch`` (one dask task per log, ``--workers`` local workers, the
default configuration unless ``--config``), and fits each stage's time from
``ProcessResult.stage_times_s``: calibration uses a fixed number of frames (``calibration.frames``,
whatever the log length), so its time is the mean over the logs (as is ``other``: opening the log,
setup); every other stage (mapping, tables, write-back) grows with the scans and is fitted as
``b * scans`` (least squares through 0).
The fit is extrapolated to ``--target-s`` (default 60 s) and turned into logs/hour assuming
``--workers`` logs run side by side without slowing each other (one single-threaded worker per core).
``--resume`` reuses finished log folders of an earlier run in ``--out-dir`` (stage times read back
from their ``result.json``) to redo only the table.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetcal.pipeline.config import load_config  # noqa: E402
from fleetcal.workflows.batch import run_batch  # noqa: E402
from fleetcal.workflows.process import load_result  # noqa: E402
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, nargs="+", default=[12, 24], help="scans per simulated log")
    parser.add_argument("--workers", type=int, default=2, help="local dask workers (default 2)")
    parser.add_argument("--config", help="fleetcal TOML for process_log (default: the defaults)")
    parser.add_argument("--target-s", type=float, default=60.0, help="log length to extrapolate to, s")
    parser.add_argument("--out-dir", help="working folder (default: a temporary one)")
    parser.add_argument("--resume", action="store_true", help="reuse finished log folders in --out-dir")
    args = parser.parse_args()
    if len(set(args.frames)) < 2:
        parser.error("--frames needs at least two different lengths to fit a + b * scans")

    work = Path(args.out_dir or tempfile.mkdtemp(prefix="fleetcal-bench-batch-"))
    logs = work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    sim_s = 0.0
    for i, frames in enumerate(args.frames):
        path = logs / f"drive{i}_{frames}f.mcap"
        if not path.exists():
            t0 = time.perf_counter()
            simulate_log(path, SimulationOptions(frames=frames, beams=64, cameras=1, seed=i))
            sim_s += time.perf_counter() - t0
    size_mb = sum(p.stat().st_size for p in logs.glob("*.mcap")) / 1e6
    print(f"simulated {len(args.frames)} logs ({size_mb:.0f} MB) in {sim_s:.1f} s under {logs}")

    config = load_config(args.config)
    t0 = time.perf_counter()
    result = run_batch(
        [str(logs / "*.mcap")], work / "out", config, workers=args.workers, quiet=False, resume=args.resume
    )
    wall_s = time.perf_counter() - t0
    failed = [o for o in result.outcomes if o.status == "failed"]
    if failed:
        raise SystemExit(f"benchmark logs failed: {[(o.path, o.error) for o in failed]}")
    for o in result.outcomes:
        if o.status == "skipped":
            o.stage_times_s = load_result(Path(o.out_dir)).stage_times_s

    scans = np.array([float(Path(o.path).stem.split("_")[-1].rstrip("f")) for o in result.outcomes])
    stages = sorted({k for o in result.outcomes for k in o.stage_times_s})
    times = {s: np.array([o.stage_times_s.get(s, 0.0) for o in result.outcomes]) for s in stages}
    totals = np.array([o.runtime_s or 0.0 for o in result.outcomes])
    times["other"] = totals - sum(times.values())
    target_scans = args.target_s * 10.0

    if not args.resume or any(o.status == "ok" for o in result.outcomes):
        print(f"\nmeasured: {len(result.outcomes)} logs in {wall_s:.1f} s wall with {args.workers} workers "
              f"({3600 * len(result.outcomes) / wall_s:.0f} logs/hour at these lengths)")  # fmt: skip
    header = f"{'stage':<14}" + "".join(f"{int(n):>4} scans s" for n in scans)
    header += f"{'fixed s':>10}{'s/scan':>9}{f'{args.target_s:.0f}s log s':>11}{'share':>8}"
    print(header)
    fits = {}
    for stage, values in times.items():
        if stage in ("calibration", "other"):
            fits[stage] = (float(np.mean(values)), 0.0)
        else:
            fits[stage] = (0.0, max(float(np.dot(scans, values) / np.dot(scans, scans)), 0.0))
    total_target = sum(a + b * target_scans for a, b in fits.values())
    for stage, values in times.items():
        a, b = fits[stage]
        t = a + b * target_scans
        cells = "".join(f"{v:>12.1f}" for v in values)
        print(f"{stage:<14}{cells}{a:>10.1f}{b:>9.3f}{t:>11.1f}{100 * t / total_target:>7.1f}%")
    print(f"{'total':<14}" + "".join(f"{v:>12.1f}" for v in totals) + f"{'':>19}{total_target:>11.1f}")
    per_hour = 3600.0 * args.workers / total_target
    print(f"\nextrapolated: {total_target:.0f} s per {args.target_s:.0f} s log per worker -> "
          f"{per_hour:.1f} logs/hour with {args.workers} workers on {os.cpu_count()} cores")  # fmt: skip


if __name__ == "__main__":
    main()
