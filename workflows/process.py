"""Recipe: the nightly job for one log — calibrate every lidar/camera pair, colourise the scans from
the calibrated cameras, map with MC-GICP, write every table, the report, the effective config and
the write-back log. ``result.json`` is written last: its presence means the output folder is complete.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import with_model
from fleetcal.pipeline.config import Config, write_toml
from fleetcal.pipeline.engine import Engine
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import TransformTree, apply
from fleetcal.readers.base import LogReader
from fleetcal.readers.decode import decode_pointcloud2
from fleetcal.readers.frames import CameraInfoTracker, decode_camera_image, load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration.frame import compensate_ego_motion
from fleetcal.stages.colorize import colorize, fill_unseen
from fleetcal.stages.registration.config import RegistrationConfig
from fleetcal.stages.registration.pointset import PointSet
from fleetcal.stages.sinks.atomic import atomic_path
from fleetcal.stages.sinks.report import jpeg_overlay
from fleetcal.workflows import calibrate as calib
from fleetcal.workflows import mapping
from fleetcal.workflows.ego_motion import has_odometry, points_at, twist_motion
from fleetcal.workflows.frame_sources import STAGE_WARMUPS
from fleetcal.workflows.pairing import raw_header_stamp_ns
from fleetcal.workflows.sensors import resolve_cameras, resolve_lidar
from fleetcal.workflows.sinks.writeback import CalibratedPose, write_back, writeback_path

log = logging.getLogger(__name__)

RESULT_FILE = "result.json"
ChannelMode = Literal["none", "intensity", "color", "combined"]


@dataclass
class ProcessResult:
    """What ``process_log`` produced (also stored as ``result.json`` in the output folder)."""

    log_paths: list[str]
    out_dir: Path
    runtime_s: float
    stage_times_s: dict[str, float]
    calibrations: list[dict[str, Any]]
    mapping: dict[str, Any] | None
    writeback_path: Path | None
    log_start_ns: int
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {
            "log_paths": self.log_paths, "out_dir": str(self.out_dir), "runtime_s": self.runtime_s,
            "stage_times_s": self.stage_times_s, "calibrations": self.calibrations, "mapping": self.mapping,
            "writeback_path": str(self.writeback_path) if self.writeback_path else None,
            "log_start_ns": self.log_start_ns, "warnings": self.warnings,
        }  # fmt: skip

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ProcessResult:
        return cls(
            log_paths=list(data["log_paths"]), out_dir=Path(data["out_dir"]), runtime_s=float(data["runtime_s"]),
            stage_times_s=dict(data["stage_times_s"]), calibrations=list(data["calibrations"]),
            mapping=data.get("mapping"), log_start_ns=int(data["log_start_ns"]),
            writeback_path=Path(data["writeback_path"]) if data.get("writeback_path") else None,
            warnings=list(data.get("warnings", [])),
        )  # fmt: skip


def is_complete(out_dir: Path) -> bool:
    """True when ``out_dir`` holds a finished ``process_log`` output (its ``result.json``)."""
    return (Path(out_dir) / RESULT_FILE).is_file()


def load_result(out_dir: Path) -> ProcessResult:
    return ProcessResult.from_json(json.loads((Path(out_dir) / RESULT_FILE).read_text(encoding="utf-8")))


@dataclass(frozen=True)
class ColorSource:
    """Calibrated cameras to colour lidar scans from (read by each worker from the log itself)."""

    paths: tuple[str, ...]
    cameras: tuple[tuple[str, tuple[tuple[float, ...], ...]], ...]
    tolerance_ns: int
    allow_truncated: bool = False
    camera_model: str = "log"
    rectified_topics: tuple[str, ...] = ()
    ego_motion: bool = True
    point_times: bool = True
    lidar_topic: str = ""
    ego_registration: RegistrationConfig | None = None  # GICP for the lidar's twist where /tf has no odometry
    max_range_m: float | None = None


@functools.lru_cache(maxsize=4)
def _worker_reader(paths: tuple[str, ...], allow_truncated: bool) -> Any:
    return open_log(list(paths) if len(paths) > 1 else paths[0], allow_truncated=allow_truncated)


def _nearest_image(reader: Any, topic: str, stamp_ns: int, tolerance_ns: int,
                   rectified_topics: tuple[str, ...] = ()) -> Any:
    """The decoded image of ``topic`` nearest ``stamp_ns`` (header stamps) within the tolerance, or None."""
    margin = tolerance_ns + 200_000_000
    best, best_gap = None, tolerance_ns + 1
    for raw in reader.messages(topics=[topic], start_ns=stamp_ns - margin, end_ns=stamp_ns + margin):
        gap = abs(raw_header_stamp_ns(raw, reader) - stamp_ns)
        if gap < best_gap:
            best, best_gap = raw, gap
    if best is None:
        return None
    frame = decode_camera_image(reader.topics[topic].msgtype, reader.deserialize(best), topic, best.log_time_ns)
    frame.camera = _camera_model(reader, topic, rectified_topics)
    return frame


@functools.lru_cache(maxsize=16)
def _camera_model(reader: Any, topic: str, rectified_topics: tuple[str, ...] = ()) -> Any:
    """The first CameraInfo of ``topic``'s camera, read once per worker and topic."""
    return CameraInfoTracker.for_image(reader, topic, rectified_topics).model


@functools.lru_cache(maxsize=4)
def _worker_tree(paths: tuple[str, ...], allow_truncated: bool) -> TransformTree | None:
    """The log's tf tree, read once per worker (None when the log has no usable tf)."""
    try:
        return load_tf_tree(_worker_reader(paths, allow_truncated))
    except InputError:
        return None


def colorize_scan(frame: LidarFrame, source: ColorSource) -> LidarFrame:
    """Per-frame stage: r, g, b channels from the calibrated cameras; points no camera sees get the
    mean colour of the seen ones (so they add no colour gradient in MC-GICP). With ``source.ego_motion`` each
    image sees the points moved to its own stamp: by the odometry on ``/tf`` (``ego_motion.points_at``), or
    where the log has none by fleetcal's own, the scan registered with its neighbour (``_odometry_twist``)."""
    reader = _worker_reader(source.paths, source.allow_truncated)
    tree = _worker_tree(source.paths, source.allow_truncated) if source.ego_motion else None
    twist = None
    if source.ego_motion and not has_odometry(tree, frame.frame_id.lstrip("/")):
        twist = _odometry_twist(reader, frame, source)
    views, moved = [], []
    for topic, T_rows in source.cameras:
        image = _nearest_image(reader, topic, frame.stamp_ns, source.tolerance_ns, source.rectified_topics)
        camera = None if image is None else with_model(image.camera, source.camera_model)
        if image is not None and camera is not None:
            views.append((image.image, camera, np.array(T_rows)))
            if twist is None:
                moved.append(points_at(tree, frame, image.stamp_ns, source.point_times))
            else:
                offsets, _ = twist_motion(frame, image.stamp_ns, twist, source.point_times)
                moved.append(compensate_ego_motion(frame.points_xyz, None, offsets, twist))
    points = np.asarray(frame.points_xyz, dtype=np.float64)
    if views:
        rgb, seen = colorize(points, views, points_per_view=moved)
    else:
        rgb, seen = np.zeros((points.shape[0], 3), np.uint8), np.zeros(points.shape[0], bool)
    rgb = fill_unseen(rgb, seen).astype(np.float32)
    channels = dict(frame.channels)
    channels.update(r=rgb[:, 0], g=rgb[:, 1], b=rgb[:, 2])
    frame.channels = channels
    return frame


def _odometry_twist(reader: Any, frame: LidarFrame, source: ColorSource) -> NDArray[np.float64] | None:
    """The lidar's twist at ``frame`` from fleetcal's own odometry (``mapping.scan_twist``): the scan registered
    with the next one on its topic (the one before, for the last); None without a neighbour, a registration
    config or a converged registration."""
    if source.ego_registration is None or not source.lidar_topic:
        return None
    neighbour = _neighbour_scan(reader, source.lidar_topic, frame, source.max_range_m)
    if neighbour is None:
        return None
    here = mapping.prepare_scan(frame, source.ego_registration)
    there = mapping.prepare_scan(neighbour, source.ego_registration)
    early, late = (here, there) if here.stamp_ns < there.stamp_ns else (there, here)
    return None if early.stamp_ns == late.stamp_ns else mapping.scan_twist(early, late, source.ego_registration)


def _neighbour_scan(reader: Any, topic: str, frame: LidarFrame, max_range_m: float | None) -> LidarFrame | None:
    """The decoded scan after ``frame`` on ``topic`` by log time (within a second), else the one before."""
    after = reader.messages(topics=[topic], start_ns=frame.log_time_ns + 1, end_ns=frame.log_time_ns + 1_000_000_000)
    raw = next(iter(after), None)
    if raw is None:
        before = list(reader.messages(topics=[topic], start_ns=frame.log_time_ns - 1_000_000_000,
                                      end_ns=frame.log_time_ns))
        raw = before[-1] if before else None
    if raw is None:
        return None
    extra = () if max_range_m is None else (max_range_m,)
    return decode_pointcloud2(reader.deserialize(raw), topic, raw.log_time_ns, *extra)


def prepare_colored_scan(frame: LidarFrame, source: ColorSource | None, config: Any) -> PointSet:
    """Per-frame stage of ``process``: colourise (when cameras are given), then prepare for MC-GICP."""
    if source is not None:
        frame = colorize_scan(frame, source)
    return mapping.prepare_scan(frame, config)


def _mapping_channels(config: Config, have_color: bool, have_intensity: bool) -> ChannelMode:
    wanted = config.mapping.channels
    if wanted in ("color", "combined") and not have_color:
        wanted = "intensity" if have_intensity else "none"
    if wanted in ("intensity", "combined") and not have_intensity:
        wanted = "color" if have_color else "none"
    return wanted


def process_log(
    paths: Sequence[str],
    out_dir: Path,
    config: Config,
    *,
    workers: int | None = 0,
    scheduler: str | None = None,
    quiet: bool = True,
) -> ProcessResult:
    """Calibrate, colourise, map and write back one log into ``out_dir``.

    Raises:
        InputError / ProcessingError: the log cannot be read, has no lidar or camera, or no pair.
    """
    start = time.perf_counter()
    times: dict[str, float] = {}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stale = out_dir / RESULT_FILE
    if stale.exists():
        stale.unlink()
    paths = [str(p) for p in paths]
    warnings: list[str] = []
    reader = open_log(paths if len(paths) > 1 else paths[0], allow_truncated=config.io.allow_truncated)
    with reader:
        lidar_topic = resolve_lidar(reader, None)
        cameras = resolve_cameras(reader, None)
        with Engine(scheduler=scheduler, workers=workers, quiet=quiet, warmups=STAGE_WARMUPS) as engine:
            t0 = time.perf_counter()
            pairs = calib.run_calibration(reader, lidar_topic, cameras, config, quiet=quiet, engine=engine)
            times["calibration"] = time.perf_counter() - t0

            t0 = time.perf_counter()
            outcome = _mapped(paths, reader, lidar_topic, pairs, config, engine, warnings)
            times["mapping"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        write_toml(config, out_dir / "config.toml")
        calib.write_calibration(pairs, config, out_dir)
        if outcome is not None:
            mapping.write_mapping(outcome, out_dir)
        times["tables_report"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        target = writeback_path(paths[0], out_dir)
        _write_back_log(reader, target, pairs, outcome)
        times["writeback"] = time.perf_counter() - t0
        log_start = reader.start_ns
    result = ProcessResult(
        log_paths=paths, out_dir=out_dir, runtime_s=time.perf_counter() - start, stage_times_s=times,
        calibrations=[p.summary() for p in pairs], mapping=outcome.summary() if outcome else None,
        writeback_path=target, log_start_ns=int(log_start), warnings=warnings,
    )  # fmt: skip
    with atomic_path(out_dir / RESULT_FILE) as tmp:
        Path(tmp).write_text(json.dumps(result.to_json(), indent=1, default=float), encoding="utf-8")
    return result


def _mapped(paths: list[str], reader: LogReader, lidar_topic: str, pairs: list[calib.PairCalibration], config: Config,
            engine: Engine, warnings: list[str]) -> mapping.MappingOutcome | None:
    """The log mapped with the scans' intensity where they have one and the images' colour (by the calibrations
    just found) where the settings ask; None where it has too few scans (said in ``warnings``)."""
    source = ColorSource(
        tuple(paths), tuple((p.camera_topic, tuple(map(tuple, p.T_camera_lidar.tolist()))) for p in pairs),
        config.io.pairing_tolerance_ns, config.io.allow_truncated, config.calibration.camera_model,
        tuple(config.io.rectified_topics), config.calibration.motion_compensation,
        config.calibration.point_times, lidar_topic, mapping.ego_motion_registration(config),
        config.io.max_range_m,
    )  # fmt: skip
    first = next(iter(reader.messages(topics=[lidar_topic])), None)
    has_intensity = first is not None and any(f.name == "intensity" for f in reader.deserialize(first).fields)
    map_config = dataclasses.replace(config, mapping=dataclasses.replace(
        config.mapping, channels=_mapping_channels(config, True, has_intensity)))  # fmt: skip
    reg = mapping.registration_config(map_config)
    uses_color = reg.channels in ("color", "combined")
    stage = functools.partial(prepare_colored_scan, source=source if uses_color else None, config=reg)
    try:
        outcome = mapping.run_mapping(paths, reader, lidar_topic, map_config, engine, stage)
    except mapping.NotEnoughScansError as err:
        warnings.append(f"mapping skipped: {err}")
        return None
    warnings.extend(outcome.warnings())
    return outcome


def _write_back_log(reader: LogReader, target: Path, pairs: list[calib.PairCalibration],
                    outcome: mapping.MappingOutcome | None) -> None:
    """The new log beside the input: the calibrations, the map, the trajectory and one overlay per camera."""
    overlays: dict[str, list[tuple[int, bytes]]] = {}
    for p in pairs:
        if p.frames and p.overlay_image is not None:
            f = p.frames[0]
            pts = f.points_at_camera_stamp()
            overlays[p.camera_topic] = [(f.stamp_ns, jpeg_overlay(p.overlay_image, f.camera,
                                                                  apply(p.T_camera_lidar, pts)))]  # fmt: skip
    write_back(
        reader, target,
        calibrations=[CalibratedPose(p.lidar_frame, p.camera_frame, p.T_camera_lidar) for p in pairs],
        map_points_xyz=outcome.map_points_xyz if outcome else None,
        map_channels=outcome.map_channels if outcome else None,
        trajectory_stamps_ns=[s.stamp_ns for s in outcome.steps] if outcome else (),
        trajectory_T_map_lidar=[s.T_map_lidar for s in outcome.steps] if outcome else (),
        overlays=overlays,
    )  # fmt: skip
