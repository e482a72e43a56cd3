"""Pairing by header stamps, frame iteration from logs, CameraInfo attachment."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import ConfigError, InputError
from fleetcal.readers.frames import camera_info_topic_for, iter_camera_frames, iter_lidar_frames
from fleetcal.readers.open import open_log
from fleetcal.workflows.pairing import PairingStats, choose_pairs, iter_pairs, pair_stamps, raw_header_stamp_ns
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter
from fleetcal.workflows.sinks.ros_messages import Profile

MS = 1_000_000
K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])


def _reference_pairs(lidar: list[int], camera: list[int], tol: int) -> list[tuple[int, int]]:
    """Brute force: nearest camera stamp (earliest index among equal gaps... by stamp), within tol."""
    out = []
    for i, t in enumerate(lidar):
        if not camera:
            break
        gaps = [(abs(c - t), c, j) for j, c in enumerate(camera)]
        gap, _, j = min(gaps)
        if gap <= tol:
            out.append((i, j))
    return out


def test_pair_stamps_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        lidar = sorted(rng.integers(0, 2000 * MS, rng.integers(0, 30)).tolist())
        camera = rng.permutation(rng.choice(2000, rng.integers(0, 40), replace=False) * MS).tolist()
        tol = int(rng.integers(0, 100)) * MS
        assert pair_stamps(lidar, camera, tol) == _reference_pairs(lidar, camera, tol)


def test_pair_stamps_edges() -> None:
    assert pair_stamps([100], [40, 160], tolerance_ns=60) == [(0, 0)]
    assert pair_stamps([100], [40, 159], tolerance_ns=60) == [(0, 1)]
    assert pair_stamps([100], [39], tolerance_ns=60) == []
    assert pair_stamps([], [1, 2]) == [] and pair_stamps([1], []) == []
    assert pair_stamps([0, 10, 20], [11]) == [(0, 0), (1, 0), (2, 0)]
    with pytest.raises(ConfigError):
        pair_stamps([1], [1], tolerance_ns=-1)


def _write_rig_log(path: Path, fmt: str, lidar_stamps: list[int], camera_stamps: list[int]) -> None:
    """A lidar topic, a camera topic (log order = stamp order + receive delay) and one late CameraInfo."""
    profile: Profile = "ros1" if fmt == "ros1" else "ros2"
    camera = CameraModel(80, 60, K, np.zeros(5))
    events = []
    for i, stamp in enumerate(lidar_stamps):
        pts = np.full((5, 3), float(i + 1), np.float32)
        events.append((stamp + 20 * MS, "/lidar/points", "sensor_msgs/msg/PointCloud2",
                       rm.pointcloud2(stamp, "lidar", pts, profile=profile)))  # fmt: skip
    for i, stamp in enumerate(camera_stamps):
        img = np.full((60, 80), i, np.uint8)
        events.append((stamp + 5 * MS, "/cam/image_raw", "sensor_msgs/msg/Image",
                       rm.image(stamp, "cam", img, "mono8", profile)))  # fmt: skip
    info_time = camera_stamps[len(camera_stamps) // 2] + 6 * MS
    events.append((info_time, "/cam/camera_info", "sensor_msgs/msg/CameraInfo",
                   rm.camera_info(0, "cam", camera, profile)))  # fmt: skip
    events.sort(key=lambda e: e[0])
    with LogWriter(path, fmt) as writer:  # type: ignore[arg-type]
        for log_time, topic, msgtype, msg in events:
            writer.write(topic, msgtype, log_time, msg)


@pytest.mark.parametrize(("fmt", "name"), [("mcap", "rig.mcap"), ("ros1", "rig.bag"), ("ros2", "rig")])
def test_iter_pairs_on_a_written_log(tmp_path: Path, fmt: str, name: str) -> None:
    lidar = [1000 * MS + i * 100 * MS for i in range(10)]
    rng = np.random.default_rng(1)
    camera = [t + int(rng.integers(-30, 30)) * MS for t in lidar if t != lidar[4]]
    camera.insert(3, lidar[4] + 70 * MS)
    camera.sort()
    _write_rig_log(tmp_path / name, fmt, lidar, camera)
    expected = pair_stamps(lidar, camera, 50 * MS)
    stats = PairingStats()
    with open_log(tmp_path / name) as reader:
        pairs = list(iter_pairs(reader, "/lidar/points", "/cam/image_raw", stats=stats))
    assert stats == PairingStats(lidar_frames=10, camera_frames=10, matched=9, unmatched_lidar=1, yielded=9)
    assert [(int(lf.points_xyz[0, 0]) - 1, int(cf.image[0, 0])) for lf, cf in pairs] == expected
    for lf, cf in pairs:
        assert abs(lf.stamp_ns - cf.stamp_ns) <= 50 * MS
        assert cf.camera is not None and cf.camera.fx == 100.0 and cf.camera.width == 80
    with open_log(tmp_path / name) as reader:
        few = list(iter_pairs(reader, "/lidar/points", "/cam/image_raw", max_pairs=3))
        assert [int(lf.points_xyz[0, 0]) - 1 for lf, _ in few] == [expected[i][0] for i in (0, 4, 8)]
        exact = list(iter_pairs(reader, "/lidar/points", "/cam/image_raw", tolerance_ns=0))
        assert [lf.stamp_ns for lf, cf in exact] == [
            lf.stamp_ns for lf, cf in pairs if cf.stamp_ns == lf.stamp_ns
        ]


def test_chosen_pairs_carry_stamps_log_times_and_the_neighbouring_scan(tmp_path: Path) -> None:
    """``choose_pairs`` picks the pairs ``iter_pairs`` decodes, each with its messages' stamps and log times and
    the scan before it in the log (after it for the first scan)."""
    lidar = [1000 * MS + i * 100 * MS for i in range(6)]
    camera = [t + 20 * MS for t in lidar]
    _write_rig_log(tmp_path / "rig.mcap", "mcap", lidar, camera)
    with open_log(tmp_path / "rig.mcap") as reader:
        chosen = choose_pairs(reader, "/lidar/points", "/cam/image_raw", max_pairs=3)
        decoded = list(iter_pairs(reader, "/lidar/points", "/cam/image_raw", max_pairs=3))
        log_times = {raw.topic: [] for raw in reader.messages(["/lidar/points", "/cam/image_raw"])}
        for raw in reader.messages(["/lidar/points", "/cam/image_raw"]):
            log_times[raw.topic].append(raw.log_time_ns)
    assert [p.lidar_stamp_ns for p in chosen] == [lf.stamp_ns for lf, _ in decoded] == [lidar[i] for i in (0, 2, 5)]
    assert [p.camera_stamp_ns for p in chosen] == [cf.stamp_ns for _, cf in decoded]
    assert [p.neighbour_stamp_ns for p in chosen] == [lidar[1], lidar[1], lidar[4]]
    assert [p.lidar_log_ns for p in chosen] == [log_times["/lidar/points"][i] for i in (0, 2, 5)]
    assert [p.neighbour_log_ns for p in chosen] == [log_times["/lidar/points"][i] for i in (1, 1, 4)]
    assert [p.camera_log_ns for p in chosen] == [log_times["/cam/image_raw"][i] for i in (0, 2, 5)]


def test_iter_frames_and_errors(tmp_path: Path) -> None:
    lidar = [i * 100 * MS for i in range(1, 6)]
    _write_rig_log(tmp_path / "a.mcap", "mcap", lidar, lidar)
    with open_log(tmp_path / "a.mcap") as reader:
        frames = list(iter_lidar_frames(reader, "/lidar/points"))
        assert [f.stamp_ns for f in frames] == lidar
        assert [f.log_time_ns - f.stamp_ns for f in frames] == [20 * MS] * 5
        window = list(iter_lidar_frames(reader, "/lidar/points", start_ns=220 * MS, end_ns=420 * MS))
        assert [f.stamp_ns for f in window] == lidar[1:3]
        images = list(iter_camera_frames(reader, "/cam/image_raw"))
        assert len(images) == 5
        assert all(f.camera is not None and f.camera.height == 60 for f in images), (
            "first images lack the model"
        )
        with pytest.raises(InputError, match="not in the log"):
            list(iter_lidar_frames(reader, "/nope"))
        with pytest.raises(InputError, match="expected sensor_msgs/msg/PointCloud2"):
            list(iter_lidar_frames(reader, "/cam/image_raw"))
        raws = list(reader.messages(topics=["/cam/image_raw", "/lidar/points"]))
        assert sorted(raw_header_stamp_ns(r) for r in raws) == sorted(lidar + lidar)


def test_raw_header_stamp_ros1_and_big_endian_cdr() -> None:
    from fleetcal.readers.base import RawMessage

    stamp = 1_700_000_123_987_654_321
    for profile, serialization in (("ros1", "ros1"), ("ros2", "cdr")):
        store = rm.get_store(profile)  # type: ignore[arg-type]
        msg = rm.image(stamp, "c", np.zeros((2, 2), np.uint8), "mono8", profile)  # type: ignore[arg-type]
        data = bytes(
            store.serialize_ros1(msg, "sensor_msgs/msg/Image")
            if profile == "ros1"
            else store.serialize_cdr(msg, "sensor_msgs/msg/Image", little_endian=False)
        )
        raw = RawMessage("/c", "sensor_msgs/msg/Image", 0, data, serialization)  # type: ignore[arg-type]
        assert raw_header_stamp_ns(raw) == stamp


def test_camera_info_topic_for() -> None:
    topics = ["/cam/camera_info", "/cam_front/camera_info", "/a/b/camera_info"]
    assert camera_info_topic_for("/cam/image_raw", topics) == "/cam/camera_info"
    assert camera_info_topic_for("/cam_front/image/compressed", topics) == "/cam_front/camera_info"
    assert camera_info_topic_for("/a/b/c/image_rect", topics) == "/a/b/camera_info"
    assert camera_info_topic_for("/other/image_raw", topics) is None


@pytest.mark.parametrize(
    ("log", "lidar", "camera", "n_pairs"),
    [
        ("kitti_2011_09_26.mcap", "/kitti/velo/pointcloud", "/kitti/camera_color_left/image_raw", 2),
        ("nuscenes_n015.bag", "/lidar_top/points", "/cam_front/image/compressed", 1),
        ("pjlab_road_rig1", "/top_center_lidar/points", "/center_camera/image/compressed", 2),
        ("pjlab_road_rig2", "/top_center_lidar/points", "/center_camera/image_raw", 1),
    ],
)
def test_real_log_pairs(shared_data: Path, log: str, lidar: str, camera: str, n_pairs: int) -> None:
    stats = PairingStats()
    with open_log(shared_data / "logs" / log) as reader:
        pairs = list(iter_pairs(reader, lidar, camera, stats=stats))
    assert len(pairs) == n_pairs and stats.unmatched_lidar == 0
    for lf, cf in pairs:
        assert lf.n_points > 10_000
        assert cf.camera is not None and (cf.camera.width, cf.camera.height) == (cf.width, cf.height)
        assert abs(lf.stamp_ns - cf.stamp_ns) <= 50 * MS
