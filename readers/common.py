"""Plumbing the fleetcal readers share (topic table, time span, deserialise, context manager).

``ReaderPlumbing`` gives any reader that fills ``_topics`` the ``topics`` property and the context
manager (``__exit__`` calls ``close``); ``ContainerReader`` adds, for readers over one container
file that fill ``_types``, ``_start_ns`` and ``_end_ns``, the time span and ``deserialize``;
``rosbags_time_span`` gives those two for the readers built on ``rosbags``.
"""

from __future__ import annotations

from typing import Any

from typing_extensions import Self

from fleetcal.readers.base import RawMessage, TopicInfo
from fleetcal.readers.typesys import LogTypes


def rosbags_time_span(reader: Any) -> tuple[int, int]:
    """(start_ns, end_ns) of an open ``rosbags`` Reader (end exclusive, as rosbags); (0, 0) when empty."""
    if reader.message_count > 0:
        return int(reader.start_time), int(reader.end_time)
    return 0, 0


class ReaderPlumbing:
    """``topics`` and the context manager of a ``LogReader`` (subclasses set ``_topics``)."""

    _topics: dict[str, TopicInfo]

    @property
    def topics(self) -> dict[str, TopicInfo]:
        """Topic name -> TopicInfo (a copy)."""
        return dict(self._topics)

    def close(self) -> None:
        """Release what the reader holds open (nothing by default)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ContainerReader(ReaderPlumbing):
    """A reader over one container file: adds the time span and ``deserialize``.

    Subclasses set ``_topics``, ``_types`` (the log's ``LogTypes``), ``_start_ns`` and ``_end_ns``.
    """

    _types: LogTypes
    _start_ns: int
    _end_ns: int

    @property
    def start_ns(self) -> int:
        """Log time (ns) of the first message (0 when there is none)."""
        return self._start_ns

    @property
    def end_ns(self) -> int:
        """One past the log time (ns) of the last message (exclusive bound, as rosbags)."""
        return self._end_ns

    def deserialize(self, raw: RawMessage) -> Any:
        """The rosbags message object of ``raw``. Raises DecodeError."""
        return self._types.deserialize(raw)
