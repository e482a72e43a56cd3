"""``open_log``: detect a log's container and open it with the matching reader.

Detection looks at the content, not only the name: MCAP and ROS 1 bags by their magic bytes, ROS 2
bags by their folder's ``metadata.yaml`` (the folder, the yaml file or a lone ``.db3`` may be
given). Anything else raises ``ReaderError`` with a one-line reason (missing path, empty file, an
image, unknown bytes). Several paths are files of one recording and are merged in log-time order.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from fleetcal.pipeline.errors import InputError, ReaderError
from fleetcal.pipeline.msgtypes import LogFormat
from fleetcal.readers.base import LogReader
from fleetcal.readers.mcap_reader import MCAP_MAGIC, McapLogReader, TruncationInfo
from fleetcal.readers.merged import MergedLogReader
from fleetcal.readers.rosbag1_reader import ROSBAG1_MAGIC, Rosbag1LogReader
from fleetcal.readers.rosbag2_reader import Rosbag2LogReader

PathArg = str | os.PathLike[str]

_SQLITE_MAGIC = b"SQLite format 3\x00"
_NOT_LOGS: dict[bytes, str] = {
    b"\x89PNG\r\n\x1a\n": "a PNG image",
    b"\xff\xd8\xff": "a JPEG image",
    b"PK\x03\x04": "a zip archive",
    b"\x1f\x8b": "a gzip archive",
    b"%PDF": "a PDF document",
}
_EXPECTED = "expected an MCAP file, a ROS 1 .bag, or a ROS 2 bag folder"


def detect_format(path: PathArg) -> LogFormat:
    """The container format of ``path``: ``mcap``, ``ros1`` or ``ros2``.

    Raises:
        InputError: the path does not exist or cannot be read.
        ReaderError: the path exists but is not a log fleetcal reads (the message says what it is).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"no such file or directory: {path}")
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "ros2"
        raise ReaderError(f"not a ROS 2 bag folder (no metadata.yaml): {path}")
    if path.name == "metadata.yaml":
        return "ros2"
    try:
        with path.open("rb") as stream:
            head = stream.read(16)
    except OSError as err:
        raise InputError(f"cannot read {path}: {err.strerror or err}") from err
    if not head:
        raise ReaderError(f"empty file: {path}")
    if head.startswith(MCAP_MAGIC):
        return "mcap"
    if head.startswith(ROSBAG1_MAGIC):
        return "ros1"
    if head.startswith(b"#ROSBAG V"):
        version = head.split(b"\n", 1)[0].decode("ascii", "replace")
        raise ReaderError(f"unsupported ROS bag version ({version!r}; only V2.0 is read): {path}")
    if head.startswith(_SQLITE_MAGIC):
        if path.suffix == ".db3":
            return "ros2"
        raise ReaderError(f"an SQLite file that is not a ROS 2 .db3 bag: {path}")
    for magic, what in _NOT_LOGS.items():
        if head.startswith(magic):
            raise ReaderError(f"not a log: {path} is {what} ({_EXPECTED})")
    if path.suffix in (".mcap", ".bag", ".db3"):
        raise ReaderError(f"not a valid {path.suffix} file (unrecognised content): {path}")
    raise ReaderError(f"unknown log format ({_EXPECTED}): {path}")


def _open_one(path: Path, allow_truncated: bool) -> LogReader:
    fmt = detect_format(path)
    if fmt == "mcap":
        return McapLogReader(path, allow_truncated=allow_truncated)
    if fmt == "ros1":
        return Rosbag1LogReader(path)
    return Rosbag2LogReader(path)


def open_log(paths: PathArg | Sequence[PathArg], allow_truncated: bool = False) -> LogReader:
    """Open one log, or several files of one recording merged in log-time order.

    Args:
        paths: an MCAP file, a ROS 1 ``.bag``, a ROS 2 bag folder (or its ``metadata.yaml``), or a
            list of those (same format).
        allow_truncated: open damaged MCAP files with what is intact instead of raising;
            ``truncation_of(reader)`` then says how many messages were recovered and bytes lost.

    Raises:
        InputError: a path is missing or unreadable.
        ReaderError: a path is not a readable log, or formats differ.
        TruncatedLogError: a file is damaged and ``allow_truncated`` is False.
    """
    path_list = [Path(paths)] if isinstance(paths, (str, os.PathLike)) else [Path(p) for p in paths]
    if not path_list:
        raise InputError("no log given")
    readers: list[LogReader] = []
    try:
        for path in path_list:
            readers.append(_open_one(path, allow_truncated))
    except BaseException:
        for reader in readers:
            reader.close()
        raise
    if len(readers) == 1:
        return readers[0]
    return MergedLogReader(readers)


def truncation_of(reader: LogReader) -> TruncationInfo | None:
    """What was lost from a damaged log opened with ``allow_truncated=True`` (None when intact)."""
    truncation = getattr(reader, "truncation", None)
    return truncation if isinstance(truncation, TruncationInfo) else None
