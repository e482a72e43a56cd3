"""MCAP files (ros2 profile with cdr, ros1 profile with ros1 serialisation).

An intact file is read through its summary with ``mcap.reader.SeekingReader``: topic counts and
time span come from the statistics record, and ``messages`` reads only the chunks whose index
matches the requested topics and time range. A file without a usable summary (no footer, cut short,
written without chunk indexes) is read with ``mcap.stream_reader.StreamReader``: every intact record
up to the first damaged one is used and the rest is reported in ``McapLogReader.truncation``
(``TruncationInfo``: recovered messages and lost bytes). With ``allow_truncated=False`` the
constructor raises ``TruncatedLogError`` carrying the same counts.
"""

from __future__ import annotations

import functools
import os
import struct
from collections.abc import Generator, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader, Summary
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import MAGIC_SIZE, StreamReader, breakup_chunk

from fleetcal.pipeline.errors import ReaderError, TruncatedLogError
from fleetcal.pipeline.msgtypes import LogFormat
from fleetcal.readers.base import ChannelInfo, RawMessage, Serialization, TopicInfo
from fleetcal.readers.common import ContainerReader
from fleetcal.readers.typesys import DefinitionEncoding, LogTypes, TypeDefinition, build_log_types, normalize_msgtype

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_PREFIX = 9
_DEFINITION_ENCODINGS: dict[str, DefinitionEncoding] = {
    "ros2msg": "ros2msg",
    "ros2idl": "ros2idl",
    "ros1msg": "ros1msg",
}
_MESSAGE_ENCODINGS: dict[str, Serialization] = {"cdr": "cdr", "ros1": "ros1"}
_PARSE_ERRORS = (McapError, zstandard.ZstdError, struct.error, ValueError, UnicodeDecodeError, StopIteration)


@dataclass(frozen=True)
class TruncationInfo:
    """What a damaged log still gave.

    Attributes:
        recovered_messages: messages read from intact records.
        lost_bytes: bytes from the first damaged record to the end of the file.
        reason: one line on what is missing (e.g. no footer, record cut short).
    """

    recovered_messages: int
    lost_bytes: int
    reason: str

    def message(self, path: str) -> str:
        """One-line description for a warning or error."""
        return (
            f"{path} is truncated ({self.reason}): recovered {self.recovered_messages} messages, "
            f"lost {self.lost_bytes} bytes"
        )


class _IndexedReader(SeekingReader):
    """A ``SeekingReader`` given the file's summary, already read: reading messages does not parse it again
    (a large log's chunk index takes tens of milliseconds, and a calibration reads hundreds of message sets)."""

    def __init__(self, stream: IO[bytes], summary: Summary) -> None:
        super().__init__(stream, validate_crcs=True)
        self._known = summary

    def get_summary(self) -> Summary:
        return self._known


@functools.lru_cache(maxsize=8)
def _summary_of(path: str, size: int, mtime_ns: int) -> Summary | None:
    """The summary section of the MCAP file at ``path`` (None: it has none), read once per process for a file
    of that size and modification time (every frame source of a log opens it again)."""
    with open(path, "rb") as stream:
        return SeekingReader(stream).get_summary()


@dataclass
class _ScanResult:
    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    counts: dict[int, int]
    start_ns: int | None
    end_ns: int | None
    truncation: TruncationInfo | None


class McapLogReader(ContainerReader):
    """A ``LogReader`` over one MCAP file.

    Args:
        path: the ``.mcap`` file.
        allow_truncated: when False, a damaged file raises ``TruncatedLogError`` (with
            ``recovered_messages`` and ``lost_bytes``); when True it opens with what is intact and
            ``truncation`` says what was lost.

    Raises:
        ReaderError: not an MCAP file, or unreadable.
        TruncatedLogError: the file is damaged and ``allow_truncated`` is False.
    """

    format: LogFormat = "mcap"

    def __init__(self, path: str | os.PathLike[str], allow_truncated: bool = False) -> None:
        self.path = Path(path)
        self.paths = [str(self.path)]
        self.truncation: TruncationInfo | None = None
        try:
            self._size = self.path.stat().st_size
            with self.path.open("rb") as stream:
                if stream.read(MAGIC_SIZE) != MCAP_MAGIC:
                    raise ReaderError(f"not an MCAP file (bad magic bytes): {self.path}")
                stream.seek(0)
                self.profile = self._read_header(stream)
                self._summary: Summary | None = None  # set where the summary is usable
                scan = self._read_summary(stream)
                if scan is None:
                    scan = self._scan(stream)
        except OSError as err:
            raise ReaderError(f"cannot read {self.path}: {err.strerror or err}") from err
        except McapError as err:
            raise ReaderError(f"cannot read MCAP file {self.path}: {err}") from err
        self._schemas = scan.schemas
        self._channels = scan.channels
        self._start_ns = scan.start_ns if scan.start_ns is not None else 0
        self._end_ns = scan.end_ns + 1 if scan.end_ns is not None else self._start_ns
        self.truncation = scan.truncation
        if self.truncation is not None and not allow_truncated:
            raise TruncatedLogError(
                self.truncation.message(str(self.path)),
                recovered_messages=self.truncation.recovered_messages,
                lost_bytes=self.truncation.lost_bytes,
            )
        self._topics, self._types = self._build_topics(scan.counts)
        self._channel_infos: dict[int, ChannelInfo] = {}
        self._raw_fields: dict[int, tuple[str, Serialization, ChannelInfo]] = {}

    def _read_header(self, stream: IO[bytes]) -> str:
        """The profile named in the Header record; ReaderError when the first record is no header."""
        try:
            return SeekingReader(stream).get_header().profile
        except _PARSE_ERRORS as err:
            raise ReaderError(f"not a valid MCAP file (no readable header record): {self.path}") from err

    def _read_summary(self, stream: IO[bytes]) -> _ScanResult | None:
        """Topic table from the summary section; None when it is missing, damaged or incomplete."""
        if self._size < 2 * MAGIC_SIZE:
            return None
        stream.seek(-MAGIC_SIZE, os.SEEK_END)
        if stream.read(MAGIC_SIZE) != MCAP_MAGIC:
            return None
        try:
            stat = self.path.stat()
            summary = _summary_of(str(self.path.resolve()), stat.st_size, stat.st_mtime_ns)
        except (McapError, struct.error, ValueError, UnicodeDecodeError):
            return None
        if summary is None or summary.statistics is None or not summary.chunk_indexes:
            return None
        self._summary = summary
        stats = summary.statistics
        has_messages = stats.message_count > 0
        return _ScanResult(
            schemas=dict(summary.schemas),
            channels=dict(summary.channels),
            counts=dict(stats.channel_message_counts),
            start_ns=stats.message_start_time if has_messages else None,
            end_ns=stats.message_end_time if has_messages else None,
            truncation=None,
        )

    def _scan(self, stream: IO[bytes]) -> _ScanResult:
        """Read every intact record once (no deserialisation) to build the topic table."""
        result = _ScanResult({}, {}, {}, None, None, None)
        records = _stream_records(stream, self._size)
        while True:
            try:
                record = next(records)
            except StopIteration as stop:
                result.truncation = stop.value
                if result.truncation is not None:
                    result.truncation = TruncationInfo(
                        recovered_messages=sum(result.counts.values()),
                        lost_bytes=result.truncation.lost_bytes,
                        reason=result.truncation.reason,
                    )
                return result
            if isinstance(record, Schema):
                result.schemas[record.id] = record
            elif isinstance(record, Channel):
                result.channels[record.id] = record
            elif isinstance(record, Message):
                result.counts[record.channel_id] = result.counts.get(record.channel_id, 0) + 1
                stamp = record.log_time
                result.start_ns = stamp if result.start_ns is None else min(result.start_ns, stamp)
                result.end_ns = stamp if result.end_ns is None else max(result.end_ns, stamp)

    def _build_topics(self, counts: dict[int, int]) -> tuple[dict[str, TopicInfo], LogTypes]:
        definitions: list[TypeDefinition] = []
        serializations: list[Serialization] = []
        for channel in self._channels.values():
            schema = self._schemas.get(channel.schema_id)
            if schema is None:
                continue
            encoding = _DEFINITION_ENCODINGS.get(schema.encoding, "")
            definitions.append(TypeDefinition(schema.name, encoding, schema.data.decode("utf-8", "replace")))
            if channel.message_encoding in _MESSAGE_ENCODINGS:
                serializations.append(_MESSAGE_ENCODINGS[channel.message_encoding])
        dominant: Serialization = (
            "ros1" if self.profile == "ros1" or (serializations and all(s == "ros1" for s in serializations))
            else "cdr"
        )
        types = build_log_types(definitions, dominant)

        topics: dict[str, TopicInfo] = {}
        for channel in sorted(self._channels.values(), key=lambda c: c.id):
            schema = self._schemas.get(channel.schema_id)
            msgtype = normalize_msgtype(schema.name) if schema is not None else ""
            serialization = _MESSAGE_ENCODINGS.get(channel.message_encoding)
            decodable = bool(msgtype) and serialization is not None and types.is_decodable(msgtype)
            if not msgtype:
                types.undecodable.setdefault("", "the channel has no schema")
            count = counts.get(channel.id, 0)
            previous = topics.get(channel.topic)
            if previous is not None:
                count += previous.count
                decodable = decodable and previous.decodable
            topics[channel.topic] = TopicInfo(
                name=channel.topic,
                msgtype=msgtype,
                count=count,
                serialization=serialization or "cdr",
                decodable=decodable,
                msgdef=schema.data.decode("utf-8", "replace") if schema is not None else "",
            )
        return topics, types

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RawMessage]:
        """Undecoded messages of ``topics`` with ``start_ns <= log_time_ns < end_ns``.

        With a summary, only chunks whose index matches are decompressed and messages come in
        log-time order; without one (damaged file) they come in file order, chunks outside the time
        range are skipped by their header.
        """
        wanted = None if topics is None else sorted(set(topics))
        if self._summary is not None:
            yield from self._messages_indexed(self._summary, wanted, start_ns, end_ns)
        else:
            yield from self._messages_streamed(wanted, start_ns, end_ns)

    def channel_info(self, channel: Channel) -> ChannelInfo:
        """How ``channel`` and its schema are stored (cached per channel id)."""
        cached = self._channel_infos.get(channel.id)
        if cached is None:
            schema = self._schemas.get(channel.schema_id)
            cached = ChannelInfo(
                topic=channel.topic,
                message_encoding=channel.message_encoding,
                schema_name=schema.name if schema is not None else "",
                schema_encoding=schema.encoding if schema is not None else "",
                schema_data=bytes(schema.data) if schema is not None else b"",
                metadata=tuple(sorted(channel.metadata.items())),
            )
            self._channel_infos[channel.id] = cached
        return cached

    def _raw(self, channel: Channel, message: Message) -> RawMessage:
        fields = self._raw_fields.get(channel.id)
        if fields is None:  # once per channel: type, serialisation and ChannelInfo
            info = self._topics[channel.topic]
            serialization = _MESSAGE_ENCODINGS.get(channel.message_encoding, info.serialization)
            fields = self._raw_fields[channel.id] = (info.msgtype, serialization, self.channel_info(channel))
        msgtype, serialization, channel_info = fields
        return RawMessage(
            topic=channel.topic,
            msgtype=msgtype,
            log_time_ns=message.log_time,
            data=message.data,
            serialization=serialization,
            publish_time_ns=message.publish_time,
            channel=channel_info,
        )

    def _messages_indexed(
        self, summary: Summary, topics: list[str] | None, start_ns: int | None, end_ns: int | None
    ) -> Iterator[RawMessage]:
        try:
            with self.path.open("rb") as stream:
                reader = _IndexedReader(stream, summary)
                for _, channel, message in reader.iter_messages(
                    topics=topics, starting_at=start_ns, ending_before=end_ns, log_time_order=True
                ):
                    yield self._raw(channel, message)
        except OSError as err:
            raise ReaderError(f"cannot read {self.path}: {err.strerror or err}") from err
        except (McapError, zstandard.ZstdError, struct.error, ValueError) as err:
            raise ReaderError(f"damaged MCAP file {self.path}: {err}") from err

    def _messages_streamed(
        self, topics: list[str] | None, start_ns: int | None, end_ns: int | None
    ) -> Iterator[RawMessage]:
        wanted_ids = {cid for cid, ch in self._channels.items() if topics is None or ch.topic in topics}

        def chunk_wanted(chunk: Chunk) -> bool:
            if start_ns is not None and chunk.message_end_time < start_ns:
                return False
            return not (end_ns is not None and chunk.message_start_time >= end_ns)

        try:
            with self.path.open("rb") as stream:
                for record in _stream_records(stream, self._size, chunk_wanted):
                    if not isinstance(record, Message) or record.channel_id not in wanted_ids:
                        continue
                    if start_ns is not None and record.log_time < start_ns:
                        continue
                    if end_ns is not None and record.log_time >= end_ns:
                        continue
                    yield self._raw(self._channels[record.channel_id], record)
        except OSError as err:
            raise ReaderError(f"cannot read {self.path}: {err.strerror or err}") from err


def _stream_records(
    stream: IO[bytes],
    size: int,
    chunk_wanted: Any = None,
) -> Generator[Schema | Channel | Message, None, TruncationInfo | None]:
    """Schema, Channel and Message records of an MCAP stream, chunks expanded, in file order.

    Stops at the footer, or before the first record that is cut short or does not parse; then
    returns (as the generator's value) a ``TruncationInfo`` with ``recovered_messages=0`` (the
    caller counts) and the bytes lost, or None when the file is complete. ``chunk_wanted(chunk)``
    may return False to skip decompressing a chunk.
    """
    fd = stream.fileno()
    stream.seek(MAGIC_SIZE)
    records = StreamReader(stream, skip_magic=True, emit_chunks=True, validate_crcs=True).records
    while True:
        offset = stream.tell()
        if offset >= size:
            return TruncationInfo(0, 0, "no footer: the file ends after its last record")
        prefix = os.pread(fd, _RECORD_PREFIX, offset)
        if len(prefix) < _RECORD_PREFIX:
            return TruncationInfo(0, size - offset, "record header cut short")
        _, length = struct.unpack("<BQ", prefix)
        if offset + _RECORD_PREFIX + length > size:
            return TruncationInfo(0, size - offset, "record cut short")
        try:
            record = next(records)
            if isinstance(record, Footer):
                return None
            if isinstance(record, Chunk):
                if chunk_wanted is not None and not chunk_wanted(record):
                    continue
                inner = breakup_chunk(record, validate_crc=True)
            else:
                inner = [record]
        except _PARSE_ERRORS as err:
            return TruncationInfo(0, size - offset, f"damaged record at byte {offset}: {err}")
        for item in inner:
            if isinstance(item, (Schema, Channel, Message)):
                yield item
