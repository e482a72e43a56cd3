"""LogWriter and builders: logs of every format read back with mcap / rosbags (and open_log when present)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.transforms import from_xyz_rpy
from fleetcal.stages.sinks.atomic import atomic_path
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter
from fleetcal.workflows.sinks.ros_messages import Profile

FORMATS = [
    pytest.param("mcap", {}, "log.mcap", id="mcap-ros2"),
    pytest.param("mcap", {"profile": "ros1"}, "log.mcap", id="mcap-ros1"),
    pytest.param("mcap", {"compression": None}, "log.mcap", id="mcap-uncompressed"),
    pytest.param("ros1", {}, "log.bag", id="ros1"),
    pytest.param("ros1", {"compression": None}, "log.bag", id="ros1-uncompressed"),
    pytest.param("ros2", {}, "bag", id="ros2-sqlite3"),
    pytest.param("ros2", {"storage": "mcap"}, "bag", id="ros2-mcap"),
]

CAMERA = CameraModel(
    64, 48, np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), np.array([0.1, -0.02, 0, 0, 0])
)
T_LIDAR_CAMERA = from_xyz_rpy(0.1, -0.2, 0.3, -90.0, 0.0, -90.0)


def _write_sample(path: Path, fmt: str, kwargs: dict[str, Any], n_frames: int = 3) -> dict[str, int]:
    """Write lidar + image + camera_info + tf_static + path; return expected message counts."""
    rng = np.random.default_rng(0)
    profile: Profile = "ros1" if fmt == "ros1" or kwargs.get("profile") == "ros1" else "ros2"
    with LogWriter(path, fmt, **kwargs) as writer:  # type: ignore[arg-type]
        writer.write(
            "/tf_static",
            "tf2_msgs/msg/TFMessage",
            0,
            rm.tf_message([(0, "lidar", "camera", T_LIDAR_CAMERA)], profile),
        )
        for i in range(n_frames):
            stamp = 1_000_000_000 + i * 100_000_000
            pts = rng.normal(size=(50, 3)).astype(np.float32)
            cloud = rm.pointcloud2(
                stamp, "lidar", pts, {"intensity": np.arange(50, dtype=np.float32)}, profile=profile
            )
            writer.write("/lidar", "sensor_msgs/msg/PointCloud2", stamp, cloud)
            img = rng.integers(0, 255, size=(48, 64, 3), dtype=np.uint8)
            writer.write(
                "/cam/image_raw",
                "sensor_msgs/msg/Image",
                stamp + 1,
                rm.image(stamp, "camera", img, "rgb8", profile),
            )
            writer.write(
                "/cam/camera_info",
                "sensor_msgs/msg/CameraInfo",
                stamp + 2,
                rm.camera_info(stamp, "camera", CAMERA, profile),
            )
        poses = np.stack([from_xyz_rpy(i, 0, 0, 0, 0, 10 * i) for i in range(n_frames)])
        stamps = [1_000_000_000 + i * 100_000_000 for i in range(n_frames)]
        writer.write(
            "/path", "nav_msgs/msg/Path", stamps[-1] + 5, rm.path(stamps[-1], "map", stamps, poses, profile)
        )
    return {
        "/tf_static": 1,
        "/lidar": n_frames,
        "/cam/image_raw": n_frames,
        "/cam/camera_info": n_frames,
        "/path": 1,
    }


def _read_back(path: Path, fmt: str, kwargs: dict[str, Any]) -> list[tuple[str, str, int, Any]]:
    """(topic, msgtype, log_time_ns, message object) of every message, read with mcap or rosbags."""
    out = []
    if fmt == "mcap":
        profile = kwargs.get("profile", "ros2")
        store = rm.get_store(profile)
        with path.open("rb") as stream:
            mcap_reader = make_reader(stream)
            assert mcap_reader.get_header().profile == profile
            for schema, channel, message in mcap_reader.iter_messages():
                assert schema is not None
                msgtype = schema.name if "/msg/" in schema.name else schema.name.replace("/", "/msg/", 1)
                if channel.message_encoding == "cdr":
                    msg = store.deserialize_cdr(message.data, msgtype)
                else:
                    assert channel.message_encoding == "ros1"
                    msg = store.deserialize_ros1(message.data, msgtype)
                out.append((channel.topic, msgtype, message.log_time, msg))
        return out
    with AnyReader([path], default_typestore=rm.get_store("ros2")) as reader:
        for conn, stamp, raw in reader.messages():
            out.append((conn.topic, conn.msgtype, stamp, reader.deserialize(raw, conn.msgtype)))
    return out


@pytest.mark.parametrize(("fmt", "kwargs", "name"), FORMATS)
def test_written_log_reads_back(tmp_path: Path, fmt: str, kwargs: dict[str, Any], name: str) -> None:
    path = tmp_path / name
    expected = _write_sample(path, fmt, kwargs)
    assert path.exists()
    assert [p.name for p in tmp_path.iterdir()] == [name], "temporary output left behind"
    messages = _read_back(path, fmt, kwargs)
    counts: dict[str, int] = {}
    for topic, _, _, _ in messages:
        counts[topic] = counts.get(topic, 0) + 1
    assert counts == expected
    times = [t for _, _, t, _ in messages]
    assert times == sorted(times)
    clouds = [m for topic, _, _, m in messages if topic == "/lidar"]
    assert clouds[1].header.stamp.sec == 1 and clouds[1].header.stamp.nanosec == 100_000_000
    assert clouds[0].width == 50 and clouds[0].point_step == 16
    tf = next(m for topic, _, _, m in messages if topic == "/tf_static").transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("lidar", "camera")
    assert tf.transform.translation.z == pytest.approx(0.3)
    path_msg = next(m for topic, _, _, m in messages if topic == "/path")
    assert len(path_msg.poses) == 3
    assert path_msg.poses[2].pose.position.x == pytest.approx(2.0)
    yaw = 2 * np.degrees(
        np.arctan2(path_msg.poses[2].pose.orientation.z, path_msg.poses[2].pose.orientation.w)
    )
    assert yaw == pytest.approx(20.0)


def test_exception_inside_with_leaves_nothing(tmp_path: Path) -> None:
    for fmt, name in (("mcap", "a.mcap"), ("ros1", "a.bag"), ("ros2", "a")):
        with pytest.raises(RuntimeError, match="boom"), LogWriter(tmp_path / name, fmt) as writer:  # type: ignore[arg-type]
            writer.write(
                "/tf", "tf2_msgs/msg/TFMessage", 1, rm.tf_message([(1, "a", "b", np.eye(4))], writer.profile)
            )
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_overwrite_replaces_existing_output(tmp_path: Path) -> None:
    target = tmp_path / "bag"
    _write_sample(target, "ros2", {}, n_frames=1)
    _write_sample(target, "ros2", {}, n_frames=2)
    counts = [m[0] for m in _read_back(target, "ros2", {})].count("/lidar")
    assert counts == 2
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]


def test_write_raw_is_byte_exact_and_converts(tmp_path: Path) -> None:
    store = rm.get_store("ros2")
    msg = rm.pointcloud2(5, "lidar", np.ones((4, 3), np.float32), {"ring": np.arange(4, dtype=np.uint16)})
    data = bytes(store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    msgdef = store.generate_msgdef("sensor_msgs/msg/PointCloud2", ros_version=2)[0]
    with LogWriter(tmp_path / "x.mcap", "mcap") as writer:
        writer.write_raw("/pc", "sensor_msgs/msg/PointCloud2", 7, data, msgdef, "cdr")
    with (tmp_path / "x.mcap").open("rb") as stream:
        ((schema, channel, message),) = list(make_reader(stream).iter_messages())
    assert message.data == data and message.log_time == 7
    assert schema is not None and schema.data.decode() == msgdef and channel.message_encoding == "cdr"

    with LogWriter(tmp_path / "x.bag", "ros1") as writer:
        writer.write_raw("/pc", "sensor_msgs/msg/PointCloud2", 7, data, msgdef, "cdr")
    ((_, _, _, back),) = _read_back(tmp_path / "x.bag", "ros1", {})
    assert back.header.frame_id == "lidar"
    assert bytes(back.data) == bytes(msg.data)


def test_bad_arguments_raise_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown log format"):
        LogWriter(tmp_path / "a", "zip")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="cannot use lz4"):
        LogWriter(tmp_path / "a", "ros2", compression="lz4")
    with pytest.raises(InputError, match="does not exist"):
        LogWriter(tmp_path / "missing" / "a.mcap", "mcap")
    with LogWriter(tmp_path / "b.mcap", "mcap") as writer:
        writer.write("/t", "tf2_msgs/msg/TFMessage", 1, rm.tf_message([]))
        with pytest.raises(InputError, match="was written as"):
            writer.write("/t", "nav_msgs/msg/Path", 2, rm.path(1, "map", [], np.zeros((0, 4, 4))))
        with pytest.raises(InputError, match="cannot serialise"):
            writer.write("/u", "sensor_msgs/msg/Image", 2, rm.tf_message([]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.mcap"]


def test_atomic_path_renames_only_on_success(tmp_path: Path) -> None:
    final = tmp_path / "out.txt"
    final.write_text("old")
    with pytest.raises(ValueError), atomic_path(final) as temp:
        temp.write_text("new")
        raise ValueError
    assert final.read_text() == "old"
    with atomic_path(final) as temp:
        assert temp.parent != tmp_path and temp.name == "out.txt"
        temp.write_text("new")
    assert final.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with pytest.raises(InputError, match="exists already"), atomic_path(final, overwrite=False):
        pass


@pytest.mark.parametrize(("fmt", "kwargs", "name"), FORMATS)
def test_written_log_opens_with_open_log(tmp_path: Path, fmt: str, kwargs: dict[str, Any], name: str) -> None:
    from fleetcal.readers.open import open_log

    path = tmp_path / name
    expected = _write_sample(path, fmt, kwargs)
    with open_log(path) as reader:
        assert {name: info.count for name, info in reader.topics.items()} == expected
        raws = list(reader.messages(topics=["/lidar"]))
        assert len(raws) == 3
        cloud = reader.deserialize(raws[0])
        assert cloud.width == 50
