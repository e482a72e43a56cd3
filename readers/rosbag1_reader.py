"""ROS 1 ``.bag`` files, read with ``rosbags.rosbag1.Reader``.

Topic and time filtering is done by rosbags (connections + ``start``/``stop``), which reads only the
chunks that hold the wanted connections in the wanted time range; nothing is deserialised until
``deserialize`` is called. Types come from the definitions stored in the bag's connection headers.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from pathlib import Path

from rosbags.rosbag1 import Reader
from rosbags.rosbag1 import ReaderError as Rosbag1Error

from fleetcal.pipeline.errors import ReaderError
from fleetcal.pipeline.msgtypes import LogFormat
from fleetcal.readers.base import RawMessage
from fleetcal.readers.common import ContainerReader, rosbags_time_span
from fleetcal.readers.typesys import channel_info_from_connection, normalize_msgtype, topics_from_connections

ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"


class Rosbag1LogReader(ContainerReader):
    """A ``LogReader`` over one ROS 1 bag file.

    Raises:
        ReaderError: not a ROS 1 bag (v2.0), unindexed or damaged.
    """

    format: LogFormat = "ros1"
    truncation = None

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.paths = [str(self.path)]
        self._reader = Reader(self.path)
        try:
            self._reader.open()
        except (Rosbag1Error, ValueError, KeyError) as err:  # damaged headers: UnicodeDecodeError, ...
            raise ReaderError(f"cannot read ROS 1 bag {self.path}: {err}") from err
        except OSError as err:
            raise ReaderError(f"cannot read {self.path}: {err.strerror or err}") from err
        self._topics, self._types = topics_from_connections(self._reader.connections, "ros1")
        self._channel_infos = {
            c.id: channel_info_from_connection(c, "ros1") for c in self._reader.connections
        }
        self._start_ns, self._end_ns = rosbags_time_span(self._reader)

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Undecoded messages of ``topics`` with ``start_ns <= log_time_ns < end_ns``, in log-time order."""
        connections = self._reader.connections
        if topics is not None:
            wanted = set(topics)
            connections = [c for c in connections if c.topic in wanted]
            if not connections:
                return
        try:
            for conn, stamp_ns, data in self._reader.messages(connections, start=start_ns, stop=end_ns):
                yield RawMessage(
                    topic=conn.topic,
                    msgtype=normalize_msgtype(conn.msgtype),
                    log_time_ns=stamp_ns,
                    data=data,
                    serialization="ros1",
                    channel=self._channel_infos[conn.id],
                )
        except (Rosbag1Error, ValueError, KeyError) as err:  # damaged headers: UnicodeDecodeError, ...
            raise ReaderError(f"damaged ROS 1 bag {self.path}: {err}") from err

    def close(self) -> None:
        """Close the bag file."""
        if self._reader.bio is not None:
            self._reader.close()
