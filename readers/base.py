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

LogFormat = Literal["mcap", "ros1", "ros2"]
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
class RawMessage:
    """One undecoded message: its topic, type, receive time (ns) and payload bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes | memoryview
    serialization: Serialization


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
