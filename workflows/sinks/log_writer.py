"""Write logs: MCAP (ros2/cdr or ros1 profile), ROS 1 ``.bag`` and ROS 2 bag folders (sqlite3 or mcap).

The container libraries do the writing (``mcap.writer.Writer``, ``rosbags.rosbag1.Writer``,
``rosbags.rosbag2.Writer``); schemas come from the typestore's message definitions. Output is
atomic: written under a temporary name in the same folder and renamed on ``close``; an exception
inside ``with LogWriter(...)`` removes the temporary output.
"""

from __future__ import annotations

import os
import sys
from contextlib import ExitStack, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Literal

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag1 import Writer as Bag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Bag2Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.msg import denormalize_msgtype
from rosbags.typesys.store import Typestore

from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.msgtypes import LogFormat
from fleetcal.stages.sinks.atomic import atomic_path
from fleetcal.workflows.sinks.ros_messages import Profile, get_store

_IDL_MARKER = "=" * 80 + "\nIDL: "
_SERIALIZATION = {"ros1": "ros1", "ros2": "cdr"}


@dataclass
class _Topic:
    msgtype: str
    handle: Any
    serialization: str
    store: Typestore


def _latched_qos() -> list[Qos]:
    """Transient-local QoS offered by ``/tf_static`` publishers (so players latch it)."""
    return [
        Qos(
            QosHistory.KEEP_LAST,
            1,
            QosReliability.RELIABLE,
            QosDurability.TRANSIENT_LOCAL,
            QosTime(0, 0),
            QosTime(0, 0),
            QosLiveliness.AUTOMATIC,
            QosTime(0, 0),
            False,
        )
    ]


def _store_from_msgdef(msgtype: str, msgdef: str, profile: Profile) -> Typestore:
    """A private typestore holding ``msgtype`` as ``msgdef`` defines it (the profile's store when empty)."""
    if not msgdef.strip():
        store = get_store(profile)
        if msgtype not in store.types:
            raise InputError(f"no message definition for type {msgtype} and it is not a standard type")
        return store
    store = get_typestore(Stores.EMPTY)
    try:
        if msgdef.startswith(_IDL_MARKER):
            store.register(get_types_from_idl(msgdef))
        else:
            store.register(get_types_from_msg(msgdef, msgtype))
    except Exception as err:
        raise InputError(f"cannot parse the message definition of {msgtype}: {err}") from err
    return store


class LogWriter:
    """A log being written; use as a context manager.

    Args:
        path: output file (``mcap``, ``ros1``) or folder (``ros2``).
        fmt: ``mcap``, ``ros1`` (ROS 1 bag v2.0) or ``ros2`` (rosbag2 folder).
        compression: ``zstd`` (default), ``lz4``, ``bz2`` or None. MCAP: chunk compression (zstd,
            lz4). ROS 1 bags have no zstd, so ``zstd`` means lz4 chunks there (bz2 also allowed).
            ROS 2: zstd storage compression for mcap storage, per-message zstd for sqlite3.
        profile: MCAP only: ``ros2`` (cdr, default) or ``ros1`` serialization.
        storage: ROS 2 only: ``sqlite3`` (default) or ``mcap``.
        chunk_size: MCAP chunk size in bytes.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        fmt: LogFormat = "mcap",
        compression: str | None = "zstd",
        *,
        profile: Profile | None = None,
        storage: Literal["sqlite3", "mcap"] = "sqlite3",
        chunk_size: int = 4 * 1024 * 1024,
    ) -> None:
        if fmt not in ("mcap", "ros1", "ros2"):
            raise InputError(f"unknown log format {fmt!r} (expected mcap, ros1 or ros2)")
        if fmt == "ros1":
            profile = "ros1"
        elif fmt == "ros2":
            profile = "ros2"
        self.profile: Profile = profile or "ros2"
        if self.profile not in ("ros1", "ros2"):
            raise InputError(f"unknown message profile {self.profile!r} (expected 'ros1' or 'ros2')")
        self.path = Path(path)
        self.fmt: LogFormat = fmt
        self.store = get_store(self.profile)
        self.messages_written = 0
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[tuple[str, str, str], int] = {}
        self._stack = ExitStack()
        self._closed = False
        temp = self._stack.enter_context(atomic_path(self.path))
        try:
            self._open(temp, compression, storage, chunk_size)
        except BaseException:
            self._stack.__exit__(*sys.exc_info())
            raise

    def _open(self, temp: Path, compression: str | None, storage: str, chunk_size: int) -> None:
        if compression not in (None, "zstd", "lz4", "bz2"):
            raise InputError(f"unknown compression {compression!r} (expected zstd, lz4, bz2 or none)")
        self._mcap: McapWriter | None = None
        self._bag1: Bag1Writer | None = None
        self._bag2: Bag2Writer | None = None
        if self.fmt == "mcap":
            kinds = {None: CompressionType.NONE, "zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}
            if compression not in kinds:
                raise InputError(f"MCAP cannot use {compression} compression (zstd, lz4 or none)")
            self._stream: IO[bytes] = self._stack.enter_context(temp.open("wb"))
            self._mcap = McapWriter(self._stream, chunk_size=chunk_size, compression=kinds[compression])
            self._mcap.start(profile=self.profile, library="fleetcal")
        elif self.fmt == "ros1":
            self._bag1 = Bag1Writer(temp)
            if compression is not None:
                kind = (
                    Bag1Writer.CompressionFormat.BZ2
                    if compression == "bz2"
                    else Bag1Writer.CompressionFormat.LZ4
                )
                self._bag1.set_compression(kind)
            self._bag1.open()
        else:
            if storage not in ("sqlite3", "mcap"):
                raise InputError(f"unknown rosbag2 storage {storage!r} (expected sqlite3 or mcap)")
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self._bag2 = Bag2Writer(temp, version=Bag2Writer.VERSION_LATEST, storage_plugin=plugin)
            if compression == "zstd":
                mode = CompressionMode.STORAGE if storage == "mcap" else CompressionMode.MESSAGE
                self._bag2.set_compression(mode, CompressionFormat.ZSTD)
            elif compression is not None:
                raise InputError(f"ROS 2 bags cannot use {compression} compression (zstd or none)")
            self._bag2.open()

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort(exc_type, exc, tb)

    def write(self, topic: str, msgtype: str, log_time_ns: int, msg: Any) -> None:
        """Serialise ``msg`` (a ``msgtype`` object of this writer's profile); write it at ``log_time_ns``."""
        serialization = _SERIALIZATION[self.profile]
        try:
            if serialization == "cdr":
                data = self.store.serialize_cdr(msg, msgtype)
            else:
                data = self.store.serialize_ros1(msg, msgtype)
        except Exception as err:
            raise InputError(
                f"cannot serialise a {type(msg).__name__} as {msgtype} ({self.profile}) for {topic}: {err}"
            ) from err
        entry = self._topic(topic, msgtype, "", serialization, self.store)
        self._write(entry, int(log_time_ns), data)

    def write_raw(
        self,
        topic: str,
        msgtype: str,
        log_time_ns: int,
        data: bytes | memoryview,
        msgdef: str,
        serialization: str,
    ) -> None:
        """Write already serialised bytes (``cdr`` or ``ros1``) with their definition text.

        Byte-exact with the given definition when the container takes that serialization (MCAP
        takes both). Otherwise converted (a ROS 1 bag: cdr to ros1, a ROS 2 bag: ros1 to cdr) and
        written with the standard definition of the type (the given one for non-standard types).
        """
        if serialization not in ("cdr", "ros1"):
            raise InputError(f"unknown serialization {serialization!r} for {topic} (expected cdr or ros1)")
        target = serialization if self.fmt == "mcap" else _SERIALIZATION[self.profile]
        known = self._topics.get(topic)
        if target == serialization:
            store = known.store if known else _store_from_msgdef(msgtype, msgdef, self.profile)
            entry = self._topic(topic, msgtype, msgdef, target, store)
            self._write(entry, int(log_time_ns), data)
            return
        ros2_store = get_store("ros2")
        convert_store = ros2_store if msgtype in ros2_store.types else None
        if convert_store is None:
            source_profile: Profile = "ros1" if serialization == "ros1" else "ros2"
            convert_store = _store_from_msgdef(msgtype, msgdef, source_profile)
        try:
            if target == "ros1":
                data = convert_store.cdr_to_ros1(data, msgtype)
            else:
                data = convert_store.ros1_to_cdr(data, msgtype)
        except Exception as err:
            raise InputError(
                f"cannot convert {topic} ({msgtype}) from {serialization} to {target}: {err}"
            ) from err
        store = self.store if msgtype in self.store.types else convert_store
        entry = self._topic(topic, msgtype, "", target, store)
        self._write(entry, int(log_time_ns), data)

    def _topic(self, topic: str, msgtype: str, msgdef: str, serialization: str, store: Typestore) -> _Topic:
        entry = self._topics.get(topic)
        if entry is not None:
            if entry.msgtype != msgtype or entry.serialization != serialization:
                raise InputError(
                    f"topic {topic} was written as {entry.msgtype} ({entry.serialization}),"
                    f" not {msgtype} ({serialization})"
                )
            return entry
        if self._mcap is not None:
            handle: Any = self._mcap_channel(topic, msgtype, msgdef, serialization, store)
        elif self._bag1 is not None:
            text, md5sum = store.generate_msgdef(msgtype, ros_version=1)
            text = msgdef or text
            latching = 1 if topic.rstrip("/").endswith("tf_static") else None
            handle = self._bag1.add_connection(topic, msgtype, msgdef=text, md5sum=md5sum, latching=latching)
        else:
            assert self._bag2 is not None
            text = msgdef or store.generate_msgdef(msgtype, ros_version=2)[0]
            qos = _latched_qos() if topic.rstrip("/").endswith("tf_static") else []
            handle = self._bag2.add_connection(
                topic, msgtype, msgdef=text, rihs01=store.hash_rihs01(msgtype), offered_qos_profiles=qos
            )
        entry = _Topic(msgtype, handle, serialization, store)
        self._topics[topic] = entry
        return entry

    def _mcap_channel(
        self, topic: str, msgtype: str, msgdef: str, serialization: str, store: Typestore
    ) -> int:
        assert self._mcap is not None
        if serialization == "ros1":
            name, encoding = denormalize_msgtype(msgtype), "ros1msg"
            text = msgdef or store.generate_msgdef(msgtype, ros_version=1)[0]
            metadata = {"md5sum": store.generate_msgdef(msgtype, ros_version=1)[1]}
        else:
            text = msgdef or store.generate_msgdef(msgtype, ros_version=2)[0]
            name, encoding = msgtype, "ros2idl" if text.startswith(_IDL_MARKER) else "ros2msg"
            metadata = {}
        key = (name, encoding, text)
        schema_id = self._schemas.get(key)
        if schema_id is None:
            schema_id = self._mcap.register_schema(name=name, encoding=encoding, data=text.encode())
            self._schemas[key] = schema_id
        return self._mcap.register_channel(
            topic=topic, message_encoding=serialization, schema_id=schema_id, metadata=metadata
        )

    def _write(self, entry: _Topic, log_time_ns: int, data: bytes | memoryview) -> None:
        if self._closed:
            raise InputError(f"log {self.path} is already closed")
        if log_time_ns < 0:
            raise InputError(f"negative log time {log_time_ns} ns")
        if self._mcap is not None:
            self._mcap.add_message(
                channel_id=entry.handle, log_time=log_time_ns, data=bytes(data), publish_time=log_time_ns
            )
        elif self._bag1 is not None:
            self._bag1.write(entry.handle, log_time_ns, data)
        else:
            assert self._bag2 is not None
            self._bag2.write(entry.handle, log_time_ns, data)
        self.messages_written += 1

    def close(self) -> None:
        """Finish the container and rename it into place."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._mcap is not None:
                self._mcap.finish()
            elif self._bag1 is not None:
                self._bag1.close()
            elif self._bag2 is not None:
                self._bag2.close()
        except BaseException:
            self._stack.__exit__(*sys.exc_info())
            raise
        self._stack.close()

    def abort(self, *exc_info: Any) -> None:
        """Drop the output: nothing is left at ``path`` (an earlier file there stays untouched)."""
        if self._closed:
            return
        self._closed = True
        for writer in (self._bag1, self._bag2):
            if writer is not None:
                with suppress(Exception):
                    writer.abort()
        if not exc_info or exc_info[0] is None:
            exc_info = (InputError, InputError("aborted"), None)
        self._stack.__exit__(*exc_info)
