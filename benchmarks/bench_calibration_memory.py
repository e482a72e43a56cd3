"""Peak memory of a calibration against the number of frames it holds, on 1920x1200 images.

Simulates a street log with 1920x1200 pinhole images (``fleetcal simulate``, 64 beams, 1024 columns) in a
temporary folder, then runs the calibrate workflow (``run_calibration``: pairing, lidar feature, image
gradients, the GOM objective and a short swarm) with ``--frames`` 1, 4 and 8, each in a fresh child
process, and prints its peak RSS (``VmHWM``) and the increase per frame. The objective holds every
frame at once (``--joint`` rigs: every camera's too), so this increase times frames x cameras is what a job
needs on top of the interpreter. The swarm is cut short (50 particles, 10 iterations, 1 run): its memory
does not grow with the frames, and the accuracy is not what is measured here.

Measured (2 cores): 286 / 319 / 341 MB at 1 / 4 / 8 frames, 8-11 MB per extra frame, of which a 1920x1200
image's gradients are 2.3 MB: int16 steps (``image_gradients.quantised``) kept at every second pixel (its 3.1 px
blur allows it, ``image_gradients.sampling_stride``); the rest is the scan (65 k points) and the objective's
per-point arrays. The 8-bit grey is held only for ``--metric nmi``. With float32 gradients: 293 / 328 / 347 MB;
with the grey held as well: 293 / 333 / 365 MB; with float32 gradients at every pixel: 326 / 393 / 482 MB.

    .venv/bin/python benchmarks/bench_calibration_memory.py [--frames 1 4 8] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WIDTH, HEIGHT = 1920, 1200


def simulate(path: Path, frames: int) -> None:
    from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

    simulate_log(path, SimulationOptions(frames=frames, scene="street", beams=64, columns=1024, width=WIDTH,
                                         height=HEIGHT, seed=1))


def peak_rss_mb() -> float:
    """This process's peak RSS, MB: ``VmHWM`` on Linux (reset by exec; ``ru_maxrss`` there keeps the peak of
    the parent that forked this process, here the simulator's), else ``ru_maxrss``."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def calibrate_child(path: str, frames: int) -> None:
    """Child process: run the calibrate workflow on ``frames`` pairs; print seconds and peak RSS (MB)."""
    from fleetcal.pipeline.config import Config
    from fleetcal.readers.open import open_log
    from fleetcal.workflows.calibrate import run_calibration
    from fleetcal.workflows.simulator.truth import load_truth, truth_path_for

    truth = load_truth(truth_path_for(Path(path)))
    config = Config()
    config.calibration.frames = frames
    config.calibration.particles = 50
    config.calibration.iterations = 10
    config.calibration.repeats = 1
    start = time.perf_counter()
    with open_log(path) as reader:
        pairs = run_calibration(reader, truth["lidar_topic"], [truth["pairs"][0]["camera_topic"]], config,
                                quiet=True)
    used = len(pairs[0].frames)
    seconds = time.perf_counter() - start
    print(f"{used} {seconds:.2f} {peak_rss_mb():.1f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--dir", default=None, help="folder for the temporary log (default: system temp)")
    parser.add_argument("--child", nargs=2, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        calibrate_child(args.child[0], int(args.child[1]))
        return 0
    root = str(Path(__file__).resolve().parents[1])
    sys.path.insert(0, root)
    env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
    with tempfile.TemporaryDirectory(dir=args.dir) as folder:
        log = Path(folder) / "street_1920x1200.mcap"
        t0 = time.perf_counter()
        simulate(log, max(args.frames))
        print(f"simulated {max(args.frames)} frames of {WIDTH}x{HEIGHT} in {time.perf_counter() - t0:.0f} s")
        rows = []
        for n in sorted(args.frames):
            out = subprocess.run([sys.executable, __file__, "--child", str(log), str(n)], check=True,
                                 capture_output=True, text=True, env=env).stdout.split()
            rows.append((n, int(out[0]), float(out[1]), float(out[2])))
    from fleetcal.stages.calibration.frame import default_blur_sigma_px
    from fleetcal.stages.image_gradients import sampling_stride

    print(f"\n{'--frames':>8} {'used':>5} {'seconds':>8} {'peak RSS MB':>12} {'MB per extra frame':>19}")
    base_n, _, _, base_mb = rows[0]
    for n, used, seconds, peak_mb in rows:
        per = f"{(peak_mb - base_mb) / (n - base_n):.1f}" if n > base_n else "-"
        print(f"{n:>8} {used:>5} {seconds:>8.1f} {peak_mb:>12.1f} {per:>19}")
    stride = sampling_stride(default_blur_sigma_px(WIDTH))
    gradients_mb = 4 * (-(-WIDTH // stride)) * (-(-HEIGHT // stride)) / 1e6
    print(f"(a frame's image part: {gradients_mb:.1f} MB of int16 gradients at a stride of {stride} pixels, 4 bytes a "
          f"kept pixel; with --metric nmi also {WIDTH * HEIGHT / 1e6:.1f} MB of 8-bit grey)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
