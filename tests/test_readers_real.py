"""Readers and ``inspect`` on the real logs in ../shared/data (skipped when absent).

Counts are cross-checked against a plain iteration with the container libraries themselves (mcap's
reader for MCAP files, rosbags for ROS 1 bags, sqlite3 / mcap on a ROS 2 bag's storage files), and
tf edges against the ``truth.json`` sidecars.
"""

from __future__ import annotations

import json
import sqlite3
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.rosbag1 import Reader as Rosbag1Reader

from fleetcal.pipeline.errors import DecodeError
from fleetcal.pipeline.transforms import TransformTree, from_quat
from fleetcal.readers.base import LogReader
from fleetcal.readers.open import open_log
from fleetcal.workflows.inspect_log import inspect_log

LOGS = ["kitti_2011_09_26.mcap", "nuscenes_n015.bag", "pjlab_road_rig1", "pjlab_road_rig2",
        "outdoor_scan_pair.mcap", "rgbd_fragment.mcap"]
FORMATS = ["rosbag2_fixtures/ros1_test_bag.bag", "rosbag2_fixtures/talker_mcap",
           "rosbag2_fixtures/talker_sqlite3", "rosbag2_fixtures/cdr_test",
           "rosbag2_fixtures/only_topics.mcap", "velodyne_vlp16_packets", "hesai_xt32_packets"]


def plain_counts(path: Path) -> Counter[str]:
    """Messages per topic counted without fleetcal: mcap reader, rosbags, or the bag's sqlite3 table."""
    counts: Counter[str] = Counter()
    if path.suffix == ".mcap":
        with path.open("rb") as stream:
            for _, channel, _ in make_reader(stream).iter_messages():
                counts[channel.topic] += 1
    elif path.suffix == ".bag":
        with Rosbag1Reader(path) as reader:
            for conn, _, _ in reader.messages():
                counts[conn.topic] += 1
    else:
        for db in sorted(path.glob("*.db3")):
            with sqlite3.connect(db) as con:
                rows = con.execute(
                    "SELECT topics.name, COUNT(*) FROM messages JOIN topics ON messages.topic_id = topics.id "
                    "GROUP BY topics.name").fetchall()
            counts.update(dict(rows))
        for storage in sorted(path.glob("*.mcap")):
            counts.update(plain_counts(storage))
    return counts


def read_counts(reader: LogReader) -> Counter[str]:
    return Counter(raw.topic for raw in reader.messages())


def tf_tree(reader: LogReader) -> TransformTree:
    tree = TransformTree()
    for raw in reader.messages(["/tf", "/tf_static"]):
        for t in reader.deserialize(raw).transforms:
            stamp_ns = t.header.stamp.sec * 10**9 + t.header.stamp.nanosec
            q = t.transform.rotation
            v = t.transform.translation
            T = from_quat([v.x, v.y, v.z], [q.x, q.y, q.z, q.w])
            tree.add(t.header.frame_id, t.child_frame_id, T, stamp_ns, raw.topic == "/tf_static")
    return tree


@pytest.mark.parametrize("name", LOGS)
def test_real_log_counts_topics_and_tf(shared_data: Path, name: str) -> None:
    path = shared_data / "logs" / name
    truth = json.loads((shared_data / "logs" / f"{Path(name).stem}.truth.json").read_text())
    with open_log(path) as reader:
        counts = read_counts(reader)
        assert counts == plain_counts(path)
        assert {t: info.count for t, info in reader.topics.items() if info.count} == dict(counts)
        report = inspect_log(reader)
        topics = {t.name: t for t in report.topics}
        lidar = truth["lidar_topic"]
        assert report.lidar_topics == [lidar]
        assert topics[lidar].type == "sensor_msgs/msg/PointCloud2"
        if "lidar_frame" in truth:
            assert topics[lidar].frame_id == truth["lidar_frame"]
        pairs = truth.get("pairs", [])
        assert report.camera_topics == sorted(p["camera_topic"] for p in pairs)
        for pair in pairs:
            assert topics[pair["camera_topic"]].frame_id == pair["camera_frame"]
        assert report.undecodable_topics == []
        if not pairs:
            assert report.tf == []
            return
        tree = tf_tree(reader)
        assert sorted((e.parent, e.child, e.static) for e in report.tf) == sorted(tree.edges())
        for pair in pairs:
            if "T_camera_lidar_in_log" in pair:
                T = tree.lookup(pair["camera_frame"], truth["lidar_frame"], reader.start_ns)
                np.testing.assert_allclose(T, np.array(pair["T_camera_lidar_in_log"]), atol=1e-6)
        if "rig" in truth:
            T_base_lidar = tree.lookup("base_link", truth["lidar_frame"], reader.start_ns)
            np.testing.assert_allclose(T_base_lidar, np.array(truth["rig"]["T_base_lidar_in_log"]), atol=1e-6)


def test_real_nuscenes_tf_edges(shared_data: Path) -> None:
    with open_log(shared_data / "logs" / "nuscenes_n015.bag") as reader:
        report = inspect_log(reader)
    edges = {(e.parent, e.child, e.static) for e in report.tf}
    cams = ["cam_front", "cam_front_left", "cam_front_right", "cam_back", "cam_back_left", "cam_back_right"]
    assert edges == {("base_link", "lidar_top", True), ("odom", "base_link", False)} | {
        ("base_link", f"{c}_optical", True) for c in cams}
    assert report.format == "ros1"
    assert len(report.camera_topics) == 6


@pytest.mark.parametrize("name", FORMATS)
def test_ros_tool_fixtures_counts(shared_data: Path, name: str) -> None:
    path = shared_data / "formats" / name
    with open_log(path) as reader:
        counts = read_counts(reader)
        assert counts == plain_counts(path)
        metadata = path / "metadata.yaml"
        if metadata.is_file():
            import yaml

            info = yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]
            expected = {t["topic_metadata"]["name"]: t["message_count"]
                        for t in info["topics_with_message_count"]}
            assert {t: i.count for t, i in reader.topics.items()} == expected
            assert sum(counts.values()) == info["message_count"]


def test_rosbag2_fixture_topics(shared_data: Path) -> None:
    fixtures = shared_data / "formats" / "rosbag2_fixtures"
    with open_log(fixtures / "ros1_test_bag.bag") as reader:
        assert {t: i.count for t, i in reader.topics.items()} == {"/rosout": 3, "/test_topic": 1,
                                                                  "/test_topic2": 1}
        raws = list(reader.messages(["/test_topic"]))
        assert reader.deserialize(raws[0]).__msgtype__ == "std_msgs/msg/String"
    with open_log(fixtures / "talker_mcap") as reader:
        strings = [reader.deserialize(r).data for r in reader.messages(["/topic"])]
        assert strings == [f"Hello, world! {i}" for i in range(10)]
    with open_log(fixtures / "cdr_test") as reader:
        basic = [reader.deserialize(r) for r in reader.messages(["/test_topic"])]
        assert len(basic) == 3 and all(hasattr(m, "float64_value") for m in basic)


@pytest.mark.parametrize(("name", "topic", "msgtype"), [
    ("velodyne_vlp16_packets", "/velodyne_packets", "velodyne_msgs/msg/VelodyneScan"),
    ("hesai_xt32_packets", "/pandar_packets", "pandar_msgs/msg/PandarScan"),
])
def test_vendor_packets_are_listed_undecodable(
    shared_data: Path, name: str, topic: str, msgtype: str
) -> None:
    with open_log(shared_data / "formats" / name) as reader:
        info = reader.topics[topic]
        assert (info.msgtype, info.count, info.decodable) == (msgtype, 4, False)
        raws = list(reader.messages())
        assert len(raws) == 4 and all(len(r.data) > 1000 for r in raws)
        with pytest.raises(DecodeError, match=msgtype):
            reader.deserialize(raws[0])
        report = inspect_log(reader)
    assert report.undecodable_topics == [topic]
    assert report.lidar_topics == [] and report.topics[0].frame_id is None
