"""Write-back MCAP: every input message byte-exact (checked against mcap / rosbags directly), new
topics decodable with ``open_log`` + the decoders, input untouched, output atomic."""

from __future__ import annotations

import hashlib
import json
import os
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.errors import InputError, ReaderError
from fleetcal.pipeline.transforms import from_quat, from_xyz_rpy, invert
from fleetcal.readers.base import LogReader, RawMessage
from fleetcal.readers.decode import decode_compressed_image, decode_pointcloud2, decode_tf
from fleetcal.readers.open import open_log
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter
from fleetcal.workflows.sinks.ros_messages import Profile
from fleetcal.workflows.sinks.writeback import (
    MAP_TOPIC,
    OVERLAY_PREFIX,
    TRAJECTORY_TOPIC,
    CalibratedPose,
    write_back,
    writeback_path,
)

REAL_LOGS = [
    "kitti_2011_09_26.mcap",
    "nuscenes_n015.bag",
    "pjlab_road_rig1",
    "pjlab_road_rig2",
    "outdoor_scan_pair.mcap",
    "rgbd_fragment.mcap",
]

TINY_FORMATS = [
    pytest.param("mcap", {}, "tiny.mcap", True, id="mcap-ros2"),
    pytest.param("mcap", {"profile": "ros1"}, "tiny.mcap", True, id="mcap-ros1"),
    pytest.param("ros1", {}, "tiny.bag", True, id="ros1"),
    pytest.param("ros2", {}, "tiny", False, id="ros2-sqlite3-no-tf_static"),
    pytest.param("ros2", {"storage": "mcap"}, "tiny", True, id="ros2-mcap"),
]

Key = tuple[int, int, str]
"""(log_time_ns, publish_time_ns, sha256 of the bytes) of one message."""


# ---------------------------------------------------------------------------------------------
# Ground truth read with the container libraries directly (not through fleetcal's readers)


def _sha(data: bytes | memoryview) -> str:
    return hashlib.sha256(bytes(data)).hexdigest()


def _input_messages(path: Path) -> tuple[dict[str, Counter[Key]], dict[str, dict[str, Any]], str]:
    """Per topic: Counter of message keys; per topic: its channel/schema; the expected profile."""
    messages: dict[str, Counter[Key]] = {}
    channels: dict[str, dict[str, Any]] = {}
    if path.is_file() and path.suffix == ".mcap":
        with path.open("rb") as stream:
            reader = make_reader(stream)
            profile = reader.get_header().profile
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                key = (message.log_time, message.publish_time, _sha(message.data))
                messages.setdefault(channel.topic, Counter())[key] += 1
                channels[channel.topic] = {
                    "schema_name": schema.name if schema else "",
                    "schema_encoding": schema.encoding if schema else "",
                    "schema_data": bytes(schema.data) if schema else b"",
                    "message_encoding": channel.message_encoding,
                    "metadata": dict(channel.metadata),
                }
        return messages, channels, profile
    ros1 = path.suffix == ".bag"
    with AnyReader([path]) as bag:
        for conn, stamp_ns, data in bag.messages():
            messages.setdefault(conn.topic, Counter())[(stamp_ns, stamp_ns, _sha(data))] += 1
            channels[conn.topic] = {
                "msgtype": conn.msgtype,
                "schema_encoding": "ros1msg" if ros1 else "ros2msg",
                "schema_data": conn.msgdef.data.encode(),
                "message_encoding": "ros1" if ros1 else "cdr",
                "md5sum": conn.digest,
            }
    return messages, channels, "ros1" if ros1 else "ros2"


def _output_messages(path: Path) -> tuple[dict[str, Counter[Key]], dict[str, dict[str, Any]], list[int], Any]:
    """Like ``_input_messages`` for the output MCAP, plus log times in file order and the summary."""
    messages: dict[str, Counter[Key]] = {}
    channels: dict[str, dict[str, Any]] = {}
    file_order: list[int] = []
    with path.open("rb") as stream:
        reader = make_reader(stream)
        header = reader.get_header()
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            file_order.append(message.log_time)
            key = (message.log_time, message.publish_time, _sha(message.data))
            messages.setdefault(channel.topic, Counter())[key] += 1
            channels[channel.topic] = {
                "schema_name": schema.name if schema else "",
                "schema_encoding": schema.encoding if schema else "",
                "schema_data": bytes(schema.data) if schema else b"",
                "message_encoding": channel.message_encoding,
                "metadata": dict(channel.metadata),
                "profile": header.profile,
            }
    return messages, channels, file_order, summary


def _fingerprint(path: Path) -> dict[str, tuple[int, str]]:
    """mtime (ns) and sha256 of a file or of every file in a folder."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    return {str(p): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest()) for p in files}


# ---------------------------------------------------------------------------------------------
# The check shared by real and tiny logs


def _results(camera_topics: list[str], stamp0: int) -> dict[str, Any]:
    rng = np.random.default_rng(7)
    n = 500
    overlay_rgb = rng.integers(0, 255, size=(24, 32, 3), dtype=np.uint8)
    ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(overlay_rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return {
        "map_points_xyz": rng.normal(scale=20.0, size=(n, 3)).astype(np.float32),
        "map_channels": {
            "intensity": rng.random(n).astype(np.float32),
            "r": rng.integers(0, 256, n).astype(np.uint8),
            "g": rng.integers(0, 256, n).astype(np.uint8),
            "b": rng.integers(0, 256, n).astype(np.uint8),
        },
        "trajectory_stamps_ns": [stamp0 + i * 100_000_000 for i in range(4)],
        "trajectory_T_map_lidar": [from_xyz_rpy(i * 1.5, 0.2 * i, 0.0, 0.0, 1.0, 10.0 * i) for i in range(4)],
        "overlays": {topic: [(stamp0 + 5, jpeg.tobytes())] for topic in camera_topics[:2]},
    }


def _check_write_back(
    log_path: Path, out_path: Path, calibrations: list[CalibratedPose], camera_topics: list[str]
) -> None:
    before = _fingerprint(log_path)
    in_messages, in_channels, expected_profile = _input_messages(log_path)
    with open_log(log_path) as reader:
        start_ns, end_ns = reader.start_ns, reader.end_ns
        results = _results(camera_topics, start_ns)
        stats = write_back(reader, out_path, calibrations=calibrations, **results)
    assert _fingerprint(log_path) == before, "the input changed"
    assert not [p for p in out_path.parent.iterdir() if p.name.startswith(f".{out_path.name}.tmp-")]

    out_messages, out_channels, file_order, summary = _output_messages(out_path)
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == sum(sum(c.values()) for c in out_messages.values())
    assert file_order == sorted(file_order), "messages are not in log-time order"
    n_input = sum(sum(c.values()) for c in in_messages.values())
    assert stats.original_messages == n_input
    assert stats.profile == expected_profile

    new_topics = {"/tf_static": 1 if calibrations else 0, MAP_TOPIC: 1, TRAJECTORY_TOPIC: 1}
    new_topics.update({OVERLAY_PREFIX + t.lstrip("/"): 1 for t in results["overlays"]})
    new_keys: dict[str, Counter[Key]] = {}
    for topic, out_counter in out_messages.items():
        in_counter = in_messages.get(topic, Counter())
        assert not in_counter - out_counter, f"{topic}: input messages missing or changed"
        new_keys[topic] = out_counter - in_counter
        assert sum(new_keys[topic].values()) == new_topics.get(topic, 0), topic
    assert set(in_messages) <= set(out_messages)
    assert {t for t, n in new_topics.items() if n} <= set(out_messages)

    for topic, expected in in_channels.items():
        got = out_channels[topic]
        assert got["profile"] == expected_profile
        assert got["message_encoding"] == expected["message_encoding"]
        assert got["schema_encoding"] == expected["schema_encoding"]
        assert got["schema_data"] == expected["schema_data"]
        if "schema_name" in expected:  # MCAP input: everything as it was
            assert got["schema_name"] == expected["schema_name"]
            assert got["metadata"] == expected["metadata"]
        elif expected["message_encoding"] == "ros1":  # ROS 1 bag: ROS 1 spelling, md5sum kept
            assert got["schema_name"] == expected["msgtype"].replace("/msg/", "/")
            assert got["metadata"]["md5sum"] == expected["md5sum"]
        else:
            assert got["schema_name"] == expected["msgtype"]
    for topic in new_topics:
        if topic in out_channels and topic not in in_channels:
            expected_encoding = "ros1" if expected_profile == "ros1" else "cdr"
            assert out_channels[topic]["message_encoding"] == expected_encoding

    end_time = max(start_ns, end_ns - 1)
    with open_log(out_path) as out:
        assert out.format == "mcap"
        for topic, info in out.topics.items():
            assert info.count == sum(out_messages[topic].values())
        for raw in out.messages(topics=list(new_topics)):
            key = (raw.log_time_ns, raw.publish_time_ns, _sha(raw.data))
            if key not in new_keys[raw.topic]:
                continue
            msg = out.deserialize(raw)
            if raw.topic == "/tf_static":
                assert raw.log_time_ns == start_ns
                edges = {(parent, child): (stamp, T) for stamp, parent, child, T in decode_tf(msg)}
                assert len(edges) == len(calibrations)
                for cal in calibrations:
                    stamp, T_lidar_camera = edges[(cal.lidar_frame, cal.camera_frame)]
                    assert stamp == start_ns
                    np.testing.assert_allclose(T_lidar_camera, invert(cal.T_camera_lidar), atol=1e-9)
                    np.testing.assert_allclose(T_lidar_camera @ cal.T_camera_lidar, np.eye(4), atol=1e-9)
            elif raw.topic == MAP_TOPIC:
                assert raw.log_time_ns == end_time
                frame = decode_pointcloud2(msg, raw.topic)
                assert frame.frame_id == "map" and frame.stamp_ns == end_time
                points = results["map_points_xyz"]
                # all-zero / NaN points are dropped by the decoder; random normals have none
                np.testing.assert_array_equal(frame.points_xyz, points)
                for name in ("intensity", "r", "g", "b"):
                    np.testing.assert_array_equal(frame.channels[name], results["map_channels"][name])
            elif raw.topic == TRAJECTORY_TOPIC:
                assert msg.header.frame_id == "map"
                assert len(msg.poses) == len(results["trajectory_stamps_ns"])
                for pose, stamp, T in zip(
                    msg.poses, results["trajectory_stamps_ns"], results["trajectory_T_map_lidar"], strict=True
                ):
                    p, q = pose.pose.position, pose.pose.orientation
                    assert pose.header.stamp.sec * 1_000_000_000 + pose.header.stamp.nanosec == stamp
                    np.testing.assert_allclose(from_quat([p.x, p.y, p.z], [q.x, q.y, q.z, q.w]), T, atol=1e-9)
            else:
                camera_topic = "/" + raw.topic.removeprefix(OVERLAY_PREFIX)
                ((stamp, jpeg),) = results["overlays"][camera_topic]
                assert raw.log_time_ns == stamp
                image = decode_compressed_image(msg, raw.topic).image
                expected_bgr = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
                assert expected_bgr is not None
                np.testing.assert_array_equal(image, cv2.cvtColor(expected_bgr, cv2.COLOR_BGR2RGB))


# ---------------------------------------------------------------------------------------------
# Tiny logs of every format


def _write_tiny(path: Path, fmt: str, kwargs: dict[str, Any], with_tf_static: bool) -> None:
    rng = np.random.default_rng(3)
    profile: Profile = "ros1" if fmt == "ros1" or kwargs.get("profile") == "ros1" else "ros2"
    with LogWriter(path, fmt, **kwargs) as writer:  # type: ignore[arg-type]
        if with_tf_static:
            T = from_xyz_rpy(0.0, 0.0, 1.8, 0.0, 0.0, 0.0)
            writer.write("/tf_static", "tf2_msgs/msg/TFMessage", 1_000_000_000,
                         rm.tf_message([(1_000_000_000, "base_link", "lidar", T)], profile))
        for i in range(3):
            stamp = 1_000_000_000 + i * 100_000_000
            pts = rng.normal(size=(40, 3)).astype(np.float32)
            writer.write("/lidar/points", "sensor_msgs/msg/PointCloud2", stamp,
                         rm.pointcloud2(stamp, "lidar", pts, profile=profile))
            img = rng.integers(0, 255, size=(24, 32, 3), dtype=np.uint8)
            writer.write("/cam/image/compressed", "sensor_msgs/msg/CompressedImage", stamp + 3,
                         rm.compressed_image(stamp + 3, "cam_optical", img, profile=profile))


CALIBRATIONS = [
    CalibratedPose("lidar", "cam_optical", from_xyz_rpy(0.05, -0.1, -0.2, -90.0, 0.0, -90.0)),
    CalibratedPose("lidar", "cam2_optical", from_xyz_rpy(-0.3, 0.02, 0.1, -91.0, 2.0, 0.0)),
]


@pytest.mark.parametrize(("fmt", "kwargs", "name", "with_tf_static"), TINY_FORMATS)
def test_write_back_tiny_logs(
    tmp_path: Path, fmt: str, kwargs: dict[str, Any], name: str, with_tf_static: bool
) -> None:
    log = tmp_path / name
    _write_tiny(log, fmt, kwargs, with_tf_static)
    out = writeback_path(log)
    assert out == tmp_path / "tiny.fleetcal.mcap"
    _check_write_back(log, out, CALIBRATIONS, ["/cam/image/compressed"])
    # the camera frame of the overlay comes from the camera topic
    with open_log(out) as reader:
        (raw,) = reader.messages(topics=[OVERLAY_PREFIX + "cam/image/compressed"])
        assert reader.deserialize(raw).header.frame_id == "cam_optical"
        # new /tf_static shares the input's channel (one channel on that topic) when there was one
        with out.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        assert summary is not None
        tf_channels = [c for c in summary.channels.values() if c.topic == "/tf_static"]
        assert len(tf_channels) == 1
        assert reader.topics["/tf_static"].count == (2 if with_tf_static else 1)


# ---------------------------------------------------------------------------------------------
# Real logs


def _rigid(T: np.ndarray) -> np.ndarray:
    """T with its rotation projected onto SO(3)."""
    out = T.copy()
    out[:3, :3] = Rotation.from_matrix(T[:3, :3]).as_matrix()
    return out


@pytest.mark.parametrize("name", REAL_LOGS)
def test_write_back_real_logs(shared_data: Path, tmp_path: Path, name: str) -> None:
    log = shared_data / "logs" / name
    truth = json.loads((shared_data / "logs" / f"{Path(name).stem}.truth.json").read_text())
    pairs = truth.get("pairs", [])
    if pairs:
        # references are orthonormal to ~1e-6 only; a tf quaternion holds rotations, so project
        calibrations = [
            CalibratedPose(truth["lidar_frame"], p["camera_frame"], _rigid(np.asarray(p["T_camera_lidar"])))
            for p in pairs
        ]
    else:  # registration-only logs: any calibration exercises /tf_static creation
        calibrations = [CalibratedPose("lidar", "camera", from_xyz_rpy(0.1, 0.0, -0.1, -90.0, 0.0, -90.0))]
    out = writeback_path(log, tmp_path)
    assert out.name == f"{Path(name).stem}.fleetcal.mcap"
    _check_write_back(log, out, calibrations, [p["camera_topic"] for p in pairs])


# ---------------------------------------------------------------------------------------------
# Errors and atomicity


class _FailingReader:
    """A LogReader that raises ReaderError after ``fail_after`` messages (a damaged input)."""

    def __init__(self, inner: LogReader, fail_after: int) -> None:
        self.inner = inner
        self.fail_after = fail_after
        self.paths = inner.paths
        self.format = inner.format

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def messages(self, topics: Any = None, start_ns: Any = None, end_ns: Any = None) -> Iterator[RawMessage]:
        for i, raw in enumerate(self.inner.messages(topics, start_ns, end_ns)):
            if i == self.fail_after:
                raise ReaderError("damaged input")
            yield raw


def test_failure_leaves_nothing_and_keeps_previous_output(tmp_path: Path) -> None:
    log = tmp_path / "tiny.mcap"
    _write_tiny(log, "mcap", {}, True)
    out = writeback_path(log)
    out.write_bytes(b"previous")
    with open_log(log) as reader, pytest.raises(ReaderError, match="damaged input"):
        write_back(_FailingReader(reader, 3), out, calibrations=CALIBRATIONS)  # type: ignore[arg-type]
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.fleetcal.mcap", "tiny.mcap"]


def test_refuses_to_overwrite_input_and_bad_arguments(tmp_path: Path) -> None:
    log = tmp_path / "tiny.mcap"
    _write_tiny(log, "mcap", {}, True)
    before = _fingerprint(log)
    bag = tmp_path / "bag2"
    _write_tiny(bag, "ros2", {}, False)
    with open_log(log) as reader:
        with pytest.raises(InputError, match="overwrite its input"):
            write_back(reader, log)
        with pytest.raises(InputError, match="4x4"):
            write_back(reader, tmp_path / "o.mcap", calibrations=[CalibratedPose("l", "c", np.eye(3))])
        sheared = np.eye(4)
        sheared[0, 1] = 0.01
        with pytest.raises(InputError, match="not a rigid transform"):
            write_back(reader, tmp_path / "o.mcap", calibrations=[CalibratedPose("l", "c", sheared)])
        with pytest.raises(InputError, match="map channel intensity"):
            write_back(reader, tmp_path / "o.mcap", map_points_xyz=np.zeros((5, 3)),
                       map_channels={"intensity": np.zeros(4)})
        with pytest.raises(InputError, match="r, g, b"):
            write_back(reader, tmp_path / "o.mcap", map_points_xyz=np.zeros((5, 3)),
                       map_channels={"r": np.zeros(5)})
        with pytest.raises(InputError, match="2 stamps but 1 poses"):
            write_back(reader, tmp_path / "o.mcap", trajectory_stamps_ns=[1, 2],
                       trajectory_T_map_lidar=[np.eye(4)])
    with open_log(bag) as reader, pytest.raises(InputError, match="overwrite its input"):
        write_back(reader, bag / "inside.mcap")
    assert _fingerprint(log) == before
    assert not (tmp_path / "o.mcap").exists()


def test_nothing_new_is_a_plain_copy(tmp_path: Path) -> None:
    log = tmp_path / "tiny.bag"
    _write_tiny(log, "ros1", {}, True)
    with open_log(log) as reader:
        stats = write_back(reader, tmp_path / "copy.mcap")
    assert stats.new_messages == {} and stats.profile == "ros1"
    in_messages, _, _ = _input_messages(log)
    out_messages, _, _, _ = _output_messages(tmp_path / "copy.mcap")
    assert out_messages == in_messages
    assert os.path.getsize(tmp_path / "copy.mcap") == stats.bytes_written


def test_mcap_details_kept(tmp_path: Path) -> None:
    """Publish times, channel metadata, an IDL schema, a no-schema channel and a type without a
    definition survive byte for byte (written with mcap directly, not with fleetcal)."""
    from mcap.writer import Writer

    store = rm.get_store("ros2")
    log = tmp_path / "raw.mcap"
    msgdef = store.generate_msgdef("sensor_msgs/msg/PointCloud2", ros_version=2)[0]
    with log.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        cloud_schema = writer.register_schema("sensor_msgs/msg/PointCloud2", "ros2msg", msgdef.encode())
        vendor_schema = writer.register_schema("vendor_msgs/msg/Packet", "", b"")
        qos = {"offered_qos_profiles": "- depth: 5"}
        cloud = writer.register_channel("/points", "cdr", cloud_schema, qos)
        vendor = writer.register_channel("/packets", "cdr", vendor_schema, {"driver": "v1.2"})
        blob = writer.register_channel("/blob", "json", 0, {})
        rng = np.random.default_rng(1)
        for i in range(4):
            t = 2_000_000_000 + i * 50_000_000
            msg = rm.pointcloud2(t, "lidar", rng.normal(size=(30, 3)).astype(np.float32))
            data = bytes(store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
            writer.add_message(cloud, t, data, t - 7)
            writer.add_message(vendor, t + 1, rng.bytes(64), t - 11, sequence=i)
            writer.add_message(blob, t + 2, json.dumps({"i": i}).encode(), t + 2)
        writer.finish()
    before = _fingerprint(log)
    in_messages, in_channels, _ = _input_messages(log)
    with open_log(log) as reader:
        assert not reader.topics["/packets"].decodable
        stats = write_back(reader, tmp_path / "raw.fleetcal.mcap", calibrations=CALIBRATIONS[:1])
    assert _fingerprint(log) == before
    out_messages, out_channels, _, _ = _output_messages(tmp_path / "raw.fleetcal.mcap")
    assert stats.new_messages == {"/tf_static": 1}
    for topic in ("/points", "/packets", "/blob"):
        assert out_messages[topic] == in_messages[topic]
        assert all(publish != log_time for log_time, publish, _ in out_messages[topic] if topic != "/blob")
        got = {k: v for k, v in out_channels[topic].items() if k != "profile"}
        assert got == in_channels[topic]
