"""Readers on tiny logs of every container format, written in tmp_path with rosbags / mcap writers."""

from __future__ import annotations

import functools
import os
import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.records import Chunk
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from fleetcal.pipeline.errors import DecodeError, InputError, ReaderError, TruncatedLogError
from fleetcal.readers.mcap_reader import McapLogReader
from fleetcal.readers.merged import MergedLogReader
from fleetcal.readers.open import detect_format, open_log, truncation_of

T0_NS = 1_700_000_000_000_000_000
MS = 1_000_000
FORMATS = ["mcap-ros2", "mcap-ros1", "ros1", "ros2-sqlite3", "ros2-mcap"]
EXPECTED_FORMAT = {"mcap-ros2": "mcap", "mcap-ros1": "mcap", "ros1": "ros1", "ros2-sqlite3": "ros2",
                   "ros2-mcap": "ros2"}
PNG_BYTES = b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\rIHDR" + bytes(17)


@dataclass(frozen=True)
class Entry:
    """One message to write: topic, ROS 2 type name, log time (ns), message object."""

    topic: str
    msgtype: str
    log_time_ns: int
    msg: Any


@functools.cache
def _store(ros1: bool) -> Typestore:
    if not ros1:
        return get_typestore(Stores.LATEST)
    store = get_typestore(Stores.ROS1_NOETIC)
    tf_text = "geometry_msgs/TransformStamped[] transforms"
    store.register(get_types_from_msg(tf_text, "tf2_msgs/msg/TFMessage"))
    return store


def store_for(kind: str) -> Typestore:
    """The typestore tests write ``kind`` logs with (ROS 1 Noetic + tf2_msgs, or latest ROS 2)."""
    return _store(kind in ("ros1", "mcap-ros1"))


def build(store: Typestore, msgtype: str, **values: Any) -> Any:
    """A message of ``msgtype`` with ``values`` given by case-insensitive field name."""
    names = [name for name, _ in store.fielddefs[msgtype][1]]
    by_lower = {k.lower(): v for k, v in values.items()}
    kwargs = {name: by_lower[name.lower()] for name in names if name.lower() in by_lower}
    if "seq" in names and "seq" not in kwargs:
        kwargs["seq"] = 0
    return store.types[msgtype](**kwargs)


def header(store: Typestore, stamp_ns: int, frame_id: str) -> Any:
    stamp = build(store, "builtin_interfaces/msg/Time", sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return build(store, "std_msgs/msg/Header", stamp=stamp, frame_id=frame_id)


def pointcloud(store: Typestore, stamp_ns: int, points_xyz: np.ndarray) -> Any:
    fields = [
        build(store, "sensor_msgs/msg/PointField", name=n, offset=4 * i, datatype=7, count=1)
        for i, n in enumerate("xyz")
    ]
    data = np.ascontiguousarray(points_xyz, dtype=np.float32).view(np.uint8).reshape(-1)
    return build(
        store, "sensor_msgs/msg/PointCloud2", header=header(store, stamp_ns, "lidar"), height=1,
        width=len(points_xyz), fields=fields, is_bigendian=False, point_step=12,
        row_step=12 * len(points_xyz), data=data, is_dense=True,
    )


def image(store: Typestore, stamp_ns: int, pixels: np.ndarray) -> Any:
    return build(
        store, "sensor_msgs/msg/Image", header=header(store, stamp_ns, "cam_optical"),
        height=pixels.shape[0], width=pixels.shape[1], encoding="mono8", is_bigendian=0,
        step=pixels.shape[1], data=pixels.reshape(-1).astype(np.uint8),
    )


def camera_info(store: Typestore, stamp_ns: int) -> Any:
    roi = build(store, "sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                do_rectify=False)
    k = np.array([100.0, 0, 8, 0, 100.0, 6, 0, 0, 1])
    p = np.array([100.0, 0, 8, 0, 0, 100.0, 6, 0, 0, 0, 1, 0])
    return build(
        store, "sensor_msgs/msg/CameraInfo", header=header(store, stamp_ns, "cam_optical"), height=12,
        width=16, distortion_model="plumb_bob", d=np.zeros(5), k=k, r=np.eye(3).reshape(-1), p=p,
        binning_x=0, binning_y=0, roi=roi,
    )


def tf_message(store: Typestore, stamp_ns: int, edges: list[tuple[str, str]]) -> Any:
    transforms = []
    for parent, child in edges:
        transform = build(
            store, "geometry_msgs/msg/Transform",
            translation=build(store, "geometry_msgs/msg/Vector3", x=0.1, y=0.2, z=0.3),
            rotation=build(store, "geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=0.0, w=1.0),
        )
        transforms.append(build(store, "geometry_msgs/msg/TransformStamped",
                                header=header(store, stamp_ns, parent), child_frame_id=child,
                                transform=transform))
    return build(store, "tf2_msgs/msg/TFMessage", transforms=transforms)


def sample_entries(kind: str, t0_ns: int = T0_NS, scans: int = 5) -> list[Entry]:
    """A small recording: tf_static, lidar at 10 Hz, a camera with its info, a 20 Hz chatter."""
    store = store_for(kind)
    rng = np.random.default_rng(7)
    entries = [Entry("/tf_static", "tf2_msgs/msg/TFMessage", t0_ns,
                     tf_message(store, t0_ns, [("base_link", "lidar"), ("lidar", "cam_optical")]))]
    for i in range(scans):
        t = t0_ns + i * 100 * MS
        entries.append(Entry("/lidar/points", "sensor_msgs/msg/PointCloud2", t,
                             pointcloud(store, t, rng.normal(size=(50 + i, 3)))))
        entries.append(Entry("/cam/image_raw", "sensor_msgs/msg/Image", t + 20 * MS,
                             image(store, t + 20 * MS, rng.integers(0, 255, size=(12, 16)))))
        entries.append(Entry("/cam/camera_info", "sensor_msgs/msg/CameraInfo", t + 20 * MS,
                             camera_info(store, t + 20 * MS)))
    for i in range(2 * scans):
        t = t0_ns + i * 50 * MS + 5 * MS
        entries.append(Entry("/chatter", "std_msgs/msg/String", t,
                             build(store, "std_msgs/msg/String", data=f"hello {i}")))
    return sorted(entries, key=lambda e: e.log_time_ns)


def write_mcap(path: Path, entries: list[Entry], profile: str = "ros2", chunk_size: int = 1024 * 1024,
               use_chunking: bool = True) -> Path:
    """An MCAP file (ros2 profile with cdr, or ros1 profile) written with mcap's own writer."""
    store = store_for("mcap-ros1" if profile == "ros1" else "mcap-ros2")
    with path.open("wb") as stream:
        writer = McapWriter(stream, chunk_size=chunk_size, compression=CompressionType.ZSTD,
                            use_chunking=use_chunking)
        writer.start(profile=profile, library="fleetcal-tests")
        channels: dict[str, int] = {}
        for entry in entries:
            if entry.topic not in channels:
                if profile == "ros1":
                    name = entry.msgtype.replace("/msg/", "/")
                    text = store.generate_msgdef(entry.msgtype)[0]
                    schema = writer.register_schema(name, "ros1msg", text.encode())
                    channels[entry.topic] = writer.register_channel(entry.topic, "ros1", schema)
                else:
                    text = store.generate_msgdef(entry.msgtype, ros_version=2)[0]
                    schema = writer.register_schema(entry.msgtype, "ros2msg", text.encode())
                    channels[entry.topic] = writer.register_channel(entry.topic, "cdr", schema)
            if profile == "ros1":
                data = bytes(store.serialize_ros1(entry.msg, entry.msgtype))
            else:
                data = bytes(store.serialize_cdr(entry.msg, entry.msgtype))
            writer.add_message(channels[entry.topic], entry.log_time_ns, data, entry.log_time_ns)
        writer.finish()
    return path


def write_rosbag1(path: Path, entries: list[Entry]) -> Path:
    store = store_for("ros1")
    with Rosbag1Writer(path) as writer:
        conns: dict[str, Any] = {}
        for entry in entries:
            if entry.topic not in conns:
                conns[entry.topic] = writer.add_connection(entry.topic, entry.msgtype, typestore=store)
            data = store.serialize_ros1(entry.msg, entry.msgtype)
            writer.write(conns[entry.topic], entry.log_time_ns, data)
    return path


def write_rosbag2(path: Path, entries: list[Entry], storage: str = "sqlite3") -> Path:
    store = store_for("ros2")
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Rosbag2Writer(path, version=9, storage_plugin=plugin) as writer:
        conns: dict[str, Any] = {}
        for entry in entries:
            if entry.topic not in conns:
                conns[entry.topic] = writer.add_connection(entry.topic, entry.msgtype, typestore=store)
            writer.write(conns[entry.topic], entry.log_time_ns, store.serialize_cdr(entry.msg, entry.msgtype))
    return path


def write_log(kind: str, folder: Path, entries: list[Entry], name: str = "log") -> Path:
    """Write ``entries`` as a log of ``kind`` (one of FORMATS) under ``folder``; returns its path."""
    if kind == "mcap-ros2":
        return write_mcap(folder / f"{name}.mcap", entries, "ros2")
    if kind == "mcap-ros1":
        return write_mcap(folder / f"{name}.mcap", entries, "ros1")
    if kind == "ros1":
        return write_rosbag1(folder / f"{name}.bag", entries)
    return write_rosbag2(folder / name, entries, "sqlite3" if kind == "ros2-sqlite3" else "mcap")


@pytest.fixture(params=FORMATS)
def sample_log(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, Path, list[Entry]]:
    kind = request.param
    entries = sample_entries(kind)
    return kind, write_log(kind, tmp_path, entries), entries


def _count_calls(monkeypatch: pytest.MonkeyPatch, store: Typestore) -> list[str]:
    calls: list[str] = []
    for name in ("deserialize_cdr", "deserialize_ros1"):
        original = getattr(store, name)

        def spy(rawdata: Any, typename: str, _original: Any = original) -> Any:
            calls.append(typename)
            return _original(rawdata, typename)

        monkeypatch.setattr(store, name, spy)
    return calls


SampleLog = tuple[str, Path, list[Entry]]


def test_every_format_round_trips_topics_counts_and_messages(sample_log: SampleLog) -> None:
    kind, path, entries = sample_log
    with open_log(path) as reader:
        assert reader.format == EXPECTED_FORMAT[kind]
        topics = reader.topics
        assert {name: info.count for name, info in topics.items()} == {
            "/tf_static": 1, "/lidar/points": 5, "/cam/image_raw": 5, "/cam/camera_info": 5, "/chatter": 10,
        }
        assert topics["/lidar/points"].msgtype == "sensor_msgs/msg/PointCloud2"
        assert topics["/chatter"].serialization == ("ros1" if kind in ("ros1", "mcap-ros1") else "cdr")
        assert all(info.decodable for info in topics.values())
        assert reader.start_ns == entries[0].log_time_ns
        assert reader.end_ns == entries[-1].log_time_ns + 1

        raws = list(reader.messages())
        assert [(r.topic, r.log_time_ns) for r in raws] == [(e.topic, e.log_time_ns) for e in entries]
        for raw, entry in zip(raws, entries, strict=True):
            msg = reader.deserialize(raw)
            if entry.topic == "/lidar/points":
                assert msg.header.frame_id == "lidar"
                assert msg.width == entry.msg.width
                np.testing.assert_array_equal(msg.data, entry.msg.data)
            elif entry.topic == "/chatter":
                assert msg.data == entry.msg.data
            elif entry.topic == "/cam/camera_info":
                k = msg.K if kind in ("ros1", "mcap-ros1") else msg.k
                np.testing.assert_allclose(k, [100.0, 0, 8, 0, 100.0, 6, 0, 0, 1])
            elif entry.topic == "/tf_static":
                assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == [
                    ("base_link", "lidar"), ("lidar", "cam_optical")]
                assert msg.transforms[0].transform.translation.z == pytest.approx(0.3)


def test_topic_and_time_filter_never_deserialises_skipped_messages(
    sample_log: SampleLog, monkeypatch: pytest.MonkeyPatch
) -> None:
    _, path, entries = sample_log
    start_ns, end_ns = T0_NS + 100 * MS, T0_NS + 300 * MS
    expected = [e for e in entries if e.topic == "/chatter" and start_ns <= e.log_time_ns < end_ns]
    with open_log(path) as reader:
        store = reader._types.typestore  # type: ignore[attr-defined]
        calls = _count_calls(monkeypatch, store)
        raws = list(reader.messages(["/chatter"], start_ns=start_ns, end_ns=end_ns))
        assert calls == []
        assert [r.log_time_ns for r in raws] == [e.log_time_ns for e in expected]
        assert len(raws) == 4
        decoded = [reader.deserialize(r).data for r in raws]
        assert decoded == [e.msg.data for e in expected]
        assert len(calls) == len(raws)
        assert list(reader.messages(["/no/such/topic"])) == []
        later = [e for e in entries if e.log_time_ns >= end_ns]
        assert len(list(reader.messages(start_ns=end_ns))) == len(later)


def test_mcap_topic_filter_reads_only_matching_chunks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = store_for("mcap-ros2")
    entries = [Entry("/a", "std_msgs/msg/String", T0_NS + i, build(store, "std_msgs/msg/String", data="a"))
               for i in range(50)]
    entries += [Entry("/b", "std_msgs/msg/String", T0_NS + 1000 + i, build(store, "std_msgs/msg/String",
                data="b" * 100)) for i in range(50)]
    path = write_mcap(tmp_path / "ab.mcap", entries, chunk_size=512)
    import mcap.reader

    opened: list[int] = []
    original = mcap.reader.breakup_chunk

    def spy(chunk: Chunk, validate_crc: bool = False) -> Any:
        opened.append(chunk.message_start_time)
        return original(chunk, validate_crc)

    monkeypatch.setattr(mcap.reader, "breakup_chunk", spy)
    with open_log(path) as reader:
        raws = list(reader.messages(["/a"]))
    assert len(raws) == 50
    assert opened and all(stamp < T0_NS + 1000 for stamp in opened)


def test_mcap_summary_is_parsed_once_per_file_version(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Opening a log again and reading its messages reuses the summary already parsed; the same path written
    again (another size and time) is parsed afresh and reads its new messages."""
    import mcap.reader

    parsed: list[int] = []
    original = mcap.reader.SeekingReader.get_summary

    def spy(self: mcap.reader.SeekingReader) -> Any:
        parsed.append(1)
        return original(self)

    monkeypatch.setattr(mcap.reader.SeekingReader, "get_summary", spy)
    path = write_mcap(tmp_path / "again.mcap", sample_entries("mcap-ros2", scans=5))
    for _ in range(3):
        with open_log(path) as reader:
            assert sum(1 for _ in reader.messages(["/lidar/points"])) == 5
    assert len(parsed) == 1
    write_mcap(path, sample_entries("mcap-ros2", scans=3))
    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    with open_log(path) as reader:
        assert sum(1 for _ in reader.messages(["/lidar/points"])) == 3
    assert len(parsed) == 2


def test_several_files_merge_in_log_time_order(tmp_path: Path) -> None:
    for kind in ("mcap-ros2", "ros1"):
        first = sample_entries(kind, T0_NS)
        second = sample_entries(kind, T0_NS + 25 * MS)
        folder = tmp_path / kind
        folder.mkdir()
        a = write_log(kind, folder, first, "part_a")
        b = write_log(kind, folder, second, "part_b")
        with open_log([b, a]) as reader:
            assert isinstance(reader, MergedLogReader)
            assert reader.paths == [str(b), str(a)]
            assert reader.topics["/chatter"].count == 20
            stamps = [r.log_time_ns for r in reader.messages()]
            assert len(stamps) == 2 * len(first)
            assert stamps == sorted(e.log_time_ns for e in first + second)
            chatter = list(reader.messages(["/chatter"], end_ns=T0_NS + 100 * MS))
            assert [reader.deserialize(r).data for r in chatter] == [
                "hello 0", "hello 0", "hello 1", "hello 1"]
            assert reader.start_ns == T0_NS
            assert reader.end_ns == second[-1].log_time_ns + 1


def test_merging_different_formats_is_an_error(tmp_path: Path) -> None:
    a = write_log("mcap-ros2", tmp_path, sample_entries("mcap-ros2"))
    b = write_log("ros1", tmp_path, sample_entries("ros1"))
    with pytest.raises(ReaderError, match="different formats"):
        open_log([a, b])


def _intact_prefix(path: Path, cut: int) -> tuple[int, int]:
    """Reference: messages in complete top-level records within ``cut`` bytes, and where they end."""
    size = path.stat().st_size
    messages = 0
    end = 8
    with path.open("rb") as stream:
        stream.seek(8)
        records = StreamReader(stream, skip_magic=True, emit_chunks=True).records
        offset = 8
        while offset < size:
            opcode, length = struct.unpack("<BQ", os.pread(stream.fileno(), 9, offset))
            record = next(records)
            offset += 9 + length
            if offset > cut:
                break
            end = offset
            if isinstance(record, Chunk):
                messages += sum(1 for r in breakup_chunk(record) if type(r).__name__ == "Message")
            elif opcode == 0x05:
                messages += 1
    return messages, end


@pytest.mark.parametrize("use_chunking", [True, False])
def test_truncated_mcap_recovers_every_intact_record(tmp_path: Path, use_chunking: bool) -> None:
    entries = sample_entries("mcap-ros2", scans=40)
    full = write_mcap(tmp_path / "full.mcap", entries, chunk_size=2048, use_chunking=use_chunking)
    data = full.read_bytes()
    cut = len(data) // 2
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(data[:cut])
    expected_messages, intact_end = _intact_prefix(full, cut)
    assert 0 < expected_messages < len(entries)

    with pytest.raises(TruncatedLogError, match=rf"recovered {expected_messages} messages") as info:
        open_log(damaged)
    assert info.value.recovered_messages == expected_messages
    assert info.value.lost_bytes == cut - intact_end > 0

    with open_log(damaged, allow_truncated=True) as reader:
        truncation = truncation_of(reader)
        assert truncation is not None
        assert (truncation.recovered_messages, truncation.lost_bytes) == (expected_messages, cut - intact_end)
        raws = list(reader.messages())
        assert len(raws) == expected_messages == sum(t.count for t in reader.topics.values())
        assert [(r.topic, r.log_time_ns) for r in raws] == [(e.topic, e.log_time_ns) for e in
                                                            entries[:expected_messages]]
        assert reader.deserialize(raws[-1]) is not None
        chatter = list(reader.messages(["/chatter"], start_ns=T0_NS + 500 * MS))
        assert all(r.topic == "/chatter" and r.log_time_ns >= T0_NS + 500 * MS for r in chatter)
        assert len(chatter) == sum(1 for e in entries[:expected_messages]
                                   if e.topic == "/chatter" and e.log_time_ns >= T0_NS + 500 * MS)


def test_intact_mcap_reports_no_truncation(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "ok.mcap", sample_entries("mcap-ros2"))
    with open_log(path) as reader:
        assert truncation_of(reader) is None


def test_mcap_type_without_definition_is_listed_undecodable(tmp_path: Path) -> None:
    store = store_for("mcap-ros2")
    path = tmp_path / "vendor.mcap"
    with path.open("wb") as stream:
        writer = McapWriter(stream)
        writer.start(profile="ros2", library="fleetcal-tests")
        schema = writer.register_schema("velodyne_msgs/msg/VelodyneScan", "", b"")
        packets = writer.register_channel("/velodyne_packets", "cdr", schema)
        text = store.generate_msgdef("std_msgs/msg/String", ros_version=2)[0].encode()
        chatter = writer.register_channel("/chatter", "cdr", writer.register_schema(
            "std_msgs/msg/String", "ros2msg", text))
        writer.add_message(packets, T0_NS, b"\x00\x01\x00\x00" + bytes(64), T0_NS)
        msg = build(store, "std_msgs/msg/String", data="ok")
        data = bytes(store.serialize_cdr(msg, "std_msgs/msg/String"))
        writer.add_message(chatter, T0_NS + 1, data, T0_NS + 1)
        writer.finish()
    with open_log(path) as reader:
        assert reader.topics["/velodyne_packets"].decodable is False
        assert reader.topics["/chatter"].decodable is True
        raws = list(reader.messages())
        assert len(raws) == 2
        with pytest.raises(DecodeError, match="velodyne_msgs/msg/VelodyneScan"):
            reader.deserialize(raws[0])
        assert reader.deserialize(raws[1]).data == "ok"


def test_ros2_bag_without_stored_definition_is_listed_undecodable(tmp_path: Path) -> None:
    store = get_typestore(Stores.LATEST)
    store.register(get_types_from_msg("uint8[] packet\nuint32 stamp", "vendor_msgs/msg/Packets"))
    bag = tmp_path / "vendor_bag"
    with Rosbag2Writer(bag, version=9) as writer:
        conn = writer.add_connection("/packets", "vendor_msgs/msg/Packets", typestore=store)
        msg = store.types["vendor_msgs/msg/Packets"](packet=np.arange(4, dtype=np.uint8), stamp=3)
        for i in range(3):
            writer.write(conn, T0_NS + i, store.serialize_cdr(msg, "vendor_msgs/msg/Packets"))
    db = next(bag.glob("*.db3"))
    with sqlite3.connect(db) as con:
        con.execute("DELETE FROM message_definitions")
    with open_log(bag / "metadata.yaml") as reader:
        info = reader.topics["/packets"]
        assert (info.msgtype, info.count, info.decodable) == ("vendor_msgs/msg/Packets", 3, False)
        raws = list(reader.messages())
        assert len(raws) == 3
        with pytest.raises(DecodeError, match="no definition for message type vendor_msgs/msg/Packets"):
            reader.deserialize(raws[0])


def test_corrupt_payload_raises_decode_error(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "ok.mcap", sample_entries("mcap-ros2"))
    with open_log(path) as reader:
        raw = next(reader.messages(["/lidar/points"]))
        broken = type(raw)(raw.topic, raw.msgtype, raw.log_time_ns, bytes(raw.data)[:40], raw.serialization)
        with pytest.raises(DecodeError, match="sensor_msgs/msg/PointCloud2"):
            reader.deserialize(broken)


def test_ros2_bag_opens_from_folder_yaml_or_db3(tmp_path: Path) -> None:
    bag = write_rosbag2(tmp_path / "bag", sample_entries("ros2"))
    db3 = next(bag.glob("*.db3"))
    for path in (bag, bag / "metadata.yaml", db3):
        with open_log(path) as reader:
            assert reader.format == "ros2"
            assert sum(1 for _ in reader.messages()) == 26


def _bad_inputs(tmp_path: Path) -> Iterator[tuple[str, Path, type[Exception], str]]:
    yield "missing", tmp_path / "nope.mcap", InputError, "no such file or directory"
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    yield "empty", empty, ReaderError, "empty file"
    noise = tmp_path / "noise.mcap"
    noise.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    yield "random", noise, ReaderError, r"not a valid \.mcap file"
    png = tmp_path / "picture.png"
    png.write_bytes(PNG_BYTES)
    yield "png", png, ReaderError, "is a PNG image"
    folder = tmp_path / "not_a_bag"
    folder.mkdir()
    (folder / "readme.txt").write_text("hi")
    yield "folder", folder, ReaderError, "not a ROS 2 bag folder"
    unknown = tmp_path / "log.xyz"
    unknown.write_text("some text\n")
    yield "extension", unknown, ReaderError, "unknown log format"


def test_bad_inputs_raise_one_line_errors(tmp_path: Path) -> None:
    seen = []
    for name, path, error, pattern in _bad_inputs(tmp_path):
        with pytest.raises(error, match=pattern) as info:
            open_log(path)
        assert "\n" not in str(info.value)
        seen.append(name)
    assert len(seen) == 6


def test_mcap_magic_but_garbage_is_a_reader_error(tmp_path: Path) -> None:
    path = tmp_path / "garbage.mcap"
    path.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    for allow_truncated in (False, True):
        with pytest.raises(ReaderError, match="not a valid MCAP file"):
            McapLogReader(path, allow_truncated=allow_truncated)


def test_mcap_with_only_a_header_recovers_nothing(tmp_path: Path) -> None:
    full = write_mcap(tmp_path / "full.mcap", sample_entries("mcap-ros2"))
    _, header_end = _intact_prefix(full, 60)
    damaged = tmp_path / "header_only.mcap"
    damaged.write_bytes(full.read_bytes()[: header_end + 5])
    with pytest.raises(TruncatedLogError, match="recovered 0 messages, lost 5 bytes"):
        open_log(damaged)
    with McapLogReader(damaged, allow_truncated=True) as reader:
        assert reader.topics == {}
        assert list(reader.messages()) == []
        assert reader.truncation is not None and reader.truncation.recovered_messages == 0


def test_detect_format_by_content_not_name(tmp_path: Path) -> None:
    mcap_path = write_mcap(tmp_path / "log.mcap", sample_entries("mcap-ros2"))
    renamed = tmp_path / "recording.dat"
    renamed.write_bytes(mcap_path.read_bytes())
    assert detect_format(renamed) == "mcap"
    bag = write_rosbag1(tmp_path / "x.bag", sample_entries("ros1"))
    assert detect_format(bag) == "ros1"
    with open_log(renamed) as reader:
        assert reader.topics["/chatter"].count == 10
