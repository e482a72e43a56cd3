"""Pairwise registration benchmark: fleetcal GICP / MC-GICP / Color-ICP beside small_gicp and Open3D.

Every method gets the same raw clouds, the same voxel size, k = 20 neighbours, the same maximum
correspondence distance, convergence thresholds (0.1 deg, 1 mm) and thread count. Two timings per
method, median of ``--repeats`` runs after one warm-up:

- ``prep_ms``: downsampling + kd-tree + covariances of both clouds;
- ``align_ms``: the registration itself on the prepared clouds (the "time per pair" of odometry,
  where each scan is prepared once and used twice).

Datasets: the real ``outdoor_scan_pair.mcap`` (reference T_target_source; ../shared/data) and a
synthetic 64-beam scan pair (ray-cast street with textured walls, known motion).
small_gicp and Open3D are optional (``pip install small_gicp open3d``); never imported by fleetcal.

    .venv/bin/python benchmarks/bench_registration.py --threads 2 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fleetcal.pipeline.transforms import apply, from_xyz_rpy, invert, rotation_error_deg, translation_error_m  # noqa: E402

SHARED_LOGS = ROOT.parent / "shared" / "data" / "logs"


@dataclass
class Cloud:
    points_xyz: NDArray[np.float64]
    channels: dict[str, NDArray[np.generic]]


@dataclass
class Pair:
    name: str
    target: Cloud
    source: Cloud
    T_target_source: NDArray[np.float64]


@dataclass
class Row:
    dataset: str
    method: str
    prep_ms: float
    align_ms: float
    align_min_ms: float
    t_err_cm: float
    r_err_deg: float
    iterations: int


def load_outdoor() -> Pair | None:
    log = SHARED_LOGS / "outdoor_scan_pair.mcap"
    if not log.exists():
        return None
    from fleetcal.readers.decode import decode_pointcloud2
    from fleetcal.readers.open import open_log

    truth = json.loads(log.with_suffix(".truth.json").read_text())
    reader = open_log(log)
    frames = [
        decode_pointcloud2(reader.deserialize(raw), raw.topic, raw.log_time_ns)
        for raw in reader.messages([truth["lidar_topic"]])
    ]
    reader.close()
    reg = truth["registration"]
    clouds = [Cloud(f.points_xyz.astype(np.float64), dict(f.channels)) for f in frames]
    return Pair(
        "outdoor", clouds[reg["target_index"]], clouds[reg["source_index"]], np.array(reg["T_target_source"])
    )


def _raycast_street(T_world_lidar: NDArray[np.float64], rng: np.random.Generator) -> Cloud:
    """64 beams (-24.8..+2 deg) x 1024 azimuths from a sensor at T_world_lidar in a textured street."""
    elevation = np.radians(np.linspace(-24.8, 2.0, 64))
    azimuth = np.linspace(-np.pi, np.pi, 1024, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    dirs_lidar = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    R, origin = T_world_lidar[:3, :3], T_world_lidar[:3, 3]
    dirs = dirs_lidar @ R.T
    best = np.full(dirs.shape[0], np.inf)
    # axis-aligned boxes (min, max): ground slab, two facades, parked cars, poles
    boxes = [
        ((-200, -200, -3.0), (200, 200, -1.8)),
        ((-200, 8.0, -3), (200, 12, 15)),
        ((-200, -12, -3), (200, -7.5, 12)),
        ((5, 4, -1.8), (9.5, 6, -0.3)),
        ((-14, -5.5, -1.8), (-9.5, -3.5, -0.4)),
        ((18, 3, -1.8), (22.5, 5, -0.2)),
        ((3, -6.5, -1.8), (3.3, -6.2, 3.0)),
        ((-6, 6.5, -1.8), (-5.7, 6.8, 3.0)),
        ((12, -6.8, -1.8), (12.3, -6.5, 3.0)),
    ]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        for lo, hi in boxes:
            t1 = (np.array(lo) - origin) * inv
            t2 = (np.array(hi) - origin) * inv
            t_near = np.nanmax(np.minimum(t1, t2), axis=1)
            t_far = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (t_far >= t_near) & (t_near > 0.5)
            best = np.where(hit & (t_near < best), t_near, best)
    keep = best < 80.0
    rng_m = best[keep] + rng.normal(0, 0.01, keep.sum())
    points_lidar = dirs_lidar[keep] * rng_m[:, None]
    world = apply(T_world_lidar, points_lidar)
    stripes = 0.5 + 0.5 * np.sin(world[:, 0] * 2.1) * np.cos(world[:, 2] * 3.3)
    intensity = (20 + 60 * stripes + rng.normal(0, 3, keep.sum())).astype(np.float32)
    rgb = {
        c: np.clip(127 + 110 * np.sin(world[:, 0] * f + world[:, 2] * 0.7), 0, 255).astype(np.uint8)
        for c, f in zip("rgb", (0.9, 1.7, 2.6), strict=True)
    }
    return Cloud(points_lidar, {"intensity": intensity, **rgb})


def synthetic_pair() -> Pair:
    rng = np.random.default_rng(0)
    T_world_target = from_xyz_rpy(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    T_world_source = from_xyz_rpy(1.2, 0.1, 0.02, 0.3, -0.2, 2.0)
    return Pair(
        "synthetic64",
        _raycast_street(T_world_target, rng),
        _raycast_street(T_world_source, rng),
        invert(T_world_target) @ T_world_source,
    )


_LAST_MIN_MS = [0.0]


def _median_ms(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """(median ms over ``repeats`` runs after a warm-up, last output); the minimum goes to _LAST_MIN_MS."""
    out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - t0) * 1e3)
    _LAST_MIN_MS[0] = min(times)
    return statistics.median(times), out


def _row(pair: Pair, method: str, prep_ms: float, align_ms: float, T: NDArray[np.float64], iterations: int) -> Row:
    """A table row: errors of ``T`` (T_target_source) against the pair's truth, the last run's minimum time."""
    return Row(
        pair.name,
        method,
        prep_ms,
        align_ms,
        _LAST_MIN_MS[0],
        translation_error_m(T, pair.T_target_source) * 100,
        rotation_error_deg(T, pair.T_target_source),
        iterations,
    )


def bench_fleetcal(pair: Pair, args: argparse.Namespace) -> list[Row]:
    from fleetcal.stages.registration import RegistrationConfig, prepare_pointset, register

    modes = [("gicp", "none"), ("mcgicp", "intensity"), ("color_icp", "intensity")]
    if "r" in pair.source.channels:
        modes += [("mcgicp", "color"), ("mcgicp", "combined"), ("color_icp", "color")]
    rows = []
    for method, channels in modes:
        for robust in ("none", "cauchy") if method == "gicp" else ("none",):
            config = RegistrationConfig(
                method=method,
                channels=channels,
                voxel_size_m=args.voxel,
                k_neighbors=20,
                max_correspondence_distance_m=args.max_corr,
                workers=args.threads,
                robust_kernel=robust,
            )

            def prep(config: RegistrationConfig = config) -> tuple:
                return (
                    prepare_pointset(pair.target.points_xyz, pair.target.channels, config),
                    prepare_pointset(pair.source.points_xyz, pair.source.channels, config),
                )

            prep_ms, prepared = _median_ms(prep, args.repeats)
            target, source = prepared
            target.tree  # noqa: B018 - build the tree outside the timed alignment, like small_gicp's KdTree
            align_ms, result = _median_ms(partial(register, source, target, np.eye(4), config), args.repeats)
            label = f"fleetcal {method}" + (f"-{channels}" if channels != "none" else "")
            label += "" if robust == "none" else f" ({robust})"
            T = result.T_target_source
            rows.append(
                _row(pair, label, prep_ms, align_ms, T, result.iterations)
            )
    return rows


def bench_small_gicp(pair: Pair, args: argparse.Namespace) -> list[Row]:
    try:
        import small_gicp
    except ImportError:
        print("small_gicp not importable: skipped", file=sys.stderr)
        return []

    def prep() -> tuple:
        t, tree = small_gicp.preprocess_points(
            pair.target.points_xyz, args.voxel, num_neighbors=20, num_threads=args.threads
        )
        s, _ = small_gicp.preprocess_points(
            pair.source.points_xyz, args.voxel, num_neighbors=20, num_threads=args.threads
        )
        return t, tree, s

    prep_ms, (target, tree, source) = _median_ms(prep, args.repeats)
    align_ms, result = _median_ms(
        lambda: small_gicp.align(
            target,
            source,
            tree,
            registration_type="GICP",
            max_correspondence_distance=args.max_corr,
            num_threads=args.threads,
            max_iterations=64,
        ),
        args.repeats,
    )
    T = result.T_target_source
    # small_gicp's ``iterations`` is the index of its last linearisation (0 after one): counted here as
    # linearisations, like fleetcal's.
    return [
        _row(pair, "small_gicp GICP", prep_ms, align_ms, T, result.iterations + 1)
    ]


def bench_open3d(pair: Pair, args: argparse.Namespace) -> list[Row]:
    try:
        import open3d as o3d
    except ImportError:
        print("open3d not importable: skipped", file=sys.stderr)
        return []
    reg = o3d.pipelines.registration
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=64)

    def cloud(c: Cloud) -> object:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(c.points_xyz))
        if "r" in c.channels:
            rgb = np.stack([c.channels[k] for k in "rgb"], 1).astype(np.float64) / 255.0
            pc.colors = o3d.utility.Vector3dVector(rgb)
        pc = pc.voxel_down_sample(args.voxel)
        pc.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(20))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        return pc

    prep_ms, (target, source) = _median_ms(lambda: (cloud(pair.target), cloud(pair.source)), args.repeats)
    rows = []
    runs = [
        (
            "open3d GICP",
            lambda: reg.registration_generalized_icp(
                source,
                target,
                args.max_corr,
                np.eye(4),
                reg.TransformationEstimationForGeneralizedICP(),
                criteria,
            ),
        )
    ]
    if "r" in pair.source.channels:
        runs.append(
            (
                "open3d colored ICP",
                lambda: reg.registration_colored_icp(
                    source,
                    target,
                    args.voxel,
                    np.eye(4),
                    reg.TransformationEstimationForColoredICP(),
                    criteria,
                ),
            )
        )
    for label, fn in runs:
        align_ms, result = _median_ms(fn, args.repeats)
        T = np.asarray(result.transformation)
        rows.append(
            _row(pair, label, prep_ms, align_ms, T, -1)
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--voxel", type=float, default=0.25)
    parser.add_argument("--max-corr", type=float, default=1.0)
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import numba

    numba.set_num_threads(max(1, min(args.threads, os.cpu_count() or 1)))
    pairs = [p for p in (load_outdoor(), synthetic_pair()) if p is not None]
    print(
        f"threads={args.threads} voxel={args.voxel} m k=20 max_corr={args.max_corr} m repeats={args.repeats}"
    )
    for pair in pairs:
        rows = bench_fleetcal(pair, args) + bench_small_gicp(pair, args) + bench_open3d(pair, args)
        ref = next((r for r in rows if r.method == "small_gicp GICP"), None)
        print(
            f"\n{pair.name}: {pair.target.points_xyz.shape[0]} / {pair.source.points_xyz.shape[0]} raw points"
        )
        print(
            f"{'method':34s} {'prep ms':>8s} {'align ms':>9s} {'x sg':>6s} {'min ms':>7s} {'x sg':>6s} "
            f"{'err cm':>7s} {'err deg':>8s} {'iters':>5s}"
        )
        for r in rows:
            ratio = f"{r.align_ms / ref.align_ms:6.2f}" if ref else "     -"
            ratio_min = f"{r.align_min_ms / ref.align_min_ms:6.2f}" if ref else "     -"
            print(
                f"{r.method:34s} {r.prep_ms:8.1f} {r.align_ms:9.1f} {ratio} "
                f"{r.align_min_ms:7.1f} {ratio_min} "
                f"{r.t_err_cm:7.2f} {r.r_err_deg:8.3f} {r.iterations:5d}"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
