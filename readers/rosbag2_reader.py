"""ROS 2 bags (a folder with ``metadata.yaml``; sqlite3 or mcap storage), read with
``rosbags.rosbag2.Reader``.

Topic and time filtering is done by rosbags (connections + ``start``/``stop``, i.e. SQL ``WHERE`` or
the MCAP chunk index); nothing is deserialised until ``deserialize`` is called. Types come from the
definitions stored in the bag; bags written before definitions were stored fall back to the standard
ROS 2 types, and types neither defines (vendor packets) are listed as undecodable.
"""

from __future__ import annotations

import heapq
import os
import sqlite3
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import apsw
import zstandard
from rosbags.interfaces import ConnectionExtRosbag2
from rosbags.rosbag2 import Reader
from rosbags.rosbag2 import ReaderError as Rosbag2Error

from fleetcal.pipeline.errors import ReaderError
from fleetcal.pipeline.msgtypes import LogFormat
from fleetcal.readers.base import RawMessage, Serialization
from fleetcal.readers.common import ContainerReader, rosbags_time_span
from fleetcal.readers.typesys import channel_info_from_connection, normalize_msgtype, topics_from_connections


class Rosbag2LogReader(ContainerReader):
    """A ``LogReader`` over one ROS 2 bag (folder, its ``metadata.yaml``, or a lone ``.db3``).

    Raises:
        ReaderError: not a ROS 2 bag, or unreadable.
    """

    format: LogFormat = "ros2"
    truncation = None

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        if self.path.name == "metadata.yaml":
            self.path = self.path.parent
        self.paths = [str(self.path)]
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise ReaderError(f"not a ROS 2 bag folder (no metadata.yaml): {self.path}")
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except (Rosbag2Error, sqlite3.Error, apsw.Error, KeyError, ValueError) as err:
            reason = " ".join(str(err).split("\n", 1)[0].split())  # one line (YAML errors span several)
            raise ReaderError(f"cannot read ROS 2 bag {self.path}: {reason}") from err
        except OSError as err:
            raise ReaderError(f"cannot read ROS 2 bag {self.path}: {err.strerror or err}") from err
        exts = [c.ext for c in self._reader.connections]
        formats = {ext.serialization_format for ext in exts if isinstance(ext, ConnectionExtRosbag2)}
        unsupported = formats - {"cdr"}
        if unsupported:
            raise ReaderError(f"unsupported serialization {sorted(unsupported)} in ROS 2 bag {self.path}")
        self._serialization: Serialization = "cdr"
        self._topics, self._types = topics_from_connections(self._reader.connections, "cdr")
        self._channel_infos = {
            (c.topic, c.msgtype): channel_info_from_connection(c, "cdr") for c in self._reader.connections
        }
        self._start_ns, self._end_ns = rosbags_time_span(self._reader)

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Undecoded messages of ``topics`` with ``start_ns <= log_time_ns < end_ns``, in log-time order."""
        wanted = None if topics is None else set(topics)
        decompress = self._reader.compression_mode == "message"
        streams = []
        for storage in self._storages():
            conns = [c for c in storage.connections if wanted is None or c.topic in wanted]
            if conns:
                streams.append(storage.messages(conns, start_ns, end_ns))
        try:
            for conn, stamp_ns, data in heapq.merge(*streams, key=lambda item: item[1]):
                yield RawMessage(
                    topic=conn.topic,
                    msgtype=normalize_msgtype(conn.msgtype),
                    log_time_ns=stamp_ns,
                    data=zstandard.decompress(data) if decompress else data,
                    serialization=self._serialization,
                    channel=self._channel_infos.get((conn.topic, conn.msgtype)),
                )
        except (Rosbag2Error, sqlite3.Error, apsw.Error, zstandard.ZstdError) as err:  # rosbags reads .db3 via apsw
            raise ReaderError(f"damaged ROS 2 bag {self.path}: {err}") from err

    def _storages(self) -> list[Any]:
        """The per-file storage readers of the bag.

        ``rosbags.rosbag2.Reader.messages`` matches the metadata's connections to each file's by
        QoS as well, and older bags (metadata version 4, e.g. rosbag2's own test fixtures) store
        QoS differently in the two places, so it yields nothing. Reading each storage file with its
        own connections (filtered by topic) avoids that.
        """
        storage = self._reader.storage
        return list(getattr(storage, "storages", [storage]))

    def close(self) -> None:
        """Close the bag's storage files."""
        if self._reader.is_open:
            self._reader.close()
