"""Recipe: lidar odometry and a voxel map with GICP or MC-GICP (``mapping.channels``) over one lidar topic.

Per-frame work (decoding, downsampling, covariances, descriptors) runs on the engine in log order; the
odometry chain (each scan against the local map) and the voxel map consume the prepared scans as they
arrive. In-process, the preparation runs on a background thread one or two scans ahead.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import queue
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.engine import Engine
from fleetcal.pipeline.errors import ConfigError, InputError, TransformError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import TransformTree, root_of, to_quat, translation_error_m
from fleetcal.readers.base import LogReader
from fleetcal.readers.frames import load_tf_tree
from fleetcal.stages.registration.config import RegistrationConfig
from fleetcal.stages.registration.deskew import sweep_twist
from fleetcal.stages.registration.gicp import register
from fleetcal.stages.registration.odometry import OdometryStep, VoxelMap, run_odometry
from fleetcal.stages.registration.pointset import PointSet, pointset_from_frame
from fleetcal.stages.sinks import report
from fleetcal.stages.sinks.tables import TRAJECTORY_SCHEMA, map_table, write_rows, write_table
from fleetcal.workflows.frame_sources import LogFrames

log = logging.getLogger(__name__)
T = TypeVar("T")

CHANNEL_MODES = ("none", "intensity", "color", "combined")
MIN_FITNESS = 0.3
"""A registration with a lower fitness (share of points with a correspondence) counts as failed."""
MAX_WARNED_SCANS = 20
"""Per-scan odometry warnings printed at most; the rest are counted in one line."""


@dataclass
class MappingOutcome:
    """Trajectory (one step per scan) and the voxel map, map frame = first scan's lidar frame."""

    lidar_topic: str
    lidar_frame: str
    channels: str
    steps: list[OdometryStep]
    map_points_xyz: NDArray[np.float64]
    map_channels: dict[str, NDArray[Any]]
    scans_skipped: int
    used_tf_odometry: bool
    max_speed_m_s: float = float("inf")

    def failed_scans(self) -> list[int]:
        """Indices of the scans whose registration against the previous one failed (not converged, or
        fitness below ``MIN_FITNESS``)."""
        return [s.index for s in self.steps[1:] if not s.converged or s.fitness < MIN_FITNESS]

    def speeds_m_s(self) -> list[float]:
        """Speed of each scan's motion from the previous one, m/s (first scan: 0). Scans stamped at the
        previous one's time are given the log's median scan interval; NaN (not judged) where every scan
        has the same stamp."""
        dts = [(b.stamp_ns - a.stamp_ns) * 1e-9 for a, b in zip(self.steps, self.steps[1:], strict=False)]
        positive = [dt for dt in dts if dt > 0]
        typical = float(np.median(positive)) if positive else 0.0
        speeds = [0.0]
        for dt, step in zip(dts, self.steps[1:], strict=True):
            dist = float(np.linalg.norm(step.T_prev_curr[:3, 3]))
            dt = dt if dt > 0 else typical
            speeds.append(dist / dt if dt > 0 else float("nan"))
        return speeds

    def implausible_scans(self) -> list[int]:
        """Indices of the scans that moved faster than ``max_speed_m_s`` from the previous one."""
        return [s.index for s, v in zip(self.steps, self.speeds_m_s(), strict=True) if v > self.max_speed_m_s]

    def warnings(self) -> list[str]:
        """One line per scan with implausible odometry or a failed registration (at most
        ``MAX_WARNED_SCANS``, then a count of the rest)."""
        speeds = self.speeds_m_s()
        failed = set(self.failed_scans())
        lines = []
        for k, step in enumerate(self.steps):
            reasons = []
            if speeds[k] > self.max_speed_m_s:
                dist = float(np.linalg.norm(step.T_prev_curr[:3, 3]))
                reasons.append(f"moves {dist:.1f} m from the previous scan ({speeds[k]:.0f} m/s, above "
                               f"mapping.max_speed_m_s = {self.max_speed_m_s:g}): implausible odometry")
            if step.index in failed:
                reasons.append(f"registration failed (fitness {step.fitness:.2f}"
                               + ("" if step.converged else ", not converged") + ")")
            if reasons:
                lines.append(f"scan {step.index} at {step.stamp_ns} ns: {'; '.join(reasons)}")
        if len(lines) > MAX_WARNED_SCANS:
            lines = [*lines[:MAX_WARNED_SCANS], f"... and {len(lines) - MAX_WARNED_SCANS} more scans like these"]
        return lines

    @property
    def path_length_m(self) -> float:
        return float(sum(translation_error_m(a.T_map_lidar, b.T_map_lidar)
                         for a, b in zip(self.steps, self.steps[1:], strict=False)))  # fmt: skip

    def summary(self) -> dict[str, Any]:
        fitness = [s.fitness for s in self.steps[1:]]
        failed = self.failed_scans()
        return {
            "lidar_topic": self.lidar_topic,
            "lidar_frame": self.lidar_frame,
            "channels": self.channels,
            "scans": len(self.steps),
            "scans_skipped": self.scans_skipped,
            "path_length_m": self.path_length_m,
            "mean_fitness": float(np.mean(fitness)) if fitness else None,
            "failed_pairs": failed,
            "implausible_motion": self.implausible_scans(),
            "degenerate_pairs": [s.index for s in self.steps[1:] if s.degenerate],
            "map_points": int(self.map_points_xyz.shape[0]),
            "used_tf_odometry": self.used_tf_odometry,
            "deskewed_scans": sum(s.deskewed for s in self.steps),
        }


def registration_config(config: Config) -> RegistrationConfig:
    """RegistrationConfig from the ``[mapping]`` section (channels ``none`` = plain GICP)."""
    m = config.mapping
    if m.channels not in CHANNEL_MODES:
        raise ConfigError(f"unknown channels {m.channels!r}; expected one of {', '.join(CHANNEL_MODES)}")
    return RegistrationConfig(
        method="gicp" if m.channels == "none" else "mcgicp",
        channels=m.channels,
        voxel_size_m=m.voxel_m,
        k_neighbors=m.k,
        max_correspondence_distance_m=m.max_corr_m,
        max_iterations=m.max_iterations,
        robust_kernel=m.robust_kernel,
        workers=1,
    )


def prepare_scan(frame: LidarFrame, config: RegistrationConfig) -> PointSet:
    """Per-frame stage: downsampled points, covariances and descriptors of one scan."""
    needed = {"intensity": ("intensity",), "color": ("r", "g", "b"), "combined": ("intensity", "r", "g", "b")}
    missing = [c for c in needed.get(config.channels, ()) if c not in frame.channels]
    if missing:
        raise InputError(
            f"scan at {frame.stamp_ns} has no {', '.join(missing)} channel for --channels {config.channels}"
        )
    return pointset_from_frame(frame, config)


def ego_motion_registration(config: Config) -> RegistrationConfig:
    """The registration that gives a scan's ego-motion where the log has no odometry: plain GICP with the
    ``[mapping]`` settings."""
    return dataclasses.replace(registration_config(config), method="gicp", channels="none")


def scan_twist(early: PointSet, late: PointSet, config: RegistrationConfig) -> NDArray[np.float64] | None:
    """The lidar's twist (6,: m/s, rad/s, lidar frame) between two prepared scans of one lidar: the later
    registered onto the earlier, over their stamps' interval (``deskew.sweep_twist``); None where the
    registration does not converge."""
    result = register(late, early, config=config)
    twist = sweep_twist(result.T_target_source, (late.stamp_ns - early.stamp_ns) * 1e-9)
    return twist if result.converged and twist is not None else None


def tf_odometry(tree: TransformTree | None, lidar_frame: str) -> Callable[[int], NDArray[np.float64] | None] | None:
    """``T_odom_lidar`` at a stamp (ns) from the log's dynamic tf, or None when the log has no odometry.

    The returned function gives None at a stamp the tf does not cover (a warning is logged once).
    """
    if tree is None or lidar_frame not in tree.frames:
        return None
    world = root_of(tree, lidar_frame)
    if world == lidar_frame or tree.is_static_path(world, lidar_frame):
        return None
    warned = False

    def lookup(stamp_ns: int) -> NDArray[np.float64] | None:
        nonlocal warned
        try:
            return tree.lookup(world, lidar_frame, stamp_ns)
        except TransformError as err:
            if not warned:
                log.warning("no /tf odometry at some scans (constant-velocity guess there): %s", err)
                warned = True
            return None

    return lookup


def prefetched(items: Iterable[T], depth: int = 2) -> Iterator[T]:
    """``items`` produced on a background thread, up to ``depth`` ahead of the consumer.

    Decoding and scan preparation (numba kernels without the GIL, kd-tree builds, NumPy sorts) then
    run on the second core while the consumer registers the previous scan. An exception of the
    producer is raised in the consumer; a consumer that stops early stops the producer.
    """
    buffer: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(entry: tuple[str, Any]) -> bool:
        while not stop.is_set():
            try:
                buffer.put(entry, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put(("item", item)):
                    return
            put(("end", None))
        except BaseException as err:  # handed to the consumer, raised there
            put(("error", err))

    thread = threading.Thread(target=produce, name="fleetcal-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            kind, value = buffer.get()
            if kind == "end":
                return
            if kind == "error":
                raise value
            yield value
    finally:
        stop.set()


def map_pointsets(
    pointsets: Iterable[PointSet],
    config: Config,
    tree: TransformTree | None = None,
) -> tuple[list[OdometryStep], VoxelMap, bool]:
    """Odometry + voxel map over prepared scans in time order, consumed one at a time (memory does not
    grow with the number of scans beyond the trajectory and the map)."""
    stream = iter(pointsets)
    first = next(stream, None)
    reg = registration_config(config)
    voxel_map = VoxelMap(config.mapping.map_voxel_m)
    if first is None:
        return [], voxel_map, False
    odometry = tf_odometry(tree, first.frame_id.lstrip("/")) if config.mapping.use_tf_odometry else None
    steps = run_odometry(itertools.chain([first], stream), reg, initial_motion=odometry, voxel_map=voxel_map,
                         deskew=config.mapping.deskew, first_motion_max_m=config.mapping.first_motion_max_m)
    return steps, voxel_map, odometry is not None


def map_frames(
    frames: Iterable[LidarFrame], config: Config, tree: TransformTree | None = None
) -> tuple[list[OdometryStep], VoxelMap, bool]:
    """``map_pointsets`` over decoded scans, each prepared (``prepare_scan``) on a background thread
    while the previous one is registered."""
    reg = registration_config(config)
    return map_pointsets(prefetched(prepare_scan(frame, reg) for frame in frames), config, tree)


def mapping_workers(config: Config) -> int | None:
    """Engine workers for mapping one recording: in-process (0) unless a scheduler or a worker count is
    configured. The odometry chain is serial and the scan preparation overlaps it on a thread
    (``prefetched``), so a local cluster adds only its start-up (KITTI 00, 51 scans, 2 cores: see
    docs/performance.md)."""
    if config.engine.scheduler is not None or config.engine.workers is not None:
        return config.engine.workers
    return 0


class NotEnoughScansError(InputError):
    """Fewer than two usable scans: nothing to register."""


def run_mapping(
    paths: Sequence[str],
    reader: LogReader,
    lidar_topic: str,
    config: Config,
    engine: Engine,
    stage: Callable[[LidarFrame], PointSet] | None = None,
) -> MappingOutcome:
    """Prepare every scan on the engine (log order) with ``stage`` (default ``prepare_scan``) and chain the
    odometry and the map over the prepared scans as they arrive (in-process: prepared on a background
    thread, ``prefetched``).

    Raises:
        NotEnoughScansError: fewer than two scans survive the stage.
    """
    if stage is None:
        stage = functools.partial(prepare_scan, config=registration_config(config))
    try:
        tree: TransformTree | None = load_tf_tree(reader)
    except InputError as err:
        log.warning("not using /tf odometry: %s", err)
        tree = None
    pointsets: Iterable[PointSet] = engine.map_frames(
        LogFrames(paths, config.io.allow_truncated, config.io.max_range_m), lidar_topic, stage,
        batch_size=config.engine.batch_size, ordered=True, desc="scans",
    )  # fmt: skip
    if engine.in_process:
        pointsets = prefetched(pointsets)
    frame_id: list[str] = []
    steps, voxel_map, used_tf = map_pointsets(_noting_frame(pointsets, frame_id), config, tree)
    if len(steps) < 2:
        reasons = ", ".join(engine.stats.skip_examples[:2])
        raise NotEnoughScansError(f"need at least 2 usable scans on {lidar_topic} to map, got {len(steps)}"
                         + (f" ({reasons})" if reasons else ""))  # fmt: skip
    return MappingOutcome(
        lidar_topic, frame_id[0], config.mapping.channels, steps,
        voxel_map.points(), voxel_map.channels(), engine.stats.frames_skipped, used_tf, config.mapping.max_speed_m_s,
    )  # fmt: skip


def _noting_frame(pointsets: Iterable[PointSet], frame_id: list[str]) -> Iterator[PointSet]:
    """The pointsets, recording the first one's frame id (without a leading slash) in ``frame_id``."""
    for pointset in pointsets:
        if not frame_id:
            frame_id.append(pointset.frame_id.lstrip("/"))
        yield pointset


def trajectory_rows(steps: Sequence[OdometryStep]) -> list[dict[str, Any]]:
    rows = []
    for s in steps:
        t, q = to_quat(s.T_map_lidar)
        rows.append({"stamp_ns": s.stamp_ns, "tx_m": t[0], "ty_m": t[1], "tz_m": t[2], "qx": q[0], "qy": q[1],
                     "qz": q[2], "qw": q[3], "fitness": s.fitness, "rmse_m": s.rmse_m,
                     "iterations": s.iterations})  # fmt: skip
    return rows


def write_mapping(outcome: MappingOutcome, out_dir: Path, with_report: bool = True) -> list[Path]:
    """``trajectory.parquet``, ``map.parquet`` and ``report/map_top.png``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [
        write_rows(trajectory_rows(outcome.steps), TRAJECTORY_SCHEMA, out_dir / "trajectory.parquet"),
        write_table(map_table(outcome.map_points_xyz, outcome.map_channels), out_dir / "map.parquet"),
    ]
    if with_report:
        trajectory = np.array([s.T_map_lidar[:3, 3] for s in outcome.steps])
        written.append(report.write_map_top(outcome.map_points_xyz, out_dir / "report" / "map_top.png",
                                            outcome.map_channels.get("intensity"), trajectory))  # fmt: skip
    return written
