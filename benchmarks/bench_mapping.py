"""Mapping drift on simulated sequences: GICP vs MC-GICP (intensity / color / combined).

Scenes come from the simulator (``workflows.simulator``, public functions only): the poster
``corridor`` (paper Fig. 3: flat walls, texture only) and the ``street`` block. Colour comes from the
simulated cameras through ``stages.colorize`` (true extrinsics), so ``color`` and ``combined`` use the
same path as a real rig. Scans are de-skewed (cast from the scan-stamp pose).

Run::

    .venv/bin/python benchmarks/bench_mapping.py --scene corridor --scans 50
    .venv/bin/python benchmarks/bench_mapping.py --scene street --scans 100
    .venv/bin/python benchmarks/bench_mapping.py --real --threads 2   # real KITTI drive vs KISS-ICP, small_gicp

Prints, per method and odometry mode: final drift (|final position error| / path length), the KITTI-style
segment drift (``relative_translation_drift``), the along-track error and the time per scan.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import invert
from fleetcal.stages.colorize import colorize, fill_unseen
from fleetcal.stages.registration import RegistrationConfig, run_odometry
from fleetcal.stages.registration.odometry import relative_translation_drift

CACHE = Path("/tmp/fleetcal_bench_mapping")


@dataclass
class Sequence:
    """Simulated scans: LidarFrames (intensity, r, g, b) and true ``T_world_lidar`` (n, 4, 4)."""

    frames: list[LidarFrame]
    T_world_lidar: NDArray[np.float64]
    seen_fraction: float


def simulate_sequence(
    scene_name: str,
    n_scans: int,
    beams: int = 32,
    columns: int = 1024,
    cameras: int = 4,
    image_size: tuple[int, int] = (320, 240),
    speed_m_s: float | None = None,
    max_range_m: float = 100.0,
    seed: int = 0,
    cache: bool = True,
) -> Sequence:
    """Simulate ``n_scans`` de-skewed 10 Hz scans of ``scene_name`` with camera colour (cached in /tmp).

    ``max_range_m`` limits the lidar range: on the corridor, 100 m lets the lidar see the corridor's end
    walls (about 28 m ahead and behind), which pin the along-wall motion geometrically; 12 m hides them
    and leaves the along-wall direction to texture alone (the paper's Fig. 3 situation).
    """
    from fleetcal.workflows.simulator.camera import SimCamera, pinhole_camera, render
    from fleetcal.workflows.simulator.lidar import LidarModel, simulate_scan
    from fleetcal.workflows.simulator.motion import LoopMotion
    from fleetcal.workflows.simulator.raycast import build_grid
    from fleetcal.workflows.simulator.scene import build_scene
    from fleetcal.workflows.simulator.truth import build_rig
    from fleetcal.workflows.simulator.write import DEFAULT_SPEED_M_S

    speed = DEFAULT_SPEED_M_S[scene_name] if speed_m_s is None else speed_m_s
    size = f"{image_size[0]}x{image_size[1]}"
    key = f"{scene_name}_{n_scans}_{beams}_{columns}_{cameras}_{size}_{speed}_{max_range_m:g}_{seed}"
    path = CACHE / f"{key}.npz"
    if cache and path.exists():
        data = np.load(path)
        frames = []
        for k in range(n_scans):
            pts = data[f"p{k}"]
            chans = {name: data[f"{name}{k}"] for name in ("intensity", "r", "g", "b")}
            frames.append(LidarFrame(int(data["stamps"][k]), "/lidar", "lidar", pts, chans))
        return Sequence(frames, data["poses"], float(data["seen"]))
    scene = build_scene(scene_name, seed)
    grid = build_grid(scene.triangles)
    motion = LoopMotion(scene.route, speed)
    rig = build_rig(cameras, scene.lidar_height_m, 0.0, 0.0, seed)
    lidar = LidarModel(beams=beams, columns=columns, max_range_m=max_range_m, seed=seed)
    cams = [SimCamera(pinhole_camera(*image_size)) for _ in range(cameras)]
    frames, poses, seen_total, n_total = [], [], 0, 0
    store: dict[str, NDArray[np.generic]] = {}
    for k in range(n_scans):
        t = 0.1 * k
        T_world_base = motion.T_world_base(t)
        T_world_lidar = T_world_base @ rig.T_base_lidar
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0x11DA, k]))
        points, chans = simulate_scan(scene, grid, lidar, T_world_lidar, rng).unorganized()
        views = []
        for i, cam in enumerate(cams):
            img = render(scene, grid, cam, T_world_base @ rig.T_base_cameras[i], rng)
            views.append((img, cam.model, rig.T_camera_lidar[i]))
        rgb, seen = colorize(points, views)
        rgb = fill_unseen(rgb, seen)
        seen_total += int(seen.sum())
        n_total += int(seen.size)
        channels = {"intensity": chans["intensity"], "r": rgb[:, 0], "g": rgb[:, 1], "b": rgb[:, 2]}
        stamp = 1_000_000_000 + k * 100_000_000
        frames.append(LidarFrame(stamp, "/lidar", "lidar", points, channels))
        poses.append(T_world_lidar)
        store[f"p{k}"] = points
        for name, values in channels.items():
            store[f"{name}{k}"] = values
    seq = Sequence(frames, np.stack(poses), seen_total / max(n_total, 1))
    if cache:
        CACHE.mkdir(parents=True, exist_ok=True)
        stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
        np.savez(path, poses=seq.T_world_lidar, stamps=stamps, seen=seq.seen_fraction, **store)  # type: ignore[arg-type]
    return seq


METHODS: tuple[tuple[str, str, str], ...] = (
    ("GICP", "gicp", "none"),
    ("MC-GICP intensity", "mcgicp", "intensity"),
    ("MC-GICP color", "mcgicp", "color"),
    ("MC-GICP combined", "mcgicp", "combined"),
)


@dataclass
class DriftRow:
    label: str
    mode: str
    final_drift: float
    segment_drift: float
    along_track_m: float
    final_error_m: float
    ms_per_scan: float
    failed_pairs: int


def evaluate(seq: Sequence, label: str, method: str, channels: str, mode: str, voxel_m: float) -> DriftRow:
    """Run the odometry and compare with the truth (poses relative to the first scan)."""
    config = RegistrationConfig(method=method, channels=channels, voxel_size_m=voxel_m)
    t0 = time.perf_counter()
    steps = run_odometry(seq.frames, config, mode=mode)  # type: ignore[arg-type]
    elapsed = time.perf_counter() - t0
    truth = np.stack([invert(seq.T_world_lidar[0]) @ T for T in seq.T_world_lidar])
    est = np.stack([s.T_map_lidar for s in steps])
    path = float(np.sum(np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)))
    err = est[-1, :3, 3] - truth[-1, :3, 3]
    heading = truth[-1, :3, 3] - truth[-2, :3, 3]
    heading /= np.linalg.norm(heading)
    return DriftRow(
        label,
        mode,
        float(np.linalg.norm(err)) / path,
        relative_translation_drift(est, truth, segment_m=min(20.0, 0.5 * path)),
        float(err @ heading),
        float(np.linalg.norm(err)),
        1000.0 * elapsed / len(seq.frames),
        sum(1 for s in steps[1:] if not s.converged),
    )


def main() -> None:
    if "--real" in sys.argv[1:]:
        from bench_mapping_real import main as main_real

        raise SystemExit(main_real([a for a in sys.argv[1:] if a != "--real"]))
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scene", default="corridor", choices=("corridor", "street"))
    parser.add_argument("--scans", type=int, default=50)
    parser.add_argument("--beams", type=int, default=32)
    parser.add_argument("--columns", type=int, default=1024)
    parser.add_argument("--voxel", type=float, default=None, help="voxel, m (corridor 0.1, street 0.25)")
    parser.add_argument("--max-range", type=float, default=100.0, help="lidar max range, m")
    parser.add_argument("--modes", default="scan_to_scan,scan_to_map")
    parser.add_argument("--methods", default=",".join(m[0] for m in METHODS))
    args = parser.parse_args()
    voxel = args.voxel if args.voxel is not None else (0.1 if args.scene == "corridor" else 0.25)
    t0 = time.perf_counter()
    seq = simulate_sequence(args.scene, args.scans, args.beams, args.columns, max_range_m=args.max_range)
    truth_path = float(np.sum(np.linalg.norm(np.diff(seq.T_world_lidar[:, :3, 3], axis=0), axis=1)))
    print(
        f"{args.scene}: {args.scans} scans, {args.beams}x{args.columns}, range {args.max_range:g} m, "
        f"path {truth_path:.1f} m, "
        f"{100 * seq.seen_fraction:.0f} % of points coloured by cameras, voxel {voxel} m "
        f"(simulated/loaded in {time.perf_counter() - t0:.0f} s)"
    )
    wanted = set(args.methods.split(","))
    print(
        f"{'method':<20} {'mode':<13} {'final drift':>11} {'seg drift':>9} {'along m':>8} "
        f"{'err m':>7} {'ms/scan':>8} {'failed':>6}"
    )
    for mode in args.modes.split(","):
        for label, method, channels in METHODS:
            if label not in wanted:
                continue
            row = evaluate(seq, label, method, channels, mode, voxel)
            print(
                f"{row.label:<20} {row.mode:<13} {100 * row.final_drift:>10.2f}% "
                f"{100 * row.segment_drift:>8.2f}% {row.along_track_m:>8.3f} {row.final_error_m:>7.3f} "
                f"{row.ms_per_scan:>8.0f} {row.failed_pairs:>6d}",
                flush=True,
            )


if __name__ == "__main__":
    main()
