"""The scripting API: the four things the command line does, as typed functions.

Each takes log paths and optional ``"section.key": value`` overrides of the configuration (the keys
of ``config.toml``); each returns the same objects the commands write to their output folders.
Errors are raised as ``fleetcal.pipeline.errors.FleetcalError`` subclasses.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from fleetcal.pipeline.config import Config, load_config
from fleetcal.pipeline.engine import Engine
from fleetcal.readers.open import open_log
from fleetcal.workflows.calibrate import PairCalibration, calibration_engine, run_calibration
from fleetcal.workflows.frame_sources import STAGE_WARMUPS
from fleetcal.workflows.mapping import MappingOutcome, run_mapping
from fleetcal.workflows.process import ProcessResult
from fleetcal.workflows.process import process_log as _process_log
from fleetcal.workflows.sensors import resolve_cameras, resolve_lidar

PathLike = str | os.PathLike[str]

__all__ = ["calibrate", "map_log", "open_log", "process_log"]


def _config(settings: Mapping[str, Any] | None) -> Config:
    return load_config(overrides=dict(settings or {}))


def _paths(logs: PathLike | Sequence[PathLike]) -> list[str]:
    if isinstance(logs, (str, os.PathLike)):
        return [os.fspath(logs)]
    return [os.fspath(p) for p in logs]


def calibrate(
    logs: PathLike | Sequence[PathLike],
    *,
    lidar: str | None = None,
    cameras: Sequence[str] | None = None,
    initial: str | None = None,
    joint: bool = False,
    settings: Mapping[str, Any] | None = None,
) -> list[PairCalibration]:
    """Calibrate ``T_camera_lidar`` for every camera; one ``PairCalibration`` per lidar/camera pair.

    Topics left out are detected as ``fleetcal inspect`` does; ``initial`` is ``"x y z roll pitch yaw"``
    (metres, degrees) and overrides the log's tf, or ``"auto"``: a start found from the rig's motion or a
    search, as for a log without a lidar-camera tf.
    """
    paths = _paths(logs)
    config = _config(settings)
    with open_log(paths if len(paths) > 1 else paths[0], allow_truncated=config.io.allow_truncated) as reader:
        lidar_topic = resolve_lidar(reader, lidar)
        camera_topics = resolve_cameras(reader, list(cameras) if cameras else None)
        with calibration_engine(config) as engine:
            return run_calibration(reader, lidar_topic, camera_topics, config, initial, joint, quiet=True,
                                   engine=engine)


def map_log(
    logs: PathLike | Sequence[PathLike],
    *,
    lidar: str | None = None,
    settings: Mapping[str, Any] | None = None,
    workers: int | None = 0,
) -> MappingOutcome:
    """Register every scan of the lidar (GICP or MC-GICP odometry, ``mapping.channels``) and build the voxel map
    (map = first scan's frame).

    ``workers``: 0 runs in-process, None one local dask worker per core.
    """
    paths = _paths(logs)
    config = _config(settings)
    with open_log(paths if len(paths) > 1 else paths[0], allow_truncated=config.io.allow_truncated) as reader:
        lidar_topic = resolve_lidar(reader, lidar)
        with Engine(scheduler=config.engine.scheduler, workers=workers, quiet=True, warmups=STAGE_WARMUPS) as engine:
            return run_mapping(paths, reader, lidar_topic, config, engine)


def process_log(
    logs: PathLike | Sequence[PathLike],
    out_dir: PathLike,
    *,
    settings: Mapping[str, Any] | None = None,
    workers: int | None = 0,
) -> ProcessResult:
    """Calibrate, colourise, map and write everything back (``<log stem>.fleetcal.mcap``) into ``out_dir``."""
    return _process_log(_paths(logs), Path(out_dir), _config(settings), workers=workers)
