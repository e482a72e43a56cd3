"""Mapping a lidar that does not de-skew: drift and map sharpness with and without ``deskew``.

Simulates the street twice at the same speed (``workflows.simulator``): once as a driver that de-skews
(every point cast from the scan-stamp pose; the reference) and once as one that does not (each column
cast from the pose at its firing time, reported in that time's lidar frame, with a ``time`` field). Maps
the skewed log with MC-GICP-intensity (the ``map`` defaults) with and without de-skewing, with the true
odometry as guess (as a log's ``/tf`` gives it) or without, and prints per run: the KITTI-style segment
drift over 10 m, the final position error over the path, and the fraction of map voxels farther than
20 cm from the reference log's map.

Run::

    .venv/bin/python benchmarks/bench_deskew.py --speed 15 --scans 100
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import invert
from fleetcal.readers.decode.pointcloud2 import decode_pointcloud2
from fleetcal.readers.open import open_log
from fleetcal.stages.registration.odometry import VoxelMap, relative_translation_drift, run_odometry
from fleetcal.workflows.mapping import registration_config
from fleetcal.workflows.simulator.truth import load_truth, truth_path_for
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

CACHE = Path("/tmp/fleetcal_bench_deskew")


def sequence(speed: float, scans: int, beams: int, deskewed: bool) -> tuple[
        list[LidarFrame], list[NDArray[np.float64]]]:
    log = CACHE / f"street_{speed:g}_{scans}_{beams}_{'deskewed' if deskewed else 'skewed'}.mcap"
    if not log.exists():
        CACHE.mkdir(parents=True, exist_ok=True)
        simulate_log(log, SimulationOptions(frames=scans, scene="street", beams=beams, width=64, height=48,
                                            speed_m_s=speed, deskew=deskewed))  # fmt: skip
    truth = load_truth(truth_path_for(log))
    poses = [np.asarray(s["T_map_lidar"], dtype=np.float64) for s in truth["trajectory"]]
    reader = open_log(log)
    try:
        messages = reader.messages(["/lidar/points"])
        frames = [decode_pointcloud2(reader.deserialize(m), "/lidar/points") for m in messages]
    finally:
        reader.close()
    return frames, [invert(poses[0]) @ T for T in poses]


def mapped(frames: list[LidarFrame], truth: list[NDArray[np.float64]], deskew: bool, tf: bool) -> tuple[
        list[NDArray[np.float64]], NDArray[np.float64], float]:
    config = Config()
    voxel_map = VoxelMap(config.mapping.map_voxel_m)
    started = time.perf_counter()
    steps = run_odometry(frames, registration_config(config), initial_motion=truth if tf else None,
                         voxel_map=voxel_map, deskew=deskew)  # fmt: skip
    return [s.T_map_lidar for s in steps], voxel_map.points(), time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speed", type=float, default=15.0, help="m/s")
    parser.add_argument("--scans", type=int, default=100)
    parser.add_argument("--beams", type=int, default=64)
    args = parser.parse_args()
    ref_frames, ref_truth = sequence(args.speed, args.scans, args.beams, deskewed=True)
    frames, truth = sequence(args.speed, args.scans, args.beams, deskewed=False)
    ref_poses, ref_map, _ = mapped(ref_frames, ref_truth, deskew=True, tf=False)
    tree = cKDTree(ref_map)
    path_m = float(sum(np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in itertools.pairwise(truth)))
    print(f"street at {args.speed:g} m/s, {args.scans} scans of {args.beams} beams, path {path_m:.1f} m "
          f"(reference: the de-skewed log, drift {100 * relative_translation_drift(ref_poses, ref_truth, 10.0):.2f} %)")
    print(f"{'odometry guess':<16}{'deskew':<8}{'drift 10 m %':>13}{'end %':>8}{'map > 20 cm %':>15}{'s/scan':>8}")
    for tf in (False, True):
        for deskew in (False, True):
            poses, points, seconds = mapped(frames, truth, deskew, tf)
            end = float(np.linalg.norm(poses[-1][:3, 3] - truth[-1][:3, 3])) / path_m
            far = float(np.mean(tree.query(points)[0] > 0.2))
            print(f"{'/tf' if tf else 'none':<16}{'on' if deskew else 'off':<8}"
                  f"{100 * relative_translation_drift(poses, truth, 10.0):>13.2f}{100 * end:>8.2f}"
                  f"{100 * far:>15.1f}{seconds / len(frames):>8.3f}")


if __name__ == "__main__":
    main()
