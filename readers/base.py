"""The contract every container reader satisfies.

Reading bytes and decoding them are separate steps: ``LogReader.messages`` yields ``RawMessage``
records (undecoded payload) filtered by topic and time, and ``LogReader.deserialize`` turns one
into a ROS message object (rosbags dataclass) only when asked. ``readers.decode`` turns those
objects into frames.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Literal, Protocol

from fleetcal.pipeline.msgtypes import LogFormat

Serialization = Literal["cdr", "ros1"]


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a log.

    Attributes:
        name: topic name.
        msgtype: ROS 2 style type name, e.g. ``sensor_msgs/msg/PointCloud2``.
        count: number of messages.
        serialization: ``cdr`` or ``ros1``.
        decodable: False when the log carries no definition for the type (e.g. vendor packets).
        msgdef: the message definition text as stored in the log (may be empty).
    """

    name: str
    msgtype: str
    count: int
    serialization: Serialization
    decodable: bool = True
    msgdef: str = ""


@dataclass(frozen=True)
class ChannelInfo:
    """How a channel is stored in its log, for byte-exact copies (``workflows.sinks.writeback``).

    One object per channel (MCAP channel, ROS bag connection), shared by its messages.

    Attributes:
        topic: topic name.
        message_encoding: ``cdr`` or ``ros1`` (for MCAP: the channel's own value).
        schema_name: type name as the log spells it (``sensor_msgs/PointCloud2`` in ROS 1 logs).
        schema_encoding: ``ros2msg``, ``ros2idl``, ``ros1msg`` (MCAP: its own value), or ``""``
            when the log carries no definition.
        schema_data: the definition bytes as stored (empty when none).
        metadata: channel metadata as sorted (key, value) pairs: MCAP channel metadata; ROS 1
            ``md5sum``/``callerid``/``latching``; ROS 2 ``offered_qos_profiles`` (rosbag2 YAML).
    """

    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes
    metadata: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True, slots=True)
class RawMessage:
    """One undecoded message: its topic, type, receive time (ns) and payload bytes.

    ``publish_time_ns`` is set where the container stores one (MCAP), else None; ``channel`` says
    how the message's channel is stored (set by every fleetcal reader; None for hand-made ones).
    Slotted: one is built per message, and slots make that about a third cheaper.
    """

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes | memoryview
    serialization: Serialization
    publish_time_ns: int | None = None
    channel: ChannelInfo | None = None


class LogReader(Protocol):
    """A readable log (one recording, possibly several files, merged in time order)."""

    paths: list[str]
    format: LogFormat

    @property
    def topics(self) -> dict[str, TopicInfo]: ...

    @property
    def start_ns(self) -> int: ...

    @property
    def end_ns(self) -> int: ...

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Raw messages of ``topics`` with ``start_ns <= log_time_ns < end_ns``, in log-time order."""
        ...

    def deserialize(self, raw: RawMessage) -> Any:
        """The ROS message object of ``raw`` (rosbags dataclass). Raises DecodeError."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> LogReader: ...

    def __exit__(self, *exc: object) -> None: ...
