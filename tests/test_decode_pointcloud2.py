"""PointCloud2 decoding: builder round trips over every layout, both serialisations, bad input, real logs."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetcal.pipeline.errors import DecodeError
from fleetcal.readers.decode import decode_pointcloud2
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.ros_messages import Profile

TYPE = "sensor_msgs/msg/PointCloud2"
STAMP = 1_700_000_000_123_456_789


def _roundtrip(msg: Any, profile: Profile) -> Any:
    """Serialise with the profile's typestore and deserialise again (what a reader hands over)."""
    store = rm.get_store(profile)
    if profile == "ros1":
        return store.deserialize_ros1(bytes(store.serialize_ros1(msg, TYPE)), TYPE)
    return store.deserialize_cdr(bytes(store.serialize_cdr(msg, TYPE)), TYPE)


def _points(n: int, seed: int = 0, dtype: Any = np.float32) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-50, 50, size=(n, 3)).astype(dtype)


def _layouts() -> dict[str, dict[str, Any]]:
    rng = np.random.default_rng(1)
    n = 97
    every_type = {
        f"c_{np.dtype(dt).name}": rng.integers(0, 100, n).astype(dt)
        for dt in (np.int8, np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.float32, np.float64)
    }
    return {
        "xyz": {"points": _points(n), "channels": {}},
        "xyz_intensity": {
            "points": _points(n),
            "channels": {"intensity": rng.uniform(0, 255, n).astype(np.float32)},
        },
        "padded_32_byte": {
            "points": _points(n),
            "channels": {
                "intensity": rng.uniform(0, 1, n).astype(np.float32),
                "ring": rng.integers(0, 32, n).astype(np.uint16),
            },
            "point_step": 32,
        },
        "float64_xyz_and_time": {
            "points": _points(n, dtype=np.float64),
            "channels": {"time": np.linspace(0, 0.1, n)},
        },
        "rgb_packed": {
            "points": _points(n),
            "channels": {c: rng.integers(0, 256, n).astype(np.uint8) for c in "rgb"},
        },
        "big_endian": {
            "points": _points(n),
            "channels": {
                "intensity": rng.uniform(0, 1, n).astype(np.float32),
                "ring": np.arange(n, dtype=np.uint16),
            },
            "is_bigendian": True,
        },
        "every_datatype": {"points": _points(n), "channels": every_type},
        "every_datatype_big_endian": {"points": _points(n), "channels": every_type, "is_bigendian": True},
    }


LAYOUTS = _layouts()


@pytest.mark.parametrize("profile", ["ros2", "ros1"])
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_builder_roundtrip_every_layout(layout: str, profile: Profile) -> None:
    spec = LAYOUTS[layout]
    points, channels = spec["points"], spec["channels"]
    msg = rm.pointcloud2(
        STAMP,
        "/velodyne",
        points,
        channels,
        profile=profile,
        point_step=spec.get("point_step"),
        is_bigendian=spec.get("is_bigendian", False),
    )
    if "point_step" in spec:
        assert msg.point_step == spec["point_step"]
    frame = decode_pointcloud2(_roundtrip(msg, profile), "/points", log_time_ns=42)
    assert frame.stamp_ns == STAMP and frame.frame_id == "velodyne" and frame.topic == "/points"
    assert frame.log_time_ns == 42 and frame.dropped_points == 0 and frame.organized_shape is None
    assert frame.points_xyz.dtype == points.dtype
    np.testing.assert_array_equal(frame.points_xyz, points)
    for name, values in channels.items():
        got = frame.channels[name]
        assert got.dtype.isnative
        np.testing.assert_array_equal(got, values)
        if name in "rgb":
            assert got.dtype == np.uint8
    if "time" in channels:
        assert frame.channels["time"].dtype == np.float64
    if layout == "rgb_packed":
        assert "rgb" not in frame.channels
    if "intensity" in channels:
        assert frame.channels["intensity"].dtype == np.float32
    if "ring" in channels:
        assert frame.channels["ring"].dtype == np.uint16


@pytest.mark.parametrize("profile", ["ros2", "ros1"])
def test_organized_cloud_drops_nan_and_zero_and_keeps_grid_index(profile: Profile) -> None:
    h, w = 4, 6
    pts = _points(h * w, seed=3)
    intensity = np.arange(h * w, dtype=np.float32)
    pts[[1, 7, 20]] = np.nan
    pts[5] = 0.0
    pts[11, 2] = np.inf
    msg = rm.pointcloud2(STAMP, "os", pts, {"intensity": intensity}, organized_shape=(h, w), profile=profile)
    assert msg.is_dense is False
    frame = decode_pointcloud2(_roundtrip(msg, profile), "/os")
    dropped = [1, 5, 7, 11, 20]
    kept = np.setdiff1d(np.arange(h * w), dropped)
    assert frame.organized_shape == (h, w)
    assert frame.dropped_points == len(dropped) and frame.n_points == h * w - len(dropped)
    assert frame.organized_index is not None
    np.testing.assert_array_equal(frame.organized_index, kept)
    np.testing.assert_array_equal(frame.points_xyz, pts[kept])
    np.testing.assert_array_equal(frame.channels["intensity"], intensity[kept])


def test_row_step_padding_is_skipped() -> None:
    h, w, step = 3, 5, 16
    pts = _points(h * w, seed=4)
    msg = rm.pointcloud2(
        STAMP, "os", pts, {"ring": np.arange(h * w, dtype=np.uint16)}, organized_shape=(h, w)
    )
    rows = msg.data.reshape(h, w * step)
    padded = np.concatenate([rows, np.full((h, 8), 0xFF, dtype=np.uint8)], axis=1).reshape(-1)
    msg = dataclasses.replace(msg, data=padded, row_step=w * step + 8)
    frame = decode_pointcloud2(msg, "/os")
    np.testing.assert_array_equal(frame.points_xyz, pts)
    np.testing.assert_array_equal(frame.channels["ring"], np.arange(h * w))


def test_decode_does_not_copy_payload_before_selecting() -> None:
    """The x column is read through a view of the message buffer: mutating the buffer changes the result."""
    pts = _points(10)
    msg = rm.pointcloud2(STAMP, "l", pts)
    data = msg.data
    data[0:4] = np.frombuffer(np.float32(7.5).tobytes(), dtype=np.uint8)
    frame = decode_pointcloud2(msg, "/l")
    assert frame.points_xyz[0, 0] == np.float32(7.5)


def _fields(msg: Any, **changes: Any) -> Any:
    return dataclasses.replace(msg, **changes)


def _field(name: str, offset: int, datatype: int, count: int = 1) -> Any:
    return rm.get_store("ros2").types["sensor_msgs/msg/PointField"](
        name=name, offset=offset, datatype=datatype, count=count
    )


def test_count_greater_than_one_becomes_2d_channel() -> None:
    n = 7
    record = np.dtype({"names": ["x", "y", "z", "feat"], "formats": ["<f4", "<f4", "<f4", ("<u2", (3,))],
                       "offsets": [0, 4, 8, 12], "itemsize": 20})  # fmt: skip
    table = np.zeros(n, dtype=record)
    table["x"], table["y"], table["z"] = 1.0, 2.0, 3.0
    table["feat"] = np.arange(3 * n).reshape(n, 3)
    base = rm.pointcloud2(STAMP, "l", np.ones((n, 3), np.float32))
    msg = _fields(base, fields=[*base.fields, _field("feat", 12, 4, 3)], point_step=20, row_step=20 * n,
                  data=table.view(np.uint8).reshape(-1))  # fmt: skip
    frame = decode_pointcloud2(msg, "/l")
    assert frame.channels["feat"].shape == (n, 3)
    np.testing.assert_array_equal(frame.channels["feat"], np.arange(3 * n).reshape(n, 3))
    bad = _fields(base, fields=[_field("x", 0, 7, 2), *base.fields[1:]])
    with pytest.raises(DecodeError, match="x, y, z must have count 1"):
        decode_pointcloud2(bad, "/l")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"point_step": 8}, "past the end of a 8-byte point"),
        ({"fields_extra": ("i", 12, 7)}, "field 'i' .* past the end"),
        ({"data_cut": 1}, "data has .* bytes"),
        ({"fields_extra": ("q", 0, 9)}, "unknown datatype code 9"),
        ({"fields_extra": ("q", 0, 0)}, "unknown datatype code 0"),
        ({"drop_field": "z"}, "no z field"),
        ({"row_step": 10, "height": 2, "width": 5}, "row_step 10 is shorter"),
        ({"duplicate": "x"}, "two fields named 'x'"),
    ],
)
def test_bad_clouds_raise_decode_error(change: dict[str, Any], match: str) -> None:
    msg = rm.pointcloud2(STAMP, "l", _points(10))
    fields = list(msg.fields)
    if "fields_extra" in change:
        name, offset, code = change.pop("fields_extra")
        fields.append(_field(name, offset, code))
    if "drop_field" in change:
        dropped = change.pop("drop_field")
        fields = [f for f in fields if f.name != dropped]
    if "duplicate" in change:
        fields.append(_field(change.pop("duplicate"), 0, 7))
    data = msg.data
    if "data_cut" in change:
        data = data[: -change.pop("data_cut")]
    with pytest.raises(DecodeError, match=match):
        decode_pointcloud2(_fields(msg, fields=fields, data=data, **change), "/l")


def test_empty_cloud_is_valid() -> None:
    for h, w in ((0, 0), (1, 0), (0, 16)):
        empty = rm.pointcloud2(
            STAMP, "l", np.zeros((0, 3), np.float32), {"intensity": np.zeros(0, np.float32)}
        )
        msg = _fields(empty, height=h, width=w)
        frame = decode_pointcloud2(msg, "/l")
        assert frame.n_points == 0 and frame.points_xyz.shape == (0, 3) and frame.dropped_points == 0
        assert frame.channels["intensity"].shape == (0,)


@pytest.mark.parametrize(
    ("name", "values", "expected_s"),
    [
        ("time", np.array([0.0, 0.05, 0.1], np.float32), [0.0, 0.05, 0.1]),
        ("t", np.array([0, 50_000_000, 100_000_000], np.uint32), [0.0, 0.05, 0.1]),
        ("timestamp", STAMP * 1e-9 + np.array([-0.1, 0.0, 0.02]), [-0.1, 0.0, 0.02]),
        ("timestamp", (STAMP + np.array([-(10**8), 0, 2 * 10**7])).astype(np.float64), [-0.1, 0.0, 0.02]),
        ("offset_time", np.array([0, 1000, 2000], np.uint32), [0.0, 1e-6, 2e-6]),
    ],
)
def test_time_channel_is_seconds_relative_to_stamp(
    name: str, values: np.ndarray, expected_s: list[float]
) -> None:
    msg = rm.pointcloud2(STAMP, "l", _points(3), {name: values})
    frame = decode_pointcloud2(_roundtrip(msg, "ros2"), "/l")
    assert frame.channels["time"].dtype == np.float64
    np.testing.assert_allclose(
        np.asarray(frame.channels["time"], dtype=np.float64), np.array(expected_s), atol=2e-6
    )
    np.testing.assert_array_equal(frame.channels[name], values.astype(frame.channels[name].dtype))



def test_relative_time_from_another_field_is_its_own_array() -> None:
    """float64 seconds in ``t`` need no change; ``time`` must still not alias the ``t`` channel."""
    msg = rm.pointcloud2(STAMP, "l", _points(3), {"t": np.array([0.0, 0.05, 0.1])})
    frame = decode_pointcloud2(_roundtrip(msg, "ros2"), "/l")
    np.testing.assert_array_equal(frame.channels["time"], [0.0, 0.05, 0.1])
    assert not np.shares_memory(frame.channels["time"], frame.channels["t"])


@pytest.mark.parametrize(("fmt", "filename"), [("mcap", "log.mcap"), ("ros1", "log.bag")])
def test_reader_deserialize_keeps_pointcloud_payload_zero_copy(tmp_path: Path, fmt: str, filename: str) -> None:
    """``deserialize`` hands PointCloud2 ``data`` over as a view of the raw message bytes (cdr and ros1)."""
    from fleetcal.readers.open import open_log
    from fleetcal.workflows.sinks.log_writer import LogWriter

    intensity = np.arange(1000, dtype=np.float32)
    profile: Profile = "ros1" if fmt == "ros1" else "ros2"
    msg = rm.pointcloud2(STAMP, "l", _points(1000), {"intensity": intensity}, profile=profile)
    with LogWriter(tmp_path / filename, fmt, compression=None) as writer:  # type: ignore[arg-type]
        writer.write("/l", TYPE, STAMP, msg)
    with open_log(tmp_path / filename) as reader:
        raw = next(iter(reader.messages(topics=["/l"])))
        decoded = reader.deserialize(raw)
    assert np.shares_memory(np.frombuffer(raw.data, np.uint8), decoded.data)
    frame = decode_pointcloud2(decoded, "/l")
    np.testing.assert_array_equal(frame.points_xyz, _points(1000))
    np.testing.assert_array_equal(frame.channels["intensity"], intensity)

def _first_cloud(path: Path, topic: str | None = None) -> tuple[Any, str]:
    from fleetcal.readers.open import open_log

    with open_log(path) as reader:
        topic = topic or next(t for t, info in reader.topics.items() if info.msgtype.endswith("PointCloud2"))
        raw = next(iter(reader.messages(topics=[topic])))
        return reader.deserialize(raw), topic


@pytest.mark.parametrize(
    ("log", "min_points", "channels"),
    [
        ("kitti_2011_09_26.mcap", 100_000, {"intensity"}),
        ("nuscenes_n015.bag", 20_000, {"intensity", "ring"}),
        ("pjlab_road_rig1", 50_000, {"intensity", "ring", "timestamp", "time"}),
        ("outdoor_scan_pair.mcap", 50_000, {"intensity"}),
        ("rgbd_fragment.mcap", 60_000, {"r", "g", "b"}),
    ],
)
def test_real_logs_decode(shared_data: Path, log: str, min_points: int, channels: set[str]) -> None:
    msg, topic = _first_cloud(shared_data / "logs" / log)
    frame = decode_pointcloud2(msg, topic)
    assert frame.n_points + frame.dropped_points == msg.width * msg.height
    assert frame.n_points >= min_points
    assert channels <= set(frame.channels)
    assert np.all(np.isfinite(frame.points_xyz))
    assert not np.any(np.all(frame.points_xyz == 0, axis=1))
    ranges = np.linalg.norm(frame.points_xyz, axis=1)
    assert 1.0 < float(np.median(ranges)) < 100.0
    if "ring" in channels:
        assert frame.channels["ring"].max() < 128
    if "r" in channels:
        colours = np.stack([frame.channels[c] for c in "rgb"], axis=1)
        assert len(np.unique(colours, axis=0)) > 100
    if "time" in channels:
        assert float(np.ptp(frame.channels["time"])) < 0.2


@pytest.mark.parametrize("organized", [False, True])
def test_numba_kernel_matches_numpy_reference(organized: bool) -> None:
    """The numba x, y, z gather agrees with ``xyz_numpy`` on random, NaN, zero, inf, far (1e30 m, 1030 m
    beyond the 1000 m default range) and row-padded input, at the default and a 1 m range."""
    from fleetcal.readers.decode.pointcloud2 import _xyz_kernel, xyz_numpy

    rng = np.random.default_rng(7)
    h, w = (8, 50) if organized else (1, 400)
    pts = rng.normal(size=(h * w, 3)).astype(np.float32)
    bad = rng.choice(h * w, 60, replace=False)
    pts[bad[:20], rng.integers(0, 3, 20)] = np.nan
    pts[bad[20:40]] = 0.0
    pts[bad[40:], 1] = -np.inf
    pts[bad[40:45]] = [0.0, 0.0, 1e-30]
    good = np.setdiff1d(np.arange(h * w), bad)
    pts[good[:5], 0] = 1e30
    pts[good[5:10]] = [900.0, 500.0, 0.0]
    pts[good[10:15]] = [600.0, 0.0, 0.0]
    msg = rm.pointcloud2(STAMP, "l", pts, {"ring": np.arange(h * w, dtype=np.uint16)}, point_step=24,
                         organized_shape=(h, w) if organized else None)  # fmt: skip
    if organized:
        padded = np.concatenate([msg.data.reshape(h, -1), np.zeros((h, 8), np.uint8)], axis=1).reshape(-1)
        msg = dataclasses.replace(msg, data=padded, row_step=w * 24 + 8)
    fast = _xyz_kernel(msg, msg.data, h, w, msg.row_step, 24)
    assert fast is not None
    grid = np.ndarray((h, w, 6), np.float32, buffer=msg.data, strides=(msg.row_step, 24, 4)).reshape(h * w, 6)
    ref_points, ref_valid = xyz_numpy(grid[:, 0], grid[:, 1], grid[:, 2])
    np.testing.assert_array_equal(fast[1], ref_valid)
    np.testing.assert_array_equal(fast[0], ref_points)
    assert int(ref_valid.sum()) == h * w - 65
    frame = decode_pointcloud2(msg, "/l")
    np.testing.assert_array_equal(frame.channels["ring"], np.flatnonzero(ref_valid))
    assert frame.dropped_points == 65
    near = _xyz_kernel(msg, msg.data, h, w, msg.row_step, 24, max_range_m=1.0)
    ref_near_points, ref_near_valid = xyz_numpy(grid[:, 0], grid[:, 1], grid[:, 2], max_range_m=1.0)
    assert near is not None
    np.testing.assert_array_equal(near[1], ref_near_valid)
    np.testing.assert_array_equal(near[0], ref_near_points)
    in_range = np.linalg.norm(grid[:, :3].astype(np.float64), axis=1) <= 1.0
    assert int(ref_near_valid.sum()) == int((in_range & ref_valid).sum()) > 0
