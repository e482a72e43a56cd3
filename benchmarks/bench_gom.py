"""GOM calibration benchmark: kernel speed and accuracy on the real logs.

Prints (1) the time of one GOM evaluation per pose within a 200-pose batch for an 80k-point scan
against a 1242x375 image, (2) a table of rotation / translation error vs the ``.truth.json``
reference and runtime for every available real log x {gom, nmi, levinson} with the workflow's
defaults (``fleetcal calibrate``: range+normals, 3 seeded repeats), and (3) with
``--seeds N`` the KITTI robustness study: starts 5 deg / 0.5 m off on random axes, search 10 deg / 1 m
(the auto gradient viewpoint then takes the lidar's own sphere and the swarm explores first), and
(4) with ``--rings N`` the sparse-ring study: a simulated VLP-16 (16 rings 2 deg apart, 1800 columns,
street, 10 frames) from N starts 2 deg / 10 cm off, ring smoothing auto vs off, and (5) with ``--sweep``
the motion-distortion study: a simulated street whose scans are not de-skewed, per-point times vs
scan stamps at several speeds.

    .venv/bin/python benchmarks/bench_gom.py [--seeds 10] [--logs kitti pjlab nuscenes] [--skip-table]
        [--sim [sim-street sim-open-normals ...]]   (simulated logs with exact truth; alone: all)
        [--rings 5] [--sweep [5 10 15]]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.config import Config
from fleetcal.stages.calibration import CalibrationResult, GomScorer, GradientPlanes, calibrate
from fleetcal.workflows.calibrate import solver_config
from tests.test_calibration_real import LOGS, errors, load_real_frames
from tests.test_calibration_synthetic import perturb

CASES = {  # feature: the workflow default (range+normals) unless named
    "kitti": ("kitti_2011_09_26.mcap", {}),
    "pjlab": ("pjlab_road_rig1", {}),
    "pjlab-rig2": ("pjlab_road_rig2", {}),
    "nuscenes": ("nuscenes_n015.bag", {"cameras": 6, "ego_motion": True}),
    "kitti-range": ("kitti_2011_09_26.mcap", {"feature": "range"}),
    "pjlab-range": ("pjlab_road_rig1", {"feature": "range"}),
    "nuscenes-range": ("nuscenes_n015.bag", {"cameras": 6, "ego_motion": True, "feature": "range"}),
    "nuscenes-range-no-ego": ("nuscenes_n015.bag", {"cameras": 6, "ego_motion": False, "feature": "range"}),
    "nuscenes-no-ego": ("nuscenes_n015.bag", {"cameras": 6, "ego_motion": False}),
    "nuscenes-logr": ("nuscenes_n015.bag", {"cameras": 6, "ego_motion": True, "feature": "log_range"}),
    "nuscenes-logr-no-ego": ("nuscenes_n015.bag", {"cameras": 6, "ego_motion": False, "feature": "log_range"}),
    "kitti-logr": ("kitti_2011_09_26.mcap", {"feature": "log_range"}),
}


def bench_kernel(n_points: int = 80_000, n_poses: int = 200, repeats: int = 5) -> None:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    cam = CameraModel(1242, 375, np.array([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]]), np.zeros(5))
    uv = rng.random((n_points, 2)) * [1242, 375]
    uv = uv[np.lexsort((uv[:, 0], np.floor(uv[:, 1] / 4)))]  # scan-like order, as calibrate() sorts
    pts = cam.unproject(uv) * (5 + 30 * rng.random(n_points))[:, None]
    lidar_gx, lidar_gy = rng.standard_normal(n_points), rng.standard_normal(n_points)
    lidar_mag = rng.random(n_points)
    image = GradientPlanes.of(rng.standard_normal((375, 1242)), rng.standard_normal((375, 1242)), cam)
    scorer = GomScorer(pts, lidar_gx, lidar_gy, lidar_mag, image, cam)
    T = np.tile(np.eye(4), (n_poses, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.standard_normal((n_poses, 3)) * 0.005).as_matrix()
    scorer.score(T[:2])
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        batch = scorer.score(T)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    best = int(np.argmin(wall))
    print(f"GOM evaluation, {n_points} points all in view, 1242x375 image, batch of {n_poses} poses: "
          f"{wall[best] / n_poses * 1e3:.2f} ms wall per pose (best of {repeats}; median "
          f"{np.median(wall) / n_poses * 1e3:.2f}), {cpu[best] / n_poses * 1e3:.2f} ms CPU per pose; "
          f"{int(batch.counts.mean())} points projected")


def verdict_of(result: CalibrationResult) -> str:
    """The verdict, with ``+t held`` where the translation was held at the initial guess's."""
    return result.verdict + ("+t held" if result.translation_held else "")


def table(names: list[str], metrics: list[str]) -> None:
    print(f"\n{'log':18s} {'metric':9s} {'rot_deg':>8s} {'trans_m':>8s} {'score':>8s} {'init':>8s} "
          f"{'runtime_s':>9s} {'frames':>6s} verdict   (log tf start: rot_deg trans_m)")
    print("(+t held: no 6-DoF run confirmed another and the translation was held at the log's)")
    for name in names:
        log, kwargs = CASES[name]
        if not (LOGS / log).exists():
            print(f"{name:18s} skipped: {LOGS / log} not present")
            continue
        problem = load_real_frames(log, **kwargs)  # type: ignore[arg-type]
        r0, t0 = errors(problem.T_init, problem.T_true)
        for metric in metrics:
            result = calibrate(problem.frames, problem.T_init, replace(solver_config(Config()), metric=metric))
            rot, trans = errors(result.T_camera_lidar, problem.T_true)
            print(f"{name:18s} {metric:9s} {rot:8.3f} {trans:8.3f} {result.score:8.4f} "
                  f"{result.initial_score:8.4f} {result.runtime_s:9.1f} {result.frames_used:6d} "
                  f"{verdict_of(result):9s} ({r0:.2f} {t0:.3f})",
                  flush=True)


SIM_CASES = {  # name: (scene, feature, search_deg, search_m, beams); the logs' tf is 5 deg / 0.5 m off
    "sim-street": ("street", "intensity", 10.0, 1.0, 64),
    "sim-street-box5": ("street", "intensity", 5.0, 0.5, 64),
    "sim-street-32beams": ("street", "intensity", 10.0, 1.0, 32),
    "sim-street-16beams": ("street", "intensity", 10.0, 1.0, 16),
    "sim-open-intensity": ("open", "intensity", 5.0, 0.5, 64),
    "sim-open-range": ("open", "range", 5.0, 0.5, 64),
    "sim-open-normals": ("open", "normals", 5.0, 0.5, 64),
}


def sim_table(names: list[str], metrics: list[str]) -> None:
    """Simulated logs (10 frames, 64 beams unless named x 512 columns, 640x360), exact truth."""
    import tempfile

    from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
    from fleetcal.stages.calibration import SolverConfig
    from tests.test_calibration_sim import simulated_frames

    print(f"\n{'simulated':18s} {'metric':9s} {'rot_deg':>8s} {'trans_m':>8s} {'score':>8s} {'init':>8s} "
          f"{'runtime_s':>9s} {'box':>9s} viewpoint verdict")
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            scene, feature, deg, metres, beams = SIM_CASES[name]
            frames, T_init, T_true = simulated_frames(Path(tmp), scene, feature, 10, beams)
            for metric in metrics:
                cfg = SolverConfig(metric=metric, search_deg=deg, search_m=metres, repeats=3)
                result = calibrate(frames, T_init, cfg)
                rot = rotation_error_deg(result.T_camera_lidar, T_true)
                trans = translation_error_m(result.T_camera_lidar, T_true)
                print(f"{name:18s} {metric:9s} {rot:8.3f} {trans:8.3f} {result.score:8.4f} "
                      f"{result.initial_score:8.4f} {result.runtime_s:9.1f} {deg:4.0f}/{metres:.1f}m "
                      f"{result.gradient_viewpoint:9s} {verdict_of(result)}", flush=True)


def rings_study(n: int) -> None:
    """Simulated VLP-16 from ``n`` starts 2 deg / 10 cm off (seeds 7, 8, ...): ring smoothing auto vs off."""
    import tempfile

    from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
    from fleetcal.stages.calibration import SolverConfig
    from tests.test_calibration_sim import simulated_frames

    print(f"\nsimulated VLP-16 (16 rings x 1800 columns, street, intensity) from 2 deg / 10 cm, {n} starts")
    print(f"{'start':>5s} {'smoothing':9s} {'sigma_px':>8s} {'rot_deg':>8s} {'trans_m':>8s} {'runtime_s':>9s} verdict")
    within = {"auto": 0, "off": 0}
    with tempfile.TemporaryDirectory() as tmp:
        frames, _, T_true = simulated_frames(Path(tmp), "street", "intensity", 10, beams=16, columns=1800)
        for seed in range(7, 7 + n):
            T_start = perturb(T_true, 2.0, 0.1, seed=seed)
            for mode in ("auto", "off"):
                result = calibrate(frames, T_start, SolverConfig(repeats=3, ring_smoothing=mode))
                rot = rotation_error_deg(result.T_camera_lidar, T_true)
                trans = translation_error_m(result.T_camera_lidar, T_true)
                within[mode] += rot <= 0.5
                print(f"{seed:5d} {mode:9s} {result.ring_smoothing_px:8.2f} {rot:8.3f} {trans:8.3f} "
                      f"{result.runtime_s:9.1f} {result.verdict}", flush=True)
    print(f"  rotation within 0.5 deg: auto {within['auto']} of {n}, off {within['off']} of {n}")


def sweep_study(speeds: list[float]) -> None:
    """Simulated motion-distorted street (columns fired over 0.1 s, 640x360 x 512 columns, intensity) at
    each speed, from 5 deg / 0.5 m in a 10 deg / 1 m box, 3 seeded repeats (the workflow's): points moved
    by their own time field vs each scan by its stamp (``calibration.point_times``)."""
    import tempfile

    from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
    from fleetcal.stages.calibration import SolverConfig
    from tests.test_calibration_sim import simulated_frames

    print("\nmotion during the sweep (simulated street, not de-skewed), from 5 deg / 0.5 m, box 10 deg / 1 m")
    print(f"{'speed_m_s':>9s} {'motion':12s} {'rot_deg':>8s} {'trans_m':>8s} {'runtime_s':>9s} verdict")
    with tempfile.TemporaryDirectory() as tmp:
        for speed in speeds:
            for point_times in (True, False):
                frames, T_init, T_true = simulated_frames(Path(tmp), "street", "intensity", 10,
                                                          skewed_at_m_s=speed, point_times=point_times)
                result = calibrate(frames, T_init, SolverConfig(search_deg=10.0, search_m=1.0, repeats=3))
                rot = rotation_error_deg(result.T_camera_lidar, T_true)
                trans = translation_error_m(result.T_camera_lidar, T_true)
                label = "point times" if point_times else "scan stamp"
                print(f"{speed:9.1f} {label:12s} {rot:8.3f} {trans:8.3f} {result.runtime_s:9.1f} {result.verdict}",
                      flush=True)


def seeds_study(n: int) -> None:
    log = "kitti_2011_09_26.mcap"
    if not (LOGS / log).exists():
        print(f"seed study skipped: {LOGS / log} not present")
        return
    problem = load_real_frames(log)
    print(f"\nKITTI from 5 deg / 0.5 m offsets (random axes), search 10 deg / 1 m, {n} seeds")
    ok = 0
    for seed in range(n):
        T_start = perturb(problem.T_true, 5.0, 0.5, seed=100 + seed)
        cfg = replace(solver_config(Config()), search_deg=10.0, search_m=1.0, seed=seed)
        result = calibrate(problem.frames, T_start, cfg)
        rot, trans = errors(result.T_camera_lidar, problem.T_true)
        good = rot <= 0.3 and trans <= 0.10
        ok += good
        print(f"  seed {seed}: {rot:.3f} deg {trans:.3f} m score {result.score:.4f} "
              f"runtime {result.runtime_s:.1f} s verdict {result.verdict} {'ok' if good else 'FAIL'}", flush=True)
    print(f"  within 0.3 deg / 10 cm: {ok} of {n}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--logs", nargs="*", default=list(CASES), choices=list(CASES))
    parser.add_argument("--metrics", nargs="*", default=["gom", "nmi", "levinson"])
    parser.add_argument("--seeds", type=int, default=0, help="KITTI offset study with this many seeds")
    parser.add_argument("--rings", type=int, default=0, help="simulated VLP-16 study with this many starts")
    parser.add_argument("--sweep", nargs="*", type=float, default=None, metavar="M_S",
                        help="motion-distortion study at these speeds (alone: 5 10 15)")
    parser.add_argument("--skip-table", action="store_true")
    parser.add_argument("--sim", nargs="*", default=None, choices=list(SIM_CASES),
                        help="simulated cases to add (give the flag alone for all)")
    args = parser.parse_args()
    bench_kernel()
    if not args.skip_table:
        table(args.logs, args.metrics)
    if args.sim is not None:
        sim_table(args.sim or list(SIM_CASES), args.metrics)
    if args.seeds:
        seeds_study(args.seeds)
    if args.rings:
        rings_study(args.rings)
    if args.sweep is not None:
        sweep_study(args.sweep or [5.0, 10.0, 15.0])


if __name__ == "__main__":
    main()
