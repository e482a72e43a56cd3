"""Several files of one recording, merged into one log-time ordered stream.

``MergedLogReader`` wraps one reader per file (all of one container format) and merges their
``messages`` iterators with ``heapq.merge`` on ``log_time_ns``; ties keep the order of the files.
Each file's iterator is streamed, so memory stays at one message per file.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

from fleetcal.pipeline.errors import DecodeError, ReaderError
from fleetcal.pipeline.msgtypes import LogFormat
from fleetcal.readers.base import LogReader, RawMessage, TopicInfo
from fleetcal.readers.common import ReaderPlumbing
from fleetcal.readers.mcap_reader import TruncationInfo


class MergedLogReader(ReaderPlumbing):
    """A ``LogReader`` over several files of one recording.

    Args:
        readers: one open reader per file, all of the same ``format``. The merged reader owns them
            (``close`` closes them).

    Raises:
        ReaderError: no readers, or readers of different formats.
    """

    def __init__(self, readers: Sequence[LogReader]) -> None:
        if not readers:
            raise ReaderError("no log files to merge")
        formats = sorted({r.format for r in readers})
        if len(formats) > 1:
            paths = ", ".join(p for r in readers for p in r.paths)
            raise ReaderError(f"cannot merge logs of different formats ({', '.join(formats)}): {paths}")
        self.readers = list(readers)
        self.format: LogFormat = self.readers[0].format
        self.paths = [p for r in self.readers for p in r.paths]
        self._topics: dict[str, TopicInfo] = {}
        self._topic_reader: dict[str, LogReader] = {}
        for reader in self.readers:
            for name, info in reader.topics.items():
                self._topic_reader.setdefault(name, reader)
                previous = self._topics.get(name)
                if previous is None:
                    self._topics[name] = info
                    continue
                self._topics[name] = TopicInfo(
                    name=name,
                    msgtype=previous.msgtype or info.msgtype,
                    count=previous.count + info.count,
                    serialization=previous.serialization,
                    decodable=previous.decodable and info.decodable,
                    msgdef=previous.msgdef or info.msgdef,
                )
                if not previous.decodable and info.decodable:
                    self._topic_reader[name] = reader

    @property
    def start_ns(self) -> int:
        """Earliest log time (ns) over the files that hold messages."""
        starts = [r.start_ns for r in self.readers if r.end_ns > r.start_ns]
        return min(starts) if starts else 0

    @property
    def end_ns(self) -> int:
        """One past the latest log time (ns) over the files."""
        ends = [r.end_ns for r in self.readers if r.end_ns > r.start_ns]
        return max(ends) if ends else 0

    @property
    def truncation(self) -> TruncationInfo | None:
        """Damage summed over the files, or None when every file is intact."""
        damaged = [t for t in (getattr(r, "truncation", None) for r in self.readers) if t is not None]
        if not damaged:
            return None
        return TruncationInfo(
            recovered_messages=sum(t.recovered_messages for t in damaged),
            lost_bytes=sum(t.lost_bytes for t in damaged),
            reason="; ".join(t.reason for t in damaged),
        )

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Undecoded messages of every file, merged in log-time order (see ``LogReader.messages``)."""
        wanted = None if topics is None else list(topics)
        streams = [r.messages(wanted, start_ns, end_ns) for r in self.readers]
        yield from heapq.merge(*streams, key=lambda raw: raw.log_time_ns)

    def deserialize(self, raw: RawMessage) -> Any:
        """Deserialise with the types of the file that holds ``raw.topic``. Raises DecodeError."""
        reader = self._topic_reader.get(raw.topic)
        if reader is None:
            raise DecodeError(f"topic {raw.topic} is not in {', '.join(self.paths)}")
        return reader.deserialize(raw)

    def close(self) -> None:
        """Close every file."""
        for reader in self.readers:
            reader.close()
