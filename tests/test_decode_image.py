"""Image and CompressedImage decoding: builder round trips over every encoding, bad input, real logs."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fleetcal.pipeline.errors import DecodeError, UnsupportedEncodingError
from fleetcal.readers.decode import SUPPORTED_ENCODINGS, decode_compressed_image, decode_image
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.ros_messages import Profile

STAMP = 1_600_000_000_000_000_001
H, W = 24, 32


def _roundtrip(msg: Any, msgtype: str, profile: Profile) -> Any:
    store = rm.get_store(profile)
    if profile == "ros1":
        return store.deserialize_ros1(bytes(store.serialize_ros1(msg, msgtype)), msgtype)
    return store.deserialize_cdr(bytes(store.serialize_cdr(msg, msgtype)), msgtype)


def _rgb(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(H, W, 3), dtype=np.uint8)


def _blocks() -> np.ndarray:
    """RGB image of four flat colour quadrants (demosaicing reproduces flat areas exactly)."""
    img = np.zeros((H, W, 3), np.uint8)
    img[: H // 2, : W // 2] = (200, 30, 90)
    img[: H // 2, W // 2 :] = (10, 240, 60)
    img[H // 2 :, : W // 2] = (70, 70, 250)
    img[H // 2 :, W // 2 :] = (128, 128, 128)
    return img


@pytest.mark.parametrize("profile", ["ros2", "ros1"])
@pytest.mark.parametrize("padding", [0, 5])
@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_image_roundtrip_every_encoding(encoding: str, padding: int, profile: Profile) -> None:
    if encoding == "mono16":
        source: np.ndarray = np.random.default_rng(2).integers(0, 65536, size=(H, W), dtype=np.uint16)
    elif encoding == "mono8":
        source = _rgb()[:, :, 0].copy()
    elif encoding.startswith("bayer"):
        source = _blocks()
    else:
        source = _rgb()
    msg = rm.image(STAMP, "/cam_optical", source, encoding, profile, row_padding=padding)
    assert (
        msg.step == W * {"mono16": 2, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}.get(encoding, 1) + padding
    )
    frame = decode_image(_roundtrip(msg, "sensor_msgs/msg/Image", profile), "/cam/image_raw", log_time_ns=9)
    assert frame.stamp_ns == STAMP and frame.frame_id == "cam_optical" and frame.log_time_ns == 9
    assert (frame.width, frame.height) == (W, H)
    assert frame.image.flags.c_contiguous
    if encoding.startswith("bayer"):
        assert frame.encoding == "rgb8" and frame.image.shape == (H, W, 3)
        inner = np.ones((H, W), bool)
        inner[[0, H // 2 - 1, H // 2, H - 1], :] = False
        inner[:, [0, W // 2 - 1, W // 2, W - 1]] = False
        np.testing.assert_array_equal(frame.image[inner], source[inner])
    else:
        assert frame.encoding == {"mono8": "mono8", "mono16": "mono16"}.get(encoding, "rgb8")
        assert frame.image.dtype == source.dtype
        np.testing.assert_array_equal(frame.image, source)


def test_bayer_patterns_are_distinguished() -> None:
    """Decoding a mosaic with the wrong pattern gives wrong colours."""
    source = _blocks()
    msg = rm.image(STAMP, "c", source, "bayer_rggb8")
    wrong = decode_image(dataclasses.replace(msg, encoding="bayer_bggr8"), "/c").image
    assert np.abs(wrong[4, 4].astype(int) - source[4, 4].astype(int)).max() > 50


def test_mono16_big_endian() -> None:
    source = np.arange(H * W, dtype=np.uint16).reshape(H, W) * 37
    msg = rm.image(STAMP, "c", source, "mono16", is_bigendian=True)
    assert bytes(msg.data[:4]) == source[0, :2].astype(">u2").tobytes()
    frame = decode_image(msg, "/c")
    assert frame.image.dtype == np.uint16 and frame.image.dtype.isnative
    np.testing.assert_array_equal(frame.image, source)


def test_bad_images_raise() -> None:
    msg = rm.image(STAMP, "c", _rgb(), "rgb8")
    with pytest.raises(DecodeError, match="step 90 is shorter"):
        decode_image(dataclasses.replace(msg, step=90), "/c")
    with pytest.raises(DecodeError, match="data has 2303 bytes"):
        decode_image(dataclasses.replace(msg, data=msg.data[:-1]), "/c")
    for encoding in ("yuv422", "32FC1", "bayer_rggb16"):
        with pytest.raises(UnsupportedEncodingError, match=encoding):
            decode_image(dataclasses.replace(msg, encoding=encoding), "/c")
    for height, width in ((0, 0), (0, 32), (24, 0)):
        with pytest.raises(DecodeError, match=f"image size {width}x{height} is empty"):
            decode_image(dataclasses.replace(msg, height=height, width=width, step=width * 3), "/c")


def test_huge_claimed_image_is_rejected_without_allocating() -> None:
    """100000 x 100000 rgb8 (30 GB) claimed over 16 bytes: rejected from the sizes alone."""
    import tracemalloc

    msg = rm.image(STAMP, "c", _rgb(), "rgb8")
    huge = dataclasses.replace(msg, height=100_000, width=100_000, step=300_000, data=np.zeros(16, np.uint8))
    tracemalloc.start()
    try:
        with pytest.raises(DecodeError, match="image data has 16 bytes, 30000000000 needed for 100000x100000"):
            decode_image(huge, "/c")
        _, peak_bytes = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak_bytes < 1_000_000


@pytest.mark.parametrize("profile", ["ros2", "ros1"])
@pytest.mark.parametrize("kind", ["rgb", "mono8", "mono16"])
def test_png_roundtrip_is_exact(kind: str, profile: Profile) -> None:
    source = {
        "rgb": _rgb(3),
        "mono8": _rgb(4)[:, :, 1].copy(),
        "mono16": np.random.default_rng(5).integers(0, 65536, (H, W), dtype=np.uint16),
    }[kind]
    msg = rm.compressed_image(STAMP, "c", source, fmt="png", profile=profile)
    frame = decode_compressed_image(
        _roundtrip(msg, "sensor_msgs/msg/CompressedImage", profile), "/c/compressed"
    )
    assert frame.encoding == {"rgb": "rgb8"}.get(kind, kind)
    np.testing.assert_array_equal(frame.image, source)


def test_jpeg_roundtrip_keeps_colour_order() -> None:
    source = _blocks()
    msg = rm.compressed_image(STAMP, "c", source, fmt="jpeg", quality=95)
    assert bytes(msg.data[:2]) == b"\xff\xd8"
    frame = decode_compressed_image(msg, "/c")
    assert frame.encoding == "rgb8" and frame.image.shape == (H, W, 3)
    error = np.abs(frame.image.astype(int) - source.astype(int))
    assert float(error.mean()) < 8.0
    assert np.abs(frame.image[4, 4].astype(int) - np.array([200, 30, 90])).max() <= 8


def test_bad_compressed_images_raise() -> None:
    jpeg = rm.compressed_image(STAMP, "c", _rgb(), fmt="jpeg")
    png = rm.compressed_image(STAMP, "c", _rgb(), fmt="png")
    with pytest.raises(DecodeError, match="truncated"):
        decode_compressed_image(dataclasses.replace(jpeg, data=jpeg.data[: jpeg.data.size // 2]), "/c")
    with pytest.raises(DecodeError, match="corrupt or truncated"):
        decode_compressed_image(dataclasses.replace(png, data=png.data[: png.data.size // 2]), "/c")
    noise = np.random.default_rng(0).integers(0, 256, 500, dtype=np.uint8)
    with pytest.raises(DecodeError, match="corrupt"):
        decode_compressed_image(dataclasses.replace(jpeg, data=noise), "/c")
    with pytest.raises(DecodeError, match="corrupt"):
        decode_compressed_image(dataclasses.replace(jpeg, data=np.zeros(0, np.uint8)), "/c")
    with pytest.raises(UnsupportedEncodingError, match="h264"):
        decode_compressed_image(dataclasses.replace(jpeg, format="h264"), "/c")
    frame = decode_compressed_image(dataclasses.replace(jpeg, format="rgb8; jpeg compressed bgr8"), "/c")
    assert frame.image.shape == (H, W, 3)


@pytest.mark.parametrize(
    ("log", "msgtype", "size", "count"),
    [
        ("kitti_2011_09_26.mcap", "sensor_msgs/msg/Image", (1242, 375), 2),
        ("nuscenes_n015.bag", "sensor_msgs/msg/CompressedImage", (1600, 900), 6),
        ("pjlab_road_rig1", "sensor_msgs/msg/CompressedImage", (1920, 1200), 2),
        ("pjlab_road_rig2", "sensor_msgs/msg/Image", (1920, 1200), 1),
    ],
)
def test_real_log_images(
    shared_data: Path, log: str, msgtype: str, size: tuple[int, int], count: int
) -> None:
    from fleetcal.readers.open import open_log

    decode = decode_image if msgtype.endswith("/Image") else decode_compressed_image
    with open_log(shared_data / "logs" / log) as reader:
        topics = [t for t, info in reader.topics.items() if info.msgtype == msgtype]
        frames = [decode(reader.deserialize(raw), raw.topic) for raw in reader.messages(topics=topics)]
    assert len(frames) == count
    for frame in frames:
        assert (frame.width, frame.height) == size
        assert frame.encoding == "rgb8" and frame.image.dtype == np.uint8
        assert 20 < float(frame.image.mean()) < 235
        assert float(frame.image.std()) > 10
