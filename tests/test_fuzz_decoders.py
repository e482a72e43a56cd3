"""Fuzzing: every decoder (PointCloud2, Image, CompressedImage, CameraInfo, TF) on random and
mutated messages, and the MCAP / ROS 1 / ROS 2 readers on byte-flipped and truncated copies of the
real logs in ../shared/data/logs. The property: a valid result or a ``FleetcalError`` subclass of
``InputError`` (DecodeError, TransformError, ReaderError...), never any other exception.

The example budget comes from ``FLEETCAL_FUZZ_EXAMPLES`` (default 60 per property here);
``benchmarks/fuzz_long.py`` runs the same properties for minutes.
"""

from __future__ import annotations

import copy
import os
import shutil
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.readers.decode import (
    decode_camera_info,
    decode_compressed_image,
    decode_image,
    decode_pointcloud2,
    decode_tf,
)
from fleetcal.readers.open import open_log
from fleetcal.workflows.sinks import ros_messages
from fleetcal.workflows.sinks.ros_messages import Profile
from tests import badinputs as bi
from tests.conftest import SHARED_DATA

EXAMPLES = int(os.environ.get("FLEETCAL_FUZZ_EXAMPLES", "60"))
FUZZ = settings(
    max_examples=EXAMPLES, deadline=None, derandomize=EXAMPLES <= 200, database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)  # fmt: skip
EXECUTIONS: Counter[str] = Counter()
"""Examples run per property (read by benchmarks/fuzz_long.py)."""

ALLOWED = (InputError,)
"""DecodeError, UnsupportedEncodingError, TransformError, ReaderError, TruncatedLogError are InputErrors."""

profiles: st.SearchStrategy[Profile] = st.sampled_from(["ros1", "ros2"])


def expect_valid_or_input_error(fn: Any, *args: Any) -> Any:
    """``fn(*args)``, or None when it raised an allowed error; anything else propagates."""
    try:
        return fn(*args)
    except ALLOWED:
        return None


# --- PointCloud2 --------------------------------------------------------------------------------


@st.composite
def pointcloud2_messages(draw: st.DrawFn) -> Any:
    profile = draw(profiles)
    n = draw(st.integers(0, 40))
    points = np.asarray(
        draw(st.lists(st.floats(width=32, allow_nan=True, allow_infinity=True), min_size=3 * n, max_size=3 * n)),
        dtype=np.float32,
    ).reshape(n, 3)
    channels = {"intensity": np.arange(n, dtype=np.float32)} if draw(st.booleans()) else None
    msg = ros_messages.pointcloud2(123, "lidar", points, channels, profile=profile,
                                   is_bigendian=draw(st.booleans()))  # fmt: skip
    for _ in range(draw(st.integers(0, 3))):
        what = draw(st.sampled_from(["height", "width", "point_step", "row_step", "offset", "datatype", "count",
                                     "truncate", "flip", "name"]))  # fmt: skip
        if what in ("height", "width", "point_step", "row_step"):
            setattr(msg, what, draw(st.integers(0, 2**16)))
        elif what in ("offset", "datatype", "count", "name") and msg.fields:
            field = draw(st.sampled_from(list(msg.fields)))
            if what == "name":
                field.name = draw(st.sampled_from(["", "x", "y", "z", "rgb", "time", "ring", "intensity"]))
            else:
                setattr(field, what, draw(st.integers(0, 300)))
        elif what == "truncate":
            msg.data = np.asarray(msg.data)[: draw(st.integers(0, max(len(msg.data), 0)))].copy()
        elif what == "flip" and len(msg.data):
            data = np.asarray(msg.data).copy()
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
            msg.data = data
    return msg


@FUZZ
@given(pointcloud2_messages())
def test_fuzz_pointcloud2(msg: Any) -> None:
    EXECUTIONS["pointcloud2"] += 1
    frame = expect_valid_or_input_error(decode_pointcloud2, msg, "/lidar")
    if frame is not None:
        assert isinstance(frame, LidarFrame)
        assert frame.points_xyz.ndim == 2 and frame.points_xyz.shape[1] == 3
        assert np.all(np.isfinite(frame.points_xyz))
        for values in frame.channels.values():
            assert values.shape[0] == frame.points_xyz.shape[0]
        assert frame.dropped_points >= 0


# --- Image --------------------------------------------------------------------------------------

ENCODINGS = ["mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "bayer_rggb8", "8UC1", "16UC1", "8UC3",
             "yuv422", "32FC1", "", "RGB8"]  # fmt: skip


@st.composite
def image_messages(draw: st.DrawFn) -> Any:
    profile = draw(profiles)
    types = ros_messages._types(profile)
    height, width = draw(st.integers(0, 12)), draw(st.integers(0, 12))
    step = draw(st.one_of(st.integers(0, 60), st.just(width * 3)))
    size = draw(st.one_of(st.integers(0, 800), st.just(height * step)))
    data = np.frombuffer(draw(st.binary(min_size=size, max_size=size)), dtype=np.uint8).copy()
    return types["sensor_msgs/msg/Image"](
        header=ros_messages.header(1, "cam", profile),
        height=height, width=width, encoding=draw(st.sampled_from(ENCODINGS)),
        is_bigendian=int(draw(st.booleans())), step=step, data=data,
    )  # fmt: skip


@FUZZ
@given(image_messages())
def test_fuzz_image(msg: Any) -> None:
    EXECUTIONS["image"] += 1
    frame = expect_valid_or_input_error(decode_image, msg, "/cam")
    if frame is not None:
        assert isinstance(frame, CameraFrame)
        assert frame.image.shape[:2] == (msg.height, msg.width)
        assert frame.encoding in ("mono8", "mono16", "rgb8")


# --- CompressedImage ----------------------------------------------------------------------------


def _encoded(ext: str, rng: np.random.Generator) -> bytes:
    img = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return bytes(buf)


_RNG = np.random.default_rng(0)
SEED_FILES = {"jpeg": _encoded(".jpg", _RNG), "png": _encoded(".png", _RNG)}


@st.composite
def compressed_messages(draw: st.DrawFn) -> Any:
    fmt = draw(st.sampled_from(["jpeg", "png"]))
    data = bytearray(SEED_FILES[fmt])
    mode = draw(st.sampled_from(["keep", "truncate", "flip", "random", "empty"]))
    if mode == "truncate":
        data = data[: draw(st.integers(0, len(data)))]
    elif mode == "flip":
        for _ in range(draw(st.integers(1, 16))):
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    elif mode == "random":
        data = bytearray(draw(st.binary(max_size=2000)))
    elif mode == "empty":
        data = bytearray()
    msg = ros_messages.compressed_image(1, "cam", np.zeros((2, 2), np.uint8), "png", profile=draw(profiles))
    msg.format = draw(st.sampled_from([fmt, "rgb8; jpeg compressed bgr8", "h264", "", "PNG", "compressedDepth"]))
    msg.data = np.frombuffer(bytes(data), dtype=np.uint8).copy()
    return msg


@FUZZ
@given(compressed_messages())
def test_fuzz_compressed_image(msg: Any) -> None:
    EXECUTIONS["compressed_image"] += 1
    frame = expect_valid_or_input_error(decode_compressed_image, msg, "/cam")
    if frame is not None:
        assert frame.image.ndim in (2, 3) and frame.image.size > 0


# --- CameraInfo ---------------------------------------------------------------------------------

reals = st.floats(allow_nan=True, allow_infinity=True, width=64)


@st.composite
def camera_info_messages(draw: st.DrawFn) -> Any:
    profile = draw(profiles)
    msg = ros_messages.camera_info(1, "cam", bi.CAMERA, profile)
    upper = profile == "ros1"
    k_name, d_name = ("K", "D") if upper else ("k", "d")
    if draw(st.booleans()):
        setattr(msg, k_name, np.asarray(draw(st.lists(reals, min_size=9, max_size=9)), dtype=np.float64))
    if draw(st.booleans()):
        setattr(msg, d_name, np.asarray(draw(st.lists(reals, max_size=14)), dtype=np.float64))
    msg.distortion_model = draw(st.sampled_from(["plumb_bob", "rational_polynomial", "equidistant", "fisheye",
                                                 "", "weird", "cylindrical", "PLUMB_BOB"]))  # fmt: skip
    msg.width, msg.height = draw(st.integers(0, 5000)), draw(st.integers(0, 5000))
    return msg


@FUZZ
@given(camera_info_messages())
def test_fuzz_camera_info(msg: Any) -> None:
    EXECUTIONS["camera_info"] += 1
    model = expect_valid_or_input_error(decode_camera_info, msg)
    if model is not None:
        assert isinstance(model, CameraModel)
        assert np.all(np.isfinite(model.K)) and model.K[0, 0] > 0


# --- TF -----------------------------------------------------------------------------------------


@st.composite
def tf_messages(draw: st.DrawFn) -> Any:
    profile = draw(profiles)
    n = draw(st.integers(0, 4))
    msg = ros_messages.tf_message([(1, "a", "b", np.eye(4))] * n, profile)
    msg.transforms = [copy.deepcopy(t) for t in msg.transforms]
    for stamped in msg.transforms:
        q = stamped.transform.rotation
        q.x, q.y, q.z, q.w = (draw(reals) for _ in range(4))
        t = stamped.transform.translation
        t.x, t.y, t.z = (draw(reals) for _ in range(3))
        stamped.header.frame_id = draw(st.sampled_from(["", "/", "a", "/a", "b"]))
        stamped.child_frame_id = draw(st.sampled_from(["", "b", "/b", "a"]))
    return msg


@FUZZ
@given(tf_messages())
def test_fuzz_tf(msg: Any) -> None:
    EXECUTIONS["tf"] += 1
    edges = expect_valid_or_input_error(decode_tf, msg)
    for _, parent, child, T in edges or []:
        assert parent and child
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
        assert np.all(np.isfinite(T))


# --- readers on mutated real files --------------------------------------------------------------

REAL_LOGS = ["kitti_2011_09_26.mcap", "nuscenes_n015.bag", "outdoor_scan_pair.mcap", "pjlab_road_rig1"]


def read_everything(path: Path) -> int:
    """Open, list, read and deserialise every message; the number read."""
    count = 0
    with open_log(path, allow_truncated=True) as reader:
        for raw in reader.messages():
            reader.deserialize(raw)
            count += 1
    return count


def mutated_copy(src: Path, dst_dir: Path, data: st.DataObject) -> Path:
    """Copy of a real log (file, or the .db3 of a folder) with flips or a truncation."""
    if src.is_dir():
        dst = dst_dir / src.name
        shutil.copytree(src, dst)
        target = bi.db3_of(dst)
    else:
        dst = dst_dir / src.name
        shutil.copyfile(src, dst)
        target = dst
    raw = target.read_bytes()
    mode = data.draw(st.sampled_from(["flip", "truncate", "both"]))
    if mode in ("flip", "both"):
        rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
        raw = bi.flip_bytes(raw, rng, data.draw(st.integers(1, 64)))
    if mode in ("truncate", "both"):
        raw = raw[: data.draw(st.integers(0, len(raw)))]
    target.write_bytes(raw)
    return dst


@pytest.fixture(scope="module")
def real_logs() -> list[Path]:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not present at {SHARED_DATA} (../shared/data next to the repository)")
    return [SHARED_DATA / "logs" / name for name in REAL_LOGS]


@settings(FUZZ, max_examples=max(EXAMPLES // 3, 10))
@given(data=st.data())
def test_fuzz_readers_on_mutated_real_logs(real_logs: list[Path], data: st.DataObject) -> None:
    EXECUTIONS["readers"] += 1
    src = data.draw(st.sampled_from(real_logs))
    with tempfile.TemporaryDirectory() as tmp:
        path = mutated_copy(src, Path(tmp), data)
        expect_valid_or_input_error(read_everything, path)
