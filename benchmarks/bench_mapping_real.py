"""Odometry on a real drive: fleetcal ``map`` beside KISS-ICP and small_gicp scan-to-scan, in one run.

The sequence is ``kitti_odometry_00_scans_50-100.mcap`` (51 HDL-64E scans, ~38 m, reference poses in its
truth file; ../shared/data). Every method runs in its own fresh Python process on the same decoded scans
and the same thread count:

- ``fleetcal none`` / ``fleetcal intensity``: ``fleetcal map LOG --channels ...`` (amortised: the wall time
  of the command itself, start-up, decoding and writing the outputs included); the steady state is
  measured by a second process that runs the same odometry in-process on already decoded scans.
- ``KISS-ICP``: ``kiss_icp.KissICP`` with its default configuration (voxel = max range / 100 = 1 m),
  de-skew off (the scans carry no per-point times).
- ``small_gicp s2s``: ``small_gicp.preprocess_points`` + ``align`` (GICP) against the previous scan,
  constant-velocity guess, the same voxel size as fleetcal (0.25 m).

Columns: ``s/scan`` steady state (mean over the scans after the first 5, scans already decoded),
``cpu s`` the CPU time of the whole process per scan over the same scans (all its threads: on a machine
whose cores are busy with other work, wall time follows it rather than ``s/scan`` of an idle machine),
``amort`` amortised (process wall time / scans: interpreter, imports, decoding, start-up included),
``start s`` everything that is not per scan (amortised total minus scans x steady state: interpreter,
imports, decoding the log, writing outputs), ``import s`` importing the method and running it once on
a tiny cloud (numba cache load for fleetcal), ``drift %`` end-point translation
error / true path length, ``rel cm`` / ``rel deg`` mean per-scan relative translation / rotation error,
``ATE cm`` RMS position error after the best rigid alignment (Umeyama, no scale).

    .venv/bin/python benchmarks/bench_mapping.py --real --threads 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT.parent / "shared" / "data" / "logs" / "kitti_odometry_00_scans_50-100.mcap"
WARM_SCANS = 5
METHODS = ("fleetcal none", "fleetcal intensity", "KISS-ICP", "small_gicp s2s")


@dataclass
class Run:
    """One method's poses (n, 4, 4) ``T_map_lidar`` and timings, seconds."""

    method: str
    poses: NDArray[np.float64]
    steady_s: float
    amortised_s: float
    import_s: float
    cpu_s: float = float("nan")


def load_scans(log: Path) -> tuple[list[Any], str]:
    """Decoded lidar frames of the log (fleetcal's reader, the same for every method)."""
    from fleetcal.readers.frames import iter_lidar_frames
    from fleetcal.readers.open import open_log

    truth = json.loads(log.with_suffix(".truth.json").read_text())
    with open_log(log) as reader:
        return list(iter_lidar_frames(reader, truth["lidar_topic"])), truth["lidar_topic"]


def _timed(items: list[Any], marks: list[tuple[float, float]]) -> Any:
    """Yield the items, recording the (wall, process CPU) time each one is asked for (the gaps are the
    per-scan times)."""
    for item in items:
        marks.append((time.perf_counter(), time.process_time()))
        yield item
    marks.append((time.perf_counter(), time.process_time()))


def _gaps(marks: list[tuple[float, float]]) -> NDArray[np.float64]:
    """(n, 2) wall and CPU seconds between successive marks."""
    return np.diff(np.asarray(marks), axis=0)


def run_fleetcal_inprocess(frames: list[Any], channels: str) -> tuple[list[NDArray[np.float64]], NDArray[np.float64]]:
    from fleetcal.pipeline.config import Config
    from fleetcal.workflows.mapping import map_frames

    config = Config()
    config.mapping.channels = channels  # type: ignore[assignment]
    marks: list[tuple[float, float]] = []
    steps, _, _ = map_frames(_timed(frames, marks), config)
    return [s.T_map_lidar for s in steps], _gaps(marks)


def run_kiss(frames: list[Any], threads: int) -> tuple[list[NDArray[np.float64]], NDArray[np.float64]]:
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)
    config.data.deskew = False
    config.registration.max_num_threads = threads
    odometry = KissICP(config)
    poses: list[NDArray[np.float64]] = []
    marks: list[tuple[float, float]] = []
    for frame in _timed(frames, marks):
        odometry.register_frame(np.asarray(frame.points_xyz, dtype=np.float64), np.zeros(0))
        poses.append(np.array(odometry.last_pose))
    return poses, _gaps(marks)


def run_small_gicp(
    frames: list[Any], threads: int, voxel_m: float
) -> tuple[list[NDArray[np.float64]], NDArray[np.float64]]:
    import small_gicp

    T_map_lidar, velocity = np.eye(4), np.eye(4)
    target = tree = None
    poses: list[NDArray[np.float64]] = []
    marks: list[tuple[float, float]] = []
    for frame in _timed(frames, marks):
        source, source_tree = small_gicp.preprocess_points(
            np.asarray(frame.points_xyz, dtype=np.float64), voxel_m, num_neighbors=20, num_threads=threads
        )
        if target is not None:
            result = small_gicp.align(target, source, tree, velocity, registration_type="GICP",
                                      num_threads=threads, max_correspondence_distance=1.0)  # fmt: skip
            velocity = result.T_target_source
            T_map_lidar = T_map_lidar @ velocity
        poses.append(T_map_lidar.copy())
        target, tree = source, source_tree
    return poses, _gaps(marks)


def warm_start(method: str, threads: int) -> float:
    """Seconds to import the method and run it once on a tiny cloud (numba cache load for fleetcal)."""
    t0 = time.perf_counter()
    cloud = np.random.default_rng(0).normal(size=(2000, 3)) * 5.0
    if method.startswith("fleetcal"):
        import fleetcal.workflows.cmd_map  # noqa: F401 - what the CLI imports
        from fleetcal.pipeline.config import Config
        from fleetcal.stages.registration import prepare_pointset, register
        from fleetcal.workflows.mapping import registration_config

        config = Config()
        config.mapping.channels = method.split()[1]  # type: ignore[assignment]
        reg = registration_config(config)
        scan = prepare_pointset(cloud, {"intensity": cloud[:, 0]}, reg)
        register(scan, scan, np.eye(4), reg)
    elif method == "KISS-ICP":
        from kiss_icp.config import load_config
        from kiss_icp.kiss_icp import KissICP

        KissICP(load_config(None)).register_frame(cloud, np.zeros(0))
    else:
        import small_gicp

        small_gicp.preprocess_points(cloud, 0.25, num_threads=threads)
    return time.perf_counter() - t0


def worker(method: str, log: Path, threads: int, voxel_m: float, out: Path) -> None:
    """Run one method in this process; write poses, per-scan (wall, CPU) times and start-up to ``out`` (npz)."""
    startup = warm_start(method, threads)
    frames, _ = load_scans(log)
    if method.startswith("fleetcal"):
        poses, times = run_fleetcal_inprocess(frames, method.split()[1])
    elif method == "KISS-ICP":
        poses, times = run_kiss(frames, threads)
    else:
        poses, times = run_small_gicp(frames, threads, voxel_m)
    np.savez(out, poses=np.stack(poses), times=np.asarray(times), startup=startup)


def _subprocess(cmd: list[str], threads: int) -> float:
    """Wall time of a command, seconds (its output kept from the terminal unless it fails)."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "NUMBA_NUM_THREADS": str(threads)}
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")
    return wall


def run_baseline(fleetcal: str, channels: str, log: Path, threads: int, work: Path, n_scans: int) -> Run:
    """Another fleetcal installation's ``fleetcal map`` (amortised only), e.g. the main branch's."""
    out_dir = work / f"baseline_{channels}"
    wall = _subprocess([fleetcal, "map", str(log), "--channels", channels, "--out", str(out_dir), "--quiet"], threads)
    nan = float("nan")
    return Run(f"baseline {channels}", _trajectory(out_dir / "trajectory.parquet"), nan, wall / n_scans, nan)


def run_method(method: str, log: Path, threads: int, voxel_m: float, work: Path) -> Run:
    """Steady state from an in-process worker; amortised from a fresh process (the CLI for fleetcal)."""
    out = work / f"{method.replace(' ', '_')}.npz"
    me = [sys.executable, str(Path(__file__).resolve())]
    worker_args = ["--worker", method, "--log", str(log), "--threads", str(threads), "--voxel", str(voxel_m)]
    wall = _subprocess([*me, *worker_args, "--out", str(out)], threads)
    data = np.load(out)
    poses, times, cpu = data["poses"], data["times"][:, 0], data["times"][:, 1]
    if method.startswith("fleetcal"):
        out_dir = work / method.replace(" ", "_")
        fleetcal = str(Path(sys.executable).with_name("fleetcal"))
        wall = _subprocess([fleetcal, "map", str(log), "--channels", method.split()[1], "--out", str(out_dir),
                            "--quiet", "--json"], threads)  # fmt: skip
        poses = _trajectory(out_dir / "trajectory.parquet")
    return Run(method, poses, float(np.mean(times[WARM_SCANS:])), wall / len(times), float(data["startup"]),
               float(np.mean(cpu[WARM_SCANS:])))  # fmt: skip


def _trajectory(path: Path) -> NDArray[np.float64]:
    import pyarrow.parquet as pq

    from fleetcal.pipeline.transforms import from_quat

    table = pq.read_table(path).to_pydict()
    return np.stack([
        from_quat(np.array([table[k][i] for k in ("tx_m", "ty_m", "tz_m")]),
                  np.array([table[k][i] for k in ("qx", "qy", "qz", "qw")]))
        for i in range(len(table["stamp_ns"]))
    ])  # fmt: skip


def ate_m(est: NDArray[np.float64], true: NDArray[np.float64]) -> float:
    """RMS position error after the best rigid alignment of ``est`` onto ``true`` (Umeyama, no scale)."""
    p, q = est[:, :3, 3], true[:, :3, 3]
    pc, qc = p - p.mean(0), q - q.mean(0)
    U, _, Vt = np.linalg.svd(qc.T @ pc)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return float(np.sqrt(np.mean(np.sum((pc @ R.T - qc) ** 2, axis=1))))


def accuracy(est: NDArray[np.float64], true: NDArray[np.float64]) -> dict[str, float]:
    """Drift % of path, mean relative error per scan (cm, deg) and ATE (cm) of ``est`` against ``true``."""
    from scipy.spatial.transform import Rotation

    from fleetcal.pipeline.transforms import invert, translation_error_m

    path = float(np.sum(np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1)))
    rel_t, rel_r = [], []
    for i in range(1, est.shape[0]):
        rel_est, rel_true = invert(est[i - 1]) @ est[i], invert(true[i - 1]) @ true[i]
        rel_t.append(translation_error_m(rel_est, rel_true))
        rel_r.append(float(np.degrees(Rotation.from_matrix(rel_true[:3, :3].T @ rel_est[:3, :3]).magnitude())))
    return {
        "drift_pct": 100 * translation_error_m(est[-1], true[-1]) / path,
        "rel_cm": 100 * float(np.mean(rel_t)),
        "rel_deg": float(np.mean(rel_r)),
        "ate_cm": 100 * ate_m(est, true),
        "path_m": path,
    }


def memory_worker(n_scans: int) -> None:
    """Peak RSS of ``map_frames`` over ``n_scans`` synthetic scans of one room driven around in circles
    (5000 points each, 10 Hz, 0.3 m and 3 deg per scan): the map stops growing after the first lap, so
    memory that still grows is held per scan."""
    import resource

    from fleetcal.pipeline.config import Config
    from fleetcal.pipeline.frames import LidarFrame
    from fleetcal.pipeline.transforms import apply, from_xyz_rpy, invert
    from fleetcal.workflows.mapping import map_frames

    rng = np.random.default_rng(0)
    boxes = [((-20, -20, 0), (20, -19.9, 4)), ((-20, 19.9, 0), (20, 20, 4)), ((-20, -20, 0), (-19.9, 20, 4)),
             ((19.9, -20, 0), (20, 20, 4)), ((-20, -20, -0.05), (20, 20, 0.0)), ((-3, -3, 0), (3, 3, 2))]  # fmt: skip
    walls = [rng.uniform(lo, hi, (6000, 3)) for lo, hi in boxes]
    world = np.concatenate(walls)

    def scans() -> Any:
        for k in range(n_scans):
            angle = np.radians(3.0 * k)
            T_world_lidar = from_xyz_rpy(6 * np.cos(angle), 6 * np.sin(angle), 1.5, 0, 0, 90 + 3.0 * k)
            pick = rng.choice(world.shape[0], 5000, replace=False)
            yield LidarFrame(1_000_000_000 + k * 100_000_000, "/lidar", "lidar",
                             apply(invert(T_world_lidar), world[pick]).astype(np.float32), {})  # fmt: skip

    config = Config()
    config.mapping.channels = "none"  # type: ignore[assignment]
    steps, voxel_map, _ = map_frames(scans(), config)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"scans": len(steps), "peak_rss_mb": peak_mb, "map_voxels": voxel_map.n_voxels}))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--log", type=Path, default=LOG)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--voxel", type=float, default=0.25, help="small_gicp voxel, m (fleetcal's default)")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--baseline", metavar="FLEETCAL",
                        help="another installation's fleetcal executable to time beside (amortised only)")
    parser.add_argument("--memory", type=int, nargs="*", metavar="SCANS",
                        help="instead: peak memory of mapping synthetic drives of these lengths (e.g. 200 2000)")
    parser.add_argument("--memory-worker", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        worker(args.worker, args.log, args.threads, args.voxel, args.out)
        return 0
    if args.memory_worker:
        memory_worker(args.memory_worker)
        return 0
    if args.memory:
        for n in args.memory:
            proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--memory-worker", str(n)],
                                  capture_output=True, text=True, check=True)  # fmt: skip
            print(proc.stdout.strip())
        return 0
    if not args.log.exists():
        print(f"error: {args.log} not found (../shared/data)", file=sys.stderr)
        return 1
    poses = np.array(json.loads(args.log.with_suffix(".truth.json").read_text())["lidar_poses"])
    from fleetcal.pipeline.transforms import invert

    true = np.stack([invert(poses[0]) @ T for T in poses])
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for method in args.methods.split(","):
            runs.append(run_method(method, args.log, args.threads, args.voxel, Path(tmp)))
        if args.baseline:
            for channels in ("none", "intensity"):
                runs.append(run_baseline(args.baseline, channels, args.log, args.threads, Path(tmp), true.shape[0]))
    kiss = next((r for r in runs if r.method == "KISS-ICP"), None)
    print(f"{args.log.name}: {true.shape[0]} scans, path {accuracy(true, true)['path_m']:.1f} m, "
          f"threads {args.threads}, {os.cpu_count()} cores")  # fmt: skip
    print(f"{'method':<20} {'s/scan':>7} {'x KISS':>6} {'cpu s':>6} {'x KISS':>6} {'amort':>7} {'x KISS':>6} "
          f"{'start s':>7} {'import s':>8} {'drift %':>7} {'rel cm':>6} {'rel deg':>7} {'ATE cm':>6}")  # fmt: skip
    for r in runs:
        acc = accuracy(r.poses, true)
        start = (r.amortised_s - r.steady_s) * true.shape[0]
        ratio = f"{r.steady_s / kiss.steady_s:6.2f}" if kiss else "     -"
        ratio_a = f"{r.amortised_s / kiss.amortised_s:6.2f}" if kiss else "     -"
        ratio_c = f"{r.cpu_s / kiss.cpu_s:6.2f}" if kiss else "     -"
        print(f"{r.method:<20} {r.steady_s:7.3f} {ratio} {r.cpu_s:6.3f} {ratio_c} {r.amortised_s:7.3f} {ratio_a} "
              f"{start:7.2f} {r.import_s:8.2f} "
              f"{acc['drift_pct']:7.2f} {acc['rel_cm']:6.2f} {acc['rel_deg']:7.3f} {acc['ate_cm']:6.1f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    raise SystemExit(main())
