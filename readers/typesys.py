"""Typestore handling: message types registered from the log's own definitions.

A log carries the definitions of the types it holds (MCAP schemas, ROS 1 connection headers,
rosbag2 ``type_description``/metadata). ``build_log_types`` registers those in a fresh rosbags
typestore, on top of a standard store (ROS 1 Noetic or the latest ROS 2 LTS) for types the log does
not define. A type neither source defines (vendor packets such as ``velodyne_msgs/msg/VelodyneScan``
in a bag without definitions) is marked undecodable; ``LogTypes.deserialize`` then raises
``DecodeError`` naming the type instead of crashing.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cache, lru_cache
from typing import Any, Literal

from rosbags.interfaces import (
    Connection,
    ConnectionExtRosbag1,
    ConnectionExtRosbag2,
    MessageDefinitionFormat,
    Nodetype,
)
from rosbags.rosbag2.metadata import dump_qos_v8
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, TypesysError, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.msg import denormalize_msgtype
from rosbags.typesys.store import Typestore

from fleetcal.pipeline.errors import DecodeError
from fleetcal.readers.base import ChannelInfo, RawMessage, Serialization, TopicInfo

DefinitionEncoding = Literal["ros2msg", "ros2idl", "ros1msg", ""]

_IDL_SEPARATOR = "=" * 80 + "\n"
_BUILTIN_TYPES = {"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"}


@dataclass(frozen=True)
class TypeDefinition:
    """The definition a log carries for one message type.

    Attributes:
        msgtype: type name, ROS 1 (``pkg/Type``) or ROS 2 (``pkg/msg/Type``) spelling.
        encoding: ``ros2msg``, ``ros2idl``, ``ros1msg``, or ``""`` when the log carries none.
        text: the definition text (the type itself, then its dependencies).
    """

    msgtype: str
    encoding: DefinitionEncoding
    text: str


@lru_cache(maxsize=4096)
def normalize_msgtype(msgtype: str) -> str:
    """ROS 2 spelling of a type name: ``sensor_msgs/PointCloud2`` -> ``sensor_msgs/msg/PointCloud2``.

    Cached: readers call it for every message.
    """
    parts = msgtype.strip().split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return "/".join(parts)


def parse_definition(definition: TypeDefinition) -> dict[str, Any]:
    """Parse one definition into a rosbags ``Typesdict`` (type name -> field definitions).

    Raises:
        TypesysError: the text is not a valid definition of that encoding.
    """
    msgtype = normalize_msgtype(definition.msgtype)
    if definition.encoding in ("ros2msg", "ros1msg"):
        return dict(get_types_from_msg(definition.text, msgtype))
    if definition.encoding == "ros2idl":
        typs: dict[str, Any] = {}
        if definition.text.startswith(f"{_IDL_SEPARATOR}IDL: "):
            for section in definition.text.split(_IDL_SEPARATOR)[1:]:
                _, idl = section.split("\n", 1)
                typs.update(get_types_from_idl(idl))
        else:
            typs.update(get_types_from_idl(definition.text))
        return typs
    return {}


@dataclass
class LogTypes:
    """The message types of one log and the typestore that decodes them.

    Attributes:
        typestore: rosbags typestore holding the log's types (plus standard ones as fallback).
        undecodable: type name (ROS 2 spelling) -> why it cannot be decoded.
    """

    typestore: Typestore
    undecodable: dict[str, str] = field(default_factory=dict)

    def is_decodable(self, msgtype: str) -> bool:
        """Whether messages of ``msgtype`` can be deserialised."""
        return normalize_msgtype(msgtype) not in self.undecodable

    def deserialize(self, raw: RawMessage) -> Any:
        """The rosbags message object of ``raw``.

        Raises:
            DecodeError: the type has no definition, or the bytes do not match it.
        """
        msgtype = normalize_msgtype(raw.msgtype)
        reason = self.undecodable.get(msgtype)
        if reason is not None:
            raise DecodeError(f"cannot decode {raw.topic}: {reason}")
        try:
            if raw.serialization == "ros1":
                return self.typestore.deserialize_ros1(raw.data, msgtype)
            # rosbags slices off the 4-byte CDR header: on bytes that copies the whole payload, on a
            # memoryview it does not, so uint8[] fields (PointCloud2.data, Image.data) stay views.
            return self.typestore.deserialize_cdr(memoryview(raw.data), msgtype)
        except (SerdeError, struct.error, ValueError, IndexError, KeyError, UnicodeDecodeError) as err:
            msg = f"cannot decode a {msgtype} message on {raw.topic} ({raw.serialization}): {err}"
            raise DecodeError(msg) from err


@cache
def _base_fielddefs(serialization: Serialization) -> dict[str, Any]:
    """Field definitions of the fallback store (built once per process; callers must copy)."""
    store = get_typestore(Stores.ROS1_NOETIC if serialization == "ros1" else Stores.LATEST)
    return dict(store.fielddefs)


def _field_type_names(desc: Any) -> list[str]:
    """Type names a rosbags field description ``(Nodetype, data)`` refers to."""
    nodetype, data = desc
    if nodetype == Nodetype.NAME:
        return [str(data)]
    if nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _field_type_names(data[0])
    return []


def _referenced_types(fielddefs: dict[str, Any], msgtype: str) -> set[str]:
    """Names of every type ``msgtype`` refers to (transitively), itself included."""
    seen: set[str] = set()
    stack = [msgtype]
    while stack:
        name = stack.pop()
        if name in seen:
            continue
        seen.add(name)
        entry = fielddefs.get(name)
        if entry is None:
            continue
        for _, desc in entry[1]:
            stack.extend(_field_type_names(desc))
    return seen


def build_log_types(definitions: Iterable[TypeDefinition], serialization: Serialization) -> LogTypes:
    """A typestore with every type ``definitions`` provide, standard types as a fallback.

    Args:
        definitions: one entry per topic type of the log (``encoding=""`` when it carries none).
        serialization: the log's dominant serialization; picks the fallback store (ROS 1 Noetic for
            ``ros1``, latest ROS 2 LTS for ``cdr``).

    Returns:
        LogTypes whose ``undecodable`` lists each type that neither the log nor the fallback store
        defines completely (with the reason). Its typestore holds the log's topic types and the
        types they use (not the whole fallback store), and is shared by every log with the same
        definitions (cached per process; never register types in it).
    """
    cached = _build_log_types_cached(tuple(definitions), serialization)
    return LogTypes(typestore=cached.typestore, undecodable=dict(cached.undecodable))


@lru_cache(maxsize=64)
def _build_log_types_cached(
    definitions: tuple[TypeDefinition, ...], serialization: Serialization
) -> LogTypes:
    log_typs: dict[str, Any] = {}
    broken: dict[str, str] = {}
    for definition in definitions:
        msgtype = normalize_msgtype(definition.msgtype)
        if not definition.encoding or not definition.text.strip():
            continue
        try:
            log_typs.update(parse_definition(definition))
        except (TypesysError, ValueError, IndexError) as err:
            broken[msgtype] = f"its definition in the log ({definition.encoding}) does not parse: {err}"

    combined = dict(_base_fielddefs(serialization))
    combined.update(log_typs)
    for name in _BUILTIN_TYPES:
        combined.pop(name, None)
    needed: set[str] = set()
    for definition in definitions:
        needed |= _referenced_types(combined, normalize_msgtype(definition.msgtype))
    typestore = get_typestore(Stores.EMPTY)
    try:
        typestore.register({name: combined[name] for name in sorted(needed) if name in combined})
    except TypesysError:
        typestore = get_typestore(Stores.EMPTY)
        typestore.register({k: v for k, v in log_typs.items() if k not in _BUILTIN_TYPES})

    undecodable: dict[str, str] = dict(broken)
    for definition in definitions:
        msgtype = normalize_msgtype(definition.msgtype)
        if msgtype in undecodable:
            continue
        referenced = _referenced_types(typestore.fielddefs, msgtype)
        missing = sorted(name for name in referenced if name not in typestore.fielddefs)
        if missing:
            what = "it" if missing == [msgtype] else ", ".join(missing)
            undecodable[msgtype] = (
                f"the log carries no definition for message type {msgtype} (missing: {what})"
            )
            continue
        try:
            typestore.get_msgdef(msgtype)
        except (KeyError, TypesysError, SerdeError) as err:
            undecodable[msgtype] = f"message type {msgtype} cannot be compiled: {err}"
    return LogTypes(typestore=typestore, undecodable=undecodable)


def topics_from_connections(
    connections: Iterable[Connection], serialization: Serialization
) -> tuple[dict[str, TopicInfo], LogTypes]:
    """Topic table and types of a rosbags reader's connections (several per topic are merged).

    Args:
        connections: ``rosbags`` connections (rosbag1 or rosbag2).
        serialization: ``ros1`` for ROS 1 bags, ``cdr`` for ROS 2 bags.
    """
    connections = list(connections)
    msg_encoding: DefinitionEncoding = "ros1msg" if serialization == "ros1" else "ros2msg"
    definitions = []
    for conn in connections:
        if conn.msgdef.format == MessageDefinitionFormat.MSG:
            definitions.append(TypeDefinition(conn.msgtype, msg_encoding, conn.msgdef.data))
        elif conn.msgdef.format == MessageDefinitionFormat.IDL:
            definitions.append(TypeDefinition(conn.msgtype, "ros2idl", conn.msgdef.data))
        else:
            definitions.append(TypeDefinition(conn.msgtype, "", ""))
    types = build_log_types(definitions, serialization)
    topics: dict[str, TopicInfo] = {}
    for conn in connections:
        msgtype = normalize_msgtype(conn.msgtype)
        previous = topics.get(conn.topic)
        topics[conn.topic] = TopicInfo(
            name=conn.topic,
            msgtype=msgtype,
            count=conn.msgcount + (previous.count if previous is not None else 0),
            serialization=serialization,
            decodable=types.is_decodable(msgtype) and (previous is None or previous.decodable),
            msgdef=conn.msgdef.data,
        )
    return topics, types


def channel_info_from_connection(conn: Connection, serialization: Serialization) -> ChannelInfo:
    """How a rosbags connection is stored, as a ``ChannelInfo`` (for byte-exact copies).

    ROS 1: schema name in ROS 1 spelling, ``ros1msg``, metadata ``md5sum`` and, where the connection
    header has them, ``callerid`` and ``latching`` (``true``/``false``). ROS 2: ``ros2msg`` or
    ``ros2idl`` by the stored definition's format, metadata ``offered_qos_profiles`` (rosbag2 YAML).
    """
    has_definition = conn.msgdef.format != MessageDefinitionFormat.NONE and bool(conn.msgdef.data.strip())
    metadata: dict[str, str] = {}
    if serialization == "ros1":
        schema_name = denormalize_msgtype(conn.msgtype)
        schema_encoding = "ros1msg" if has_definition else ""
        if conn.digest:
            metadata["md5sum"] = conn.digest
        if isinstance(conn.ext, ConnectionExtRosbag1):
            if conn.ext.callerid is not None:
                metadata["callerid"] = conn.ext.callerid
            if conn.ext.latching is not None:
                metadata["latching"] = "true" if conn.ext.latching else "false"
    else:
        schema_name = normalize_msgtype(conn.msgtype)
        schema_encoding = ""
        if has_definition:
            schema_encoding = "ros2idl" if conn.msgdef.format == MessageDefinitionFormat.IDL else "ros2msg"
        if isinstance(conn.ext, ConnectionExtRosbag2):
            metadata["offered_qos_profiles"] = dump_qos_v8(conn.ext.offered_qos_profiles)
    return ChannelInfo(
        topic=conn.topic,
        message_encoding=serialization,
        schema_name=schema_name,
        schema_encoding=schema_encoding,
        schema_data=conn.msgdef.data.encode() if has_definition else b"",
        metadata=tuple(sorted(metadata.items())),
    )
