"""Frame sources for ``pipeline.engine.Engine``: logs opened and decoded by ``readers``, and the warm-up of the
stages' numba kernels that the engine runs once per worker.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.engine import SkipFn
from fleetcal.pipeline.errors import DecodeError, InputError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.pipeline.msgtypes import CAMERA_TYPES, LIDAR_TYPES
from fleetcal.readers.decode import decode_pointcloud2
from fleetcal.readers.frames import CameraInfoTracker, decode_camera_image
from fleetcal.readers.open import open_log

__all__ = ["STAGE_WARMUPS", "LogFrames", "warm_up_kernels"]

PathsArg = str | os.PathLike[str] | Sequence[str | os.PathLike[str]]


def _normalise_paths(log_paths: PathsArg) -> tuple[str, ...]:
    if isinstance(log_paths, (str, os.PathLike)):
        return (os.fspath(log_paths),)
    paths = tuple(os.fspath(p) for p in log_paths)
    if not paths:
        raise InputError("no log given")
    return paths


@dataclass(frozen=True, init=False)
class LogFrames:
    """The frames of one recording: a log file, a ROS 2 bag folder or the files of one recording.

    Lidar topics (PointCloud2) give ``LidarFrame``; camera topics (Image, CompressedImage) give
    ``CameraFrame`` with the latest CameraInfo of the topic (``readers.frames.CameraInfoTracker``: seeded
    with the log's first CameraInfo, updated by those inside the requested range). Holds only paths, so a
    task that carries it stays small; each worker opens the log itself.

    Attributes:
        paths: the log's files (as given to ``readers.open.open_log``).
        allow_truncated: open damaged logs with what is intact.
        max_range_m: lidar points farther than this are dropped at decode, metres (None: the decoder's default).
    """

    paths: tuple[str, ...]
    allow_truncated: bool
    max_range_m: float | None

    def __init__(self, log_paths: PathsArg, allow_truncated: bool = False, max_range_m: float | None = None) -> None:
        object.__setattr__(self, "paths", _normalise_paths(log_paths))
        object.__setattr__(self, "allow_truncated", allow_truncated)
        object.__setattr__(self, "max_range_m", max_range_m)

    def log_times(self, topic: str, start_ns: int | None, end_ns: int | None) -> NDArray[np.int64]:
        """Log times, ns, of the topic's messages in ``[start_ns, end_ns)``; nothing is decoded.

        Raises:
            InputError: unknown topic, a type the engine cannot decode; reader errors.
        """
        with open_log(list(self.paths), allow_truncated=self.allow_truncated) as reader:
            _check_topic(reader.topics, topic)
            return np.fromiter((raw.log_time_ns for raw in reader.messages([topic], start_ns, end_ns)), dtype=np.int64)

    def frames(self, topic: str, start_ns: int, end_ns: int, skip: SkipFn) -> Iterator[LidarFrame | CameraFrame]:
        """Decoded frames of the topic with ``start_ns <= log time < end_ns``; a message that cannot be
        decoded is reported to ``skip`` and not yielded."""
        with open_log(list(self.paths), allow_truncated=self.allow_truncated) as reader:
            msgtype = _check_topic(reader.topics, topic)
            info: CameraInfoTracker | None = None
            wanted = [topic]
            if msgtype in CAMERA_TYPES:
                info = CameraInfoTracker.for_image(reader, topic)
                if info.topic is not None:
                    wanted.append(info.topic)
            for raw in reader.messages(wanted, start_ns, end_ns):
                if info is not None and raw.topic == info.topic:
                    info.update(reader, raw)
                    continue
                frame: LidarFrame | CameraFrame
                try:
                    msg = reader.deserialize(raw)
                    if info is None:
                        frame = decode_pointcloud2(msg, topic, raw.log_time_ns,
                                                   *(() if self.max_range_m is None else (self.max_range_m,)))
                    else:
                        frame = decode_camera_image(msgtype, msg, topic, raw.log_time_ns)
                        frame.camera = info.model
                except DecodeError as err:
                    skip(f"decode {type(err).__name__}", f"{topic} @ log time {raw.log_time_ns}: {err}")
                    continue
                yield frame


def _check_topic(topics: Mapping[str, Any], topic: str) -> str:
    if topic not in topics:
        raise InputError(f"topic {topic!r} is not in the log (topics: {', '.join(sorted(topics)) or 'none'})")
    msgtype = str(topics[topic].msgtype)
    if msgtype not in LIDAR_TYPES | CAMERA_TYPES:
        raise InputError(
            f"topic {topic!r} has type {msgtype}; the engine runs stages on PointCloud2, Image and "
            "CompressedImage topics"
        )
    return msgtype


def warm_up_kernels() -> None:
    """Compile (or load from numba's cache) the per-frame stage kernels in this process."""
    from fleetcal.stages import image_kernels, lidar_feature_kernels

    image_kernels.warm_up()
    lidar_feature_kernels.warm_up()


STAGE_WARMUPS: tuple[Callable[[], None], ...] = (warm_up_kernels,)
"""Warm-ups for ``Engine(warmups=...)`` when the engine runs fleetcal's per-frame stages."""
