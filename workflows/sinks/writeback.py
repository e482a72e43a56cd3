"""Write-back: ``<log stem>.fleetcal.mcap``, the input log unchanged plus fleetcal's results.

Every message of the input is copied with its original bytes, log time and publish time (where
the input stores one, else the log time), on a channel with the input's topic, message encoding and
metadata, and a schema with the input's name, encoding and definition text. A ROS 1 bag becomes a
ros1-profile MCAP (``ros1msg``/``ros1``), a ROS 2 bag a ros2-profile MCAP (``ros2msg``/``cdr``), an
MCAP keeps its own profile. New topics are serialised in the output's profile:

- ``/tf_static`` (``tf2_msgs/msg/TFMessage``): one message at the log's start time holding
  ``T_lidar_camera`` (parent = lidar frame, child = camera frame) of each calibrated camera. When the
  input has a ``/tf_static`` channel of that type and encoding, the message goes on that channel.
- ``/fleetcal/map`` (``sensor_msgs/msg/PointCloud2``, frame ``map``; x, y, z, intensity float32 and
  PCL-packed ``rgb``): one message at the log's end time (the last message's log time).
- ``/fleetcal/trajectory`` (``nav_msgs/msg/Path``, frame ``map``): one message at the end time.
- ``/fleetcal/overlay/<camera topic>`` (``sensor_msgs/msg/CompressedImage``, jpeg): one message per
  overlay at its stamp, in the camera's frame.

The input is streamed (one message in memory at a time) and only read; new messages are merged in
by log time (``heapq.merge``; originals first on equal times). The output is written under a
temporary name and renamed on success (``stages.sinks.atomic.atomic_path``).
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from numpy.typing import NDArray
from rosbags.typesys.msg import denormalize_msgtype

from fleetcal.pipeline.errors import DecodeError, InputError
from fleetcal.pipeline.msgtypes import COMPRESSED_IMAGE, PATH, POINTCLOUD2, TF_MESSAGE
from fleetcal.pipeline.transforms import invert, is_rigid
from fleetcal.readers.base import ChannelInfo, LogReader, RawMessage
from fleetcal.readers.typesys import normalize_msgtype
from fleetcal.stages.sinks.atomic import atomic_path
from fleetcal.workflows.sinks import ros_messages
from fleetcal.workflows.sinks.ros_messages import Profile, get_store

TF_STATIC_TOPIC = "/tf_static"
MAP_TOPIC = "/fleetcal/map"
TRAJECTORY_TOPIC = "/fleetcal/trajectory"
OVERLAY_PREFIX = "/fleetcal/overlay/"
MAP_FRAME = "map"

_SERIALIZATION: dict[Profile, str] = {"ros1": "ros1", "ros2": "cdr"}


@dataclass(frozen=True)
class CalibratedPose:
    """A calibrated camera: ``p_camera = T_camera_lidar @ p_lidar`` (4x4, metres, optical frame)."""

    lidar_frame: str
    camera_frame: str
    T_camera_lidar: NDArray[np.float64]


@dataclass
class WriteBackStats:
    """What ``write_back`` wrote.

    Attributes:
        out_path: the written MCAP file.
        profile: the output's MCAP profile (``ros1`` or ``ros2``; an MCAP input's own).
        original_messages: messages copied from the input.
        new_messages: new topic -> messages written on it.
        channels: channels in the output.
        bytes_written: size of the output file.
    """

    out_path: Path
    profile: str
    original_messages: int = 0
    new_messages: dict[str, int] = field(default_factory=dict)
    channels: int = 0
    bytes_written: int = 0


@dataclass(frozen=True)
class _Record:
    log_time_ns: int
    publish_time_ns: int
    channel: ChannelInfo
    data: bytes | memoryview


def writeback_path(log_path: str | os.PathLike[str], out_dir: str | os.PathLike[str] | None = None) -> Path:
    """``<out_dir>/<log stem>.fleetcal.mcap`` (``out_dir`` defaults to the log's folder).

    The stem of a ROS 2 bag folder (or its ``metadata.yaml``) is the folder's name.
    """
    path = Path(log_path)
    if path.name == "metadata.yaml":
        path = path.parent
    stem = path.name if path.is_dir() else path.stem
    folder = Path(out_dir) if out_dir is not None else path.parent
    return folder / f"{stem}.fleetcal.mcap"


def _input_profile(reader: LogReader) -> str:
    """The MCAP profile of the output: ros1 bag -> ros1, ros2 bag -> ros2, MCAP -> its own."""
    if reader.format == "ros1":
        return "ros1"
    if reader.format == "ros2":
        return "ros2"
    inner = getattr(reader, "readers", [reader])
    profiles = {getattr(r, "profile", "") for r in inner} - {""}
    if len(profiles) == 1:
        return str(profiles.pop())
    serializations = {info.serialization for info in reader.topics.values()}
    return "ros1" if serializations == {"ros1"} else "ros2"


def _message_profile(output_profile: str) -> Profile:
    return "ros1" if output_profile == "ros1" else "ros2"


def _fallback_channel(reader: LogReader, raw: RawMessage) -> ChannelInfo:
    """A ChannelInfo for a message whose reader did not attach one (from the topic table)."""
    info = reader.topics.get(raw.topic)
    msgdef = info.msgdef if info is not None else ""
    if raw.serialization == "ros1":
        name, encoding = denormalize_msgtype(raw.msgtype), "ros1msg"
    else:
        name, encoding = raw.msgtype, "ros2msg"
    return ChannelInfo(
        topic=raw.topic,
        message_encoding=raw.serialization,
        schema_name=name,
        schema_encoding=encoding if msgdef.strip() else "",
        schema_data=msgdef.encode(),
    )


def _new_channel(topic: str, msgtype: str, profile: Profile) -> ChannelInfo:
    """Channel and schema of a new topic, from the profile's standard typestore."""
    store = get_store(profile)
    if profile == "ros1":
        text, md5sum = store.generate_msgdef(msgtype, ros_version=1)
        metadata: tuple[tuple[str, str], ...] = (("md5sum", md5sum),)
        if topic == TF_STATIC_TOPIC:
            metadata = (("latching", "true"), ("md5sum", md5sum))
        return ChannelInfo(topic, "ros1", denormalize_msgtype(msgtype), "ros1msg", text.encode(), metadata)
    text = store.generate_msgdef(msgtype, ros_version=2)[0]
    return ChannelInfo(topic, "cdr", msgtype, "ros2msg", text.encode())


def _serialize(msg: Any, msgtype: str, profile: Profile) -> bytes:
    store = get_store(profile)
    try:
        if profile == "ros1":
            return bytes(store.serialize_ros1(msg, msgtype))
        return bytes(store.serialize_cdr(msg, msgtype))
    except Exception as err:
        raise InputError(f"cannot serialise the new {msgtype} message ({profile}): {err}") from err


def _first_channel(reader: LogReader, topic: str) -> tuple[RawMessage | None, ChannelInfo | None]:
    """The first message of ``topic`` in the input and its channel (None, None when absent)."""
    if topic not in reader.topics:
        return None, None
    for raw in reader.messages(topics=[topic]):
        return raw, raw.channel if raw.channel is not None else _fallback_channel(reader, raw)
    return None, None


def _frame_of(reader: LogReader, topic: str) -> str:
    """``header.frame_id`` of the first message of ``topic`` ("" when absent or undecodable)."""
    raw, _ = _first_channel(reader, topic)
    if raw is None:
        return ""
    try:
        msg = reader.deserialize(raw)
    except DecodeError:
        return ""
    header = getattr(msg, "header", None)
    return str(getattr(header, "frame_id", ""))


_RIGID_TOL = 1e-5
"""Allowed deviation of a pose's rotation from orthonormal (a quaternion carries rotations only)."""


def _check_T(T: Any, what: str) -> NDArray[np.float64]:
    matrix = np.asarray(T, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise InputError(f"{what} must be a finite 4x4 transform, got shape {matrix.shape}")
    if not is_rigid(matrix, tol=_RIGID_TOL):
        raise InputError(f"{what} is not a rigid transform (rotation not orthonormal to {_RIGID_TOL})")
    return matrix


def _new_records(
    reader: LogReader,
    profile: Profile,
    calibrations: Sequence[CalibratedPose],
    map_points_xyz: NDArray[np.floating] | None,
    map_channels: Mapping[str, NDArray[Any]],
    trajectory_stamps_ns: Sequence[int],
    trajectory_T_map_lidar: Sequence[NDArray[np.float64]],
    overlays: Mapping[str, Sequence[tuple[int, bytes]]],
) -> list[_Record]:
    """The new messages, serialised in ``profile``, sorted by log time."""
    start_ns = reader.start_ns
    end_ns = max(start_ns, reader.end_ns - 1)
    if len(trajectory_stamps_ns) != len(trajectory_T_map_lidar):
        raise InputError(
            f"trajectory has {len(trajectory_stamps_ns)} stamps but {len(trajectory_T_map_lidar)} poses"
        )
    records: list[_Record] = []
    if calibrations:
        records.append(_record(start_ns, _tf_static_channel(reader, profile), TF_MESSAGE,
                               _calibration_message(calibrations, start_ns, profile), profile))
    if map_points_xyz is not None:
        records.append(_record(end_ns, _new_channel(MAP_TOPIC, POINTCLOUD2, profile), POINTCLOUD2,
                               _map_message(map_points_xyz, map_channels, end_ns, profile), profile))
    if len(trajectory_stamps_ns):
        poses = [_check_T(T, "a trajectory pose") for T in trajectory_T_map_lidar]
        msg = ros_messages.path(end_ns, MAP_FRAME, [int(s) for s in trajectory_stamps_ns], poses, profile)
        records.append(_record(end_ns, _new_channel(TRAJECTORY_TOPIC, PATH, profile), PATH, msg, profile))
    records += _overlay_records(reader, overlays, profile)
    records.sort(key=lambda record: record.log_time_ns)
    return records


def _record(log_time_ns: int, channel: ChannelInfo, msgtype: str, msg: Any, profile: Profile) -> _Record:
    """``msg`` serialised in ``profile`` on ``channel``, published at its log time."""
    return _Record(int(log_time_ns), int(log_time_ns), channel, _serialize(msg, msgtype, profile))


def _tf_static_channel(reader: LogReader, profile: Profile) -> ChannelInfo:
    """The log's own ``/tf_static`` channel where it has one of the same schema and encoding, else a new one."""
    _, tf_channel = _first_channel(reader, TF_STATIC_TOPIC)
    same_schema = (
        tf_channel is not None
        and normalize_msgtype(tf_channel.schema_name) == TF_MESSAGE
        and tf_channel.message_encoding == _SERIALIZATION[profile]
    )
    return tf_channel if tf_channel is not None and same_schema else _new_channel(TF_STATIC_TOPIC, TF_MESSAGE, profile)


def _calibration_message(calibrations: Sequence[CalibratedPose], stamp_ns: int, profile: Profile) -> Any:
    """A TFMessage of every calibration as ``T_lidar_camera`` (lidar frame -> camera frame)."""
    transforms = [
        (
            stamp_ns,
            cal.lidar_frame.lstrip("/"),
            cal.camera_frame.lstrip("/"),
            invert(_check_T(cal.T_camera_lidar, f"T_camera_lidar of {cal.camera_frame}")),
        )
        for cal in calibrations
    ]
    return ros_messages.tf_message(transforms, profile)


def _map_message(map_points_xyz: NDArray[np.floating], map_channels: Mapping[str, NDArray[Any]], stamp_ns: int,
                 profile: Profile) -> Any:
    """The map as a PointCloud2 in the ``map`` frame: x, y, z float32 and the channels given (intensity float32,
    r, g, b uint8, all three or none)."""
    points = np.asarray(map_points_xyz)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"map points must be (N, 3), got shape {points.shape}")
    unknown = sorted(set(map_channels) - {"intensity", "r", "g", "b"})
    if unknown:
        raise InputError(f"unknown map channels {unknown} (expected intensity, r, g, b)")
    channels: dict[str, NDArray[Any]] = {}
    if "intensity" in map_channels:
        channels["intensity"] = np.asarray(map_channels["intensity"], dtype=np.float32)
    colour = [name for name in ("r", "g", "b") if name in map_channels]
    if colour and len(colour) != 3:
        raise InputError(f"map colour needs all of r, g, b, got {colour}")
    for name in colour:
        channels[name] = np.asarray(map_channels[name], dtype=np.uint8)
    for name, values in channels.items():
        if values.shape != (points.shape[0],):
            raise InputError(f"map channel {name} has shape {values.shape}, expected ({points.shape[0]},)")
    return ros_messages.pointcloud2(stamp_ns, MAP_FRAME, points.astype(np.float32, copy=False), channels,
                                    profile=profile)


def _overlay_records(reader: LogReader, overlays: Mapping[str, Sequence[tuple[int, bytes]]],
                     profile: Profile) -> list[_Record]:
    """Each camera's overlay JPEGs on ``/fleetcal/overlay/<camera topic>``, in the camera's frame."""
    CompressedImage = get_store(profile).types[COMPRESSED_IMAGE]
    records: list[_Record] = []
    for camera_topic, images in overlays.items():
        if not images:
            continue
        channel = _new_channel(OVERLAY_PREFIX + camera_topic.lstrip("/"), COMPRESSED_IMAGE, profile)
        frame_id = _frame_of(reader, camera_topic)
        for stamp_ns, jpeg in images:
            msg = CompressedImage(
                header=ros_messages.header(int(stamp_ns), frame_id, profile),
                format="jpeg",
                data=np.frombuffer(jpeg, dtype=np.uint8).copy(),
            )
            records.append(_record(stamp_ns, channel, COMPRESSED_IMAGE, msg, profile))
    return records


def _original_records(reader: LogReader, stats: WriteBackStats) -> Iterator[_Record]:
    for raw in reader.messages():
        stats.original_messages += 1
        channel = raw.channel if raw.channel is not None else _fallback_channel(reader, raw)
        publish = raw.publish_time_ns if raw.publish_time_ns is not None else raw.log_time_ns
        yield _Record(raw.log_time_ns, publish, channel, raw.data)


def _input_paths(reader: LogReader) -> list[Path]:
    return [Path(p).resolve() for p in reader.paths]


class _McapOut:
    """An MCAP writer that registers each distinct schema and channel once."""

    def __init__(self, writer: McapWriter) -> None:
        self.writer = writer
        self.schemas: dict[tuple[str, str, bytes], int] = {}
        self.channels: dict[ChannelInfo, int] = {}

    def channel_id(self, channel: ChannelInfo) -> int:
        channel_id = self.channels.get(channel)
        if channel_id is not None:
            return channel_id
        schema_id = 0
        if channel.schema_name:
            key = (channel.schema_name, channel.schema_encoding, channel.schema_data)
            schema_id = self.schemas.get(key, 0)
            if not schema_id:
                schema_id = self.writer.register_schema(
                    name=channel.schema_name, encoding=channel.schema_encoding, data=channel.schema_data
                )
                self.schemas[key] = schema_id
        channel_id = self.writer.register_channel(
            topic=channel.topic,
            message_encoding=channel.message_encoding,
            schema_id=schema_id,
            metadata=dict(channel.metadata),
        )
        self.channels[channel] = channel_id
        return channel_id


def write_back(
    reader: LogReader,
    out_path: str | os.PathLike[str],
    *,
    calibrations: Sequence[CalibratedPose] = (),
    map_points_xyz: NDArray[np.floating] | None = None,
    map_channels: Mapping[str, NDArray[Any]] | None = None,
    trajectory_stamps_ns: Sequence[int] = (),
    trajectory_T_map_lidar: Sequence[NDArray[np.float64]] = (),
    overlays: Mapping[str, Sequence[tuple[int, bytes]]] | None = None,
    chunk_size: int = 4 * 1024 * 1024,
) -> WriteBackStats:
    """Write ``out_path`` (MCAP): every message of ``reader``'s log unchanged, plus the new topics.

    Args:
        reader: the input log (only read; streamed once, plus one peek per overlay topic and
            ``/tf_static``).
        out_path: the output ``.mcap`` file (see ``writeback_path``); must not be an input file.
        calibrations: calibrated cameras, written as ``T_lidar_camera`` on ``/tf_static``.
        map_points_xyz: (N, 3) map points in metres, frame ``map``; None writes no map.
        map_channels: per-point ``intensity`` (float) and ``r``, ``g``, ``b`` (uint8), optional.
        trajectory_stamps_ns: stamps of the lidar poses (ns); empty writes no trajectory.
        trajectory_T_map_lidar: one 4x4 ``T_map_lidar`` per stamp.
        overlays: camera topic -> (stamp_ns, JPEG bytes) per overlay image.
        chunk_size: MCAP chunk size in bytes (zstd-compressed chunks).

    Raises:
        InputError: bad arguments, or ``out_path`` is (inside) an input.
        ReaderError: the input cannot be read; nothing is left at ``out_path`` then.
    """
    out = Path(out_path)
    resolved = out.resolve()
    for path in _input_paths(reader):
        if resolved == path or path in resolved.parents:
            raise InputError(f"write-back output {out} would overwrite its input {path}")
    output_profile = _input_profile(reader)
    profile = _message_profile(output_profile)
    new = _new_records(
        reader,
        profile,
        calibrations,
        map_points_xyz,
        map_channels or {},
        trajectory_stamps_ns,
        trajectory_T_map_lidar,
        overlays or {},
    )
    stats = WriteBackStats(out_path=out, profile=output_profile)
    for record in new:
        stats.new_messages[record.channel.topic] = stats.new_messages.get(record.channel.topic, 0) + 1
    with atomic_path(out) as temp, temp.open("wb") as stream:
        writer = McapWriter(stream, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        writer.start(profile=output_profile, library="fleetcal write-back")
        mcap_out = _McapOut(writer)
        merged = heapq.merge(_original_records(reader, stats), new, key=lambda record: record.log_time_ns)
        for record in merged:
            writer.add_message(
                channel_id=mcap_out.channel_id(record.channel),
                log_time=record.log_time_ns,
                publish_time=record.publish_time_ns,
                data=bytes(record.data),
            )
        writer.finish()
        stats.channels = len(mcap_out.channels)
    stats.bytes_written = out.stat().st_size
    return stats
