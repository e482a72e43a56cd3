"""Calibration speed over frames, cameras and rig size, on simulated logs with exact truth and the real
shared logs.

Simulated rigs (``fleetcal simulate``, street, written once per rig to a temporary folder with the most
frames asked for):

- ``ouster64+fisheye``: 64 x 1024 organised cloud + one 1920x1208 equidistant fisheye;
- ``hdl32+6cams``: 32 beams + six 1600x900 pinhole cameras, calibrated with 1 camera (the forward one)
  or all 6 (``--joint``); its log's drift is the lidar mount's (``SimulationOptions.drift = "lidar"``), so the
  tf between the cameras is exact, as ``--joint`` assumes.

Each cell is one ``run_calibration`` (the calibrate workflow: pairing, per-frame stages in process, the
search) from the log's tf with ``--frames`` F, in a fresh child process, and reports wall seconds end to
end, evaluations (candidate poses scored), points x poses per second of search (``points_used`` summed
over the frames x evaluations / search seconds), the child's peak RSS (``VmHWM``) and the error of the
first camera against the truth. The real shared logs follow with their workflow defaults (nuScenes: six
cameras, ``--joint``).

    .venv/bin/python benchmarks/bench_calibration_speed.py [--quick] [--frames 2 5 10 20 40]
        [--markdown docs/performance.md]

``--quick``: frames 2 and 5 (six cameras: 2), a cut-down solver (60 particles, 40 iterations, one run, no confirmation
runs) and KITTI only of the real logs: a few minutes on 2 cores; the seconds then show the cost of the
per-frame work and the throughput, not the time of the defaults. ``--markdown`` replaces the
``## Calibration`` section of that file (the rest is kept).
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RIGS: dict[str, dict[str, Any]] = {
    "ouster64+fisheye": {"beams": 64, "columns": 1024, "organized": True, "fisheye": True, "width": 1920,
                         "height": 1208, "cameras": 1},
    "hdl32+6cams": {"beams": 32, "columns": 1024, "width": 1600, "height": 900, "cameras": 6, "drift": "lidar"},
}
REAL = {"kitti": "kitti_2011_09_26.mcap", "nuscenes": "nuscenes_n015.bag", "pjlab": "pjlab_road_rig1",
        "pjlab-rig2": "pjlab_road_rig2"}
QUICK_SOLVER = {"particles": 60, "iterations": 40, "repeats": 1, "confirm_repeats": 0}
SECTION = "## Calibration"


def peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024.0
    return float("nan")


def child(log: str, frames: int, cameras: int, quick: bool, truth_path: str) -> None:
    """Child process: one calibration of ``log``; prints one JSON line."""
    import numpy as np

    from fleetcal.pipeline.config import Config
    from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
    from fleetcal.readers.open import open_log
    from fleetcal.workflows.calibrate import run_calibration
    from fleetcal.workflows.sensors import resolve_cameras, resolve_lidar

    t0 = time.perf_counter()
    config = Config()
    if frames > 0:
        config.calibration.frames = frames
    if quick:
        for key, value in QUICK_SOLVER.items():
            setattr(config.calibration, key, value)
    with open_log(log) as reader:
        lidar = resolve_lidar(reader, None)
        topics = resolve_cameras(reader, None)[:cameras]
        pairs = run_calibration(reader, lidar, topics, config, joint=len(topics) > 1, quiet=True)
    wall = time.perf_counter() - t0
    truth = json.loads(Path(truth_path).read_text())
    T_true = np.asarray(next(p for p in truth["pairs"] if p["camera_topic"] == pairs[0].camera_topic)
                        ["T_camera_lidar"], dtype=np.float64)
    result = pairs[0].result
    print(json.dumps({
        "wall_s": wall, "search_s": result.runtime_s, "evaluations": result.evaluations,
        "frames": result.frames_used, "points": int(sum(result.points_used)),
        "rot_deg": rotation_error_deg(pairs[0].T_camera_lidar, T_true),
        "trans_cm": 100 * translation_error_m(pairs[0].T_camera_lidar, T_true),
        "verdict": result.verdict, "rss_mb": peak_rss_mb(),
    }))


def run_child(log: Path, frames: int, cameras: int, quick: bool, truth: Path) -> dict[str, Any]:
    cmd = [sys.executable, __file__, "--child", str(log), str(frames), str(cameras), str(int(quick)), str(truth)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def simulate(out: Path, rig: str, frames: int) -> Path:
    from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

    log = out / f"{rig}.mcap"
    simulate_log(log, SimulationOptions(frames=frames, perturb_deg=2.0, perturb_m=0.12, seed=1, **RIGS[rig]),
                 quiet=True)
    return log


def row(label: str, frames: str, cameras: int, r: dict[str, Any]) -> list[str]:
    if "error" in r:
        return [label, frames, str(cameras), "error: " + r["error"][:60], "", "", "", "", ""]
    rate = r["points"] * r["evaluations"] / max(r["search_s"], 1e-9)
    return [label, frames if frames else str(r["frames"]), str(cameras), f"{r['wall_s']:.1f}",
            f"{r['evaluations']}", f"{rate / 1e6:.1f} M", f"{r['rss_mb']:.0f}",
            f"{r['rot_deg']:.3f} / {r['trans_cm']:.1f}", r["verdict"]]


HEADER = ["log", "frames", "cameras", "wall s", "evaluations", "points x poses / s", "peak RSS MB",
          "error deg / cm", "verdict"]


def markdown(lines: list[list[str]], quick: bool, wall_s: float) -> str:
    mode = ("quick mode: frames 2 and 5 (six cameras: 2), the solver cut to 60 particles x 40 iterations, one "
            "run and no confirmation runs, KITTI only of the real logs; the seconds show the per-frame work and the "
            "search's throughput, not the time of the defaults" if quick else "full mode: default solver")
    return "\n".join([
        SECTION,
        "",
        "`fleetcal calibrate` chooses its N pairs by their stamps, spread over the log, and runs the per-frame "
        "work (decoding, lidar feature, image gradients; the equalised grey for NMI) on the engine for those messages "
        "only (in process by default, on dask workers with `--workers N` / `--scheduler`); the search then runs "
        "in the calling process (numba threads over poses).",
        "",
        f"`benchmarks/bench_calibration_speed.py{' --quick' if quick else ''}` ({mode}). Simulated rigs from "
        "the log's tf (2 deg / 12 cm off): `ouster64+fisheye` = 64 x 1024 organised + 1920x1208 fisheye, "
        "`hdl32+6cams` = 32 beams + six 1600x900 cameras (6: `--joint`). Each cell is one calibrate workflow "
        "in a fresh process (per-frame stages in process, `--workers 0`); points x poses / s = points in the "
        "objective x evaluations / search seconds; error of the first camera. "
        f"Ran in {wall_s / 60:.0f} min on {platform.machine()} with 2 cores.",
        "",
        "| " + " | ".join(HEADER) + " |",
        "|" + "|".join("---" for _ in HEADER) + "|",
        *("| " + " | ".join(line) + " |" for line in lines),
        "",
    ])


def write_section(path: Path, section: str) -> None:
    """Replace (or append) the ``## Calibration`` section of ``path``, keeping the other sections."""
    text = path.read_text() if path.exists() else "# Performance\n\n"
    pattern = re.compile(rf"^{re.escape(SECTION)}\n.*?(?=^## |\Z)", re.S | re.M)
    text = pattern.sub(lambda _: section + "\n", text) if pattern.search(text) else text.rstrip() + "\n\n" + section
    path.write_text(text)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        log, frames, cameras, quick, truth = sys.argv[2:7]
        child(log, int(frames), int(cameras), bool(int(quick)), truth)
        return
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, nargs="*", default=None, help="default 2 5 10 20 40 (quick: 2 5)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--markdown", type=Path, default=None)
    args = parser.parse_args()
    frames_list = args.frames or ([2, 5] if args.quick else [2, 5, 10, 20, 40])
    lines: list[list[str]] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fleetcal_speed_") as tmp:
        for rig, options in RIGS.items():
            log = simulate(Path(tmp), rig, max(frames_list))
            truth = log.with_suffix(".truth.json")
            for cameras in sorted({1, options["cameras"]}):
                for frames in frames_list[:1] if args.quick and cameras > 1 else frames_list:
                    lines.append(row(rig, str(frames), cameras, run_child(log, frames, cameras, args.quick, truth)))
                    print(" | ".join(lines[-1]), flush=True)
    from tests.test_calibration_real import LOGS

    for name, path in REAL.items():
        if args.quick and name != "kitti":
            continue
        if not (LOGS / path).exists():
            continue
        truth = LOGS / f"{path.removesuffix('.mcap').removesuffix('.bag')}.truth.json"
        cameras = 6 if name == "nuscenes" else 1
        lines.append(row(name, "", cameras, run_child(LOGS / path, 0, cameras, args.quick, truth)))
        print(" | ".join(lines[-1]), flush=True)
    section = markdown(lines, args.quick, time.perf_counter() - t0)
    print(section)
    if args.markdown is not None:
        write_section(args.markdown, section)
        print(f"wrote the calibration section of {args.markdown}")


if __name__ == "__main__":
    main()
