"""Pair lidar scans with camera images by sensor time (header stamps).

Each lidar frame is paired with the camera frame whose header stamp is nearest, if within a
tolerance (default 50 ms); lidar frames without one are skipped and counted. Stamps are read from
the first bytes of each raw message (every sensor message starts with a Header), so finding the
pairs decodes nothing; only the paired frames are decoded afterwards.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Collection, Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, DecodeError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.readers.base import LogReader, RawMessage
from fleetcal.readers.decode import decode_pointcloud2, stamp_to_ns
from fleetcal.readers.decode.pointcloud2 import MAX_RANGE_M
from fleetcal.readers.frames import (
    IMAGE_TYPES,
    POINTCLOUD2,
    CameraInfoTracker,
    decode_camera_image,
    require_topic,
)

log = logging.getLogger(__name__)

DEFAULT_TOLERANCE_NS = 50_000_000


@dataclass
class PairingStats:
    """Counts from one ``iter_pairs`` run.

    Attributes:
        lidar_frames, camera_frames: messages on each topic in the time range.
        matched: lidar frames with a camera frame within the tolerance.
        unmatched_lidar: lidar frames skipped for want of one.
        yielded: pairs actually produced (``max_pairs`` may select fewer than ``matched``).
        undecodable: selected frames that could not be decoded (their pairs are skipped).
    """

    lidar_frames: int = 0
    camera_frames: int = 0
    matched: int = 0
    unmatched_lidar: int = 0
    yielded: int = 0
    undecodable: int = 0


def pair_stamps(
    lidar_stamps_ns: Sequence[int] | NDArray[np.int64],
    camera_stamps_ns: Sequence[int] | NDArray[np.int64],
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
) -> list[tuple[int, int]]:
    """(lidar index, camera index) for each lidar stamp with a camera stamp within ``tolerance_ns``.

    The nearest camera stamp wins (the earlier one on a tie); a camera frame may serve several
    lidar frames. Inputs need not be sorted; the result is in lidar index order.
    """
    if tolerance_ns < 0:
        raise ConfigError(f"pairing tolerance must be >= 0 ns, got {tolerance_ns}")
    lidar = np.asarray(lidar_stamps_ns, dtype=np.int64).reshape(-1)
    camera = np.asarray(camera_stamps_ns, dtype=np.int64).reshape(-1)
    if lidar.size == 0 or camera.size == 0:
        return []
    order = np.argsort(camera, kind="stable")
    sorted_camera = camera[order]
    pos = np.searchsorted(sorted_camera, lidar, side="left")
    before = np.clip(pos - 1, 0, camera.size - 1)
    after = np.clip(pos, 0, camera.size - 1)
    gap_before = np.abs(lidar - sorted_camera[before])
    gap_after = np.abs(sorted_camera[after] - lidar)
    nearest = np.where(gap_after < gap_before, after, before)
    gap = np.minimum(gap_before, gap_after)
    return [(int(i), int(order[nearest[i]])) for i in np.flatnonzero(gap <= tolerance_ns)]


def raw_header_stamp_ns(raw: RawMessage, reader: LogReader | None = None) -> int:
    """Header stamp (ns) of a raw message whose type starts with ``std_msgs/Header``, without decoding it.

    CDR: 4-byte encapsulation header (byte 1 odd = little-endian), then int32 sec, uint32 nanosec.
    ROS 1: uint32 seq, uint32 sec, uint32 nsec. Falls back to ``reader.deserialize`` when the
    payload is too short to hold a header.
    """
    data = raw.data
    if len(data) >= 12:
        if raw.serialization == "cdr":
            endian = "<" if data[1] & 1 else ">"
            sec, nanosec = struct.unpack_from(endian + "iI", data, 4)
        else:
            sec, nanosec = struct.unpack_from("<II", data, 4)
        return int(sec) * 1_000_000_000 + int(nanosec)
    if reader is None:
        raise ValueError("message too short for a header and no reader to decode it")
    return stamp_to_ns(reader.deserialize(raw).header.stamp)


def _select(pairs: list[tuple[int, int]], max_pairs: int | None) -> list[tuple[int, int]]:
    """``max_pairs`` pairs spread evenly over the log (all when None or enough)."""
    if max_pairs is None or len(pairs) <= max_pairs:
        return pairs
    if max_pairs <= 0:
        return []
    picks = np.unique(np.linspace(0, len(pairs) - 1, max_pairs).round().astype(np.int64))
    return [pairs[int(i)] for i in picks]


@dataclass(frozen=True)
class ChosenPair:
    """One lidar/camera pair chosen by header stamps, nothing decoded: each message's header stamp and log
    time, ns, and its index among its topic's messages; and the lidar scan next to it in the log (the one
    before, or after for the first scan; -1 without one), whose motion to it gives the lidar's velocity; and
    likewise the image next to the camera's (whose motion to it gives the camera's)."""

    lidar_index: int
    camera_index: int
    lidar_stamp_ns: int
    camera_stamp_ns: int
    lidar_log_ns: int
    camera_log_ns: int
    neighbour_stamp_ns: int = -1
    neighbour_log_ns: int = -1
    camera_neighbour_stamp_ns: int = -1
    camera_neighbour_log_ns: int = -1


def choose_pairs(
    reader: LogReader,
    lidar_topic: str,
    camera_topic: str,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
    max_pairs: int | None = None,
    *,
    start_ns: int | None = None,
    end_ns: int | None = None,
    stats: PairingStats | None = None,
) -> list[ChosenPair]:
    """The pairs ``iter_pairs`` decodes, from one pass over the raw messages' header stamps: nearest stamps
    within ``tolerance_ns``, ``max_pairs`` spread evenly over the log, in log order.

    Raises:
        InputError: a topic is missing or of the wrong type.
    """
    require_topic(reader, lidar_topic, (POINTCLOUD2,))
    require_topic(reader, camera_topic, IMAGE_TYPES)
    stats = stats if stats is not None else PairingStats()
    stamps: dict[str, list[int]] = {lidar_topic: [], camera_topic: []}
    log_times: dict[str, list[int]] = {lidar_topic: [], camera_topic: []}
    for raw in reader.messages(topics=[lidar_topic, camera_topic], start_ns=start_ns, end_ns=end_ns):
        stamps[raw.topic].append(raw_header_stamp_ns(raw, reader))
        log_times[raw.topic].append(raw.log_time_ns)
    matched = pair_stamps(stamps[lidar_topic], stamps[camera_topic], tolerance_ns)
    stats.lidar_frames, stats.camera_frames = len(stamps[lidar_topic]), len(stamps[camera_topic])
    stats.matched = len(matched)
    stats.unmatched_lidar = stats.lidar_frames - stats.matched
    if stats.unmatched_lidar:
        log.info(
            "%d of %d lidar frames on %s have no %s frame within %.0f ms",
            stats.unmatched_lidar, stats.lidar_frames, lidar_topic, camera_topic, tolerance_ns / 1e6,
        )  # fmt: skip
    lidar_stamps, lidar_times = stamps[lidar_topic], log_times[lidar_topic]
    camera_stamps, camera_times = stamps[camera_topic], log_times[camera_topic]
    chosen = []
    for li, ci in _select(matched, max_pairs):
        nb, cn = _neighbour(li, len(lidar_stamps)), _neighbour(ci, len(camera_stamps))
        chosen.append(ChosenPair(li, ci, lidar_stamps[li], camera_stamps[ci], lidar_times[li], camera_times[ci],
                                 lidar_stamps[nb] if nb >= 0 else -1, lidar_times[nb] if nb >= 0 else -1,
                                 camera_stamps[cn] if cn >= 0 else -1, camera_times[cn] if cn >= 0 else -1))
    return chosen


def _neighbour(index: int, count: int) -> int:
    """The message before ``index`` among ``count``, or after it for the first; -1 for a lone message."""
    return index - 1 if index > 0 else (index + 1 if count > 1 else -1)


def iter_pairs(
    reader: LogReader,
    lidar_topic: str,
    camera_topic: str,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
    max_pairs: int | None = None,
    *,
    start_ns: int | None = None,
    end_ns: int | None = None,
    stats: PairingStats | None = None,
    rectified_topics: Collection[str] = (),
    max_range_m: float = MAX_RANGE_M,
) -> Iterator[tuple[LidarFrame, CameraFrame]]:
    """(LidarFrame, CameraFrame with its CameraModel) pairs, nearest header stamps within ``tolerance_ns``.

    Two passes over the raw messages: stamps first (no decoding), then only the paired frames are
    decoded, and each is dropped once its pairs are out, so memory holds a few frames. Pairs come
    in log order. ``max_pairs`` keeps that many pairs spread evenly over the log. Unmatched lidar
    frames are skipped, counted in ``stats`` and logged. The camera model is a rectified one when the
    camera topic is named so or is in ``rectified_topics`` (``CameraInfoTracker.for_image``).

    Raises:
        InputError: a topic is missing or of the wrong type.
    """
    camera_type = require_topic(reader, camera_topic, IMAGE_TYPES)
    stats = stats if stats is not None else PairingStats()
    chosen = choose_pairs(reader, lidar_topic, camera_topic, tolerance_ns, max_pairs, start_ns=start_ns,
                          end_ns=end_ns, stats=stats)
    pairs = [(pair.lidar_index, pair.camera_index) for pair in chosen]
    if not pairs:
        return
    yield from _decode_pairs(reader, lidar_topic, camera_topic, camera_type, pairs, stats, start_ns, end_ns,
                             rectified_topics, max_range_m)


def _decode_pairs(
    reader: LogReader,
    lidar_topic: str,
    camera_topic: str,
    camera_type: str,
    pairs: list[tuple[int, int]],
    stats: PairingStats,
    start_ns: int | None,
    end_ns: int | None,
    rectified_topics: Collection[str] = (),
    max_range_m: float = MAX_RANGE_M,
) -> Iterator[tuple[LidarFrame, CameraFrame]]:
    """The ``pairs`` (lidar index, camera index on their topics) decoded in one pass, each yielded as soon as
    both its frames are; a frame that does not decode drops its pairs (an error only where none decodes)."""
    waiting = _PairsWaiting(pairs)
    info = CameraInfoTracker.for_image(reader, camera_topic, rectified_topics)
    topics = [lidar_topic, camera_topic] + ([info.topic] if info.topic else [])
    seen = {lidar_topic: -1, camera_topic: -1}
    first_error: DecodeError | None = None
    for raw in reader.messages(topics=topics, start_ns=start_ns, end_ns=end_ns):
        if raw.topic == info.topic:
            info.update(reader, raw)
            continue
        seen[raw.topic] += 1
        index = seen[raw.topic]
        is_lidar = raw.topic == lidar_topic
        if not waiting.wants(is_lidar, index):
            continue
        try:
            msg = reader.deserialize(raw)
            if is_lidar:
                waiting.lidar_frames[index] = decode_pointcloud2(msg, lidar_topic, raw.log_time_ns, max_range_m)
            else:
                frame = decode_camera_image(camera_type, msg, camera_topic, raw.log_time_ns)
                frame.camera = info.model
                waiting.camera_frames[index] = frame
        except DecodeError as err:
            # One bad frame must not end the run: skip its pairs; fail only when nothing decodes.
            stats.undecodable += 1
            first_error = first_error or err
            log.warning("skipping an undecodable frame on %s at log time %d: %s", raw.topic, raw.log_time_ns, err)
            waiting.drop(is_lidar, index)
        else:
            for pair in waiting.ready():
                stats.yielded += 1
                yield pair
        if not waiting.pending:
            break
    if stats.yielded == 0 and first_error is not None:
        raise first_error


class _PairsWaiting:
    """The pairs not yet yielded and the decoded frames they still need (a frame is let go with its last pair)."""

    def __init__(self, pairs: list[tuple[int, int]]) -> None:
        self.pending = sorted(pairs)
        self.lidar_uses: dict[int, int] = {}
        self.camera_uses: dict[int, int] = {}
        for li, ci in pairs:
            self.lidar_uses[li] = self.lidar_uses.get(li, 0) + 1
            self.camera_uses[ci] = self.camera_uses.get(ci, 0) + 1
        self.lidar_frames: dict[int, LidarFrame] = {}
        self.camera_frames: dict[int, CameraFrame] = {}

    def wants(self, is_lidar: bool, index: int) -> bool:
        """Whether a pending pair needs the ``index``-th lidar (or camera) message."""
        return (self.lidar_uses if is_lidar else self.camera_uses).get(index, 0) > 0

    def _release(self, li: int, ci: int) -> None:
        self.pending.remove((li, ci))
        self.lidar_uses[li] -= 1
        self.camera_uses[ci] -= 1
        if not self.lidar_uses[li]:
            self.lidar_frames.pop(li, None)
        if not self.camera_uses[ci]:
            self.camera_frames.pop(ci, None)

    def drop(self, is_lidar: bool, index: int) -> None:
        """Give up the pairs of the ``index``-th lidar (or camera) message, which did not decode."""
        for li, ci in [pair for pair in self.pending if (pair[0] if is_lidar else pair[1]) == index]:
            self._release(li, ci)

    def ready(self) -> Iterator[tuple[LidarFrame, CameraFrame]]:
        """The pending pairs whose two frames are decoded, in order; each released once yielded."""
        for li, ci in [(li, ci) for li, ci in self.pending if li in self.lidar_frames and ci in self.camera_frames]:
            yield self.lidar_frames[li], self.camera_frames[ci]
            self._release(li, ci)
