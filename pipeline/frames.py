"""Typed frames that every reader yields and every stage consumes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel


@dataclass
class LidarFrame:
    """One lidar scan.

    Attributes:
        stamp_ns: sensor time (message header stamp), ns.
        topic: the log topic it came from.
        frame_id: lidar frame the points are expressed in.
        points_xyz: (N, 3) float32 or float64, metres, lidar frame. Invalid returns already dropped.
        channels: per-point arrays of length N, e.g. ``intensity`` (float32), ``ring`` (uint16),
            ``time`` (float64, s relative to the scan), ``r``, ``g``, ``b`` (uint8).
        organized_shape: (height, width) when the cloud was organised, else None.
        organized_index: (N,) flat index of each kept point in the organised grid, or None.
        dropped_points: how many invalid (NaN / all-zero) points were removed.
        log_time_ns: receive time in the log, ns.
    """

    stamp_ns: int
    topic: str
    frame_id: str
    points_xyz: NDArray[np.floating]
    channels: dict[str, NDArray[np.generic]] = field(default_factory=dict)
    organized_shape: tuple[int, int] | None = None
    organized_index: NDArray[np.int64] | None = None
    dropped_points: int = 0
    log_time_ns: int = 0

    @property
    def n_points(self) -> int:
        return int(self.points_xyz.shape[0])

    def channel(self, name: str) -> NDArray[np.generic] | None:
        return self.channels.get(name)


@dataclass
class CameraFrame:
    """One camera image.

    Attributes:
        stamp_ns: sensor time (message header stamp), ns.
        topic: the image topic.
        frame_id: camera optical frame.
        image: (H, W) uint8/uint16 grey or (H, W, 3) uint8 in RGB order.
        encoding: encoding of ``image`` after decoding (``mono8``, ``mono16`` or ``rgb8``).
        camera: intrinsics from the paired CameraInfo, or None when not known yet.
        log_time_ns: receive time in the log, ns.
    """

    stamp_ns: int
    topic: str
    frame_id: str
    image: NDArray[np.generic]
    encoding: str
    camera: CameraModel | None = None
    log_time_ns: int = 0

    @property
    def width(self) -> int:
        return int(self.image.shape[1])

    @property
    def height(self) -> int:
        return int(self.image.shape[0])
