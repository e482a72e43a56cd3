"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` -> ``CameraFrame`` (grey or RGB).

Output images: ``mono8`` (H, W) uint8, ``mono16`` (H, W) uint16, or ``rgb8`` (H, W, 3) uint8 in RGB
order; alpha is dropped and Bayer mosaics are demosaiced with OpenCV.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import DecodeError, UnsupportedEncodingError
from fleetcal.pipeline.frames import CameraFrame
from fleetcal.readers.decode.common import stamp_to_ns

_CHANNELS = {
    "mono8": 1, "mono16": 2, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4,
    "bayer_rggb8": 1, "bayer_bggr8": 1, "bayer_gbrg8": 1, "bayer_grbg8": 1,
}  # fmt: skip
"""Bytes per pixel of each supported raw encoding."""

_ALIASES = {"8UC1": "mono8", "16UC1": "mono16", "8UC3": "bgr8", "8UC4": "bgra8"}

_BAYER_TO_RGB = {
    "bayer_rggb8": cv2.COLOR_BayerRGGB2RGB,
    "bayer_bggr8": cv2.COLOR_BayerBGGR2RGB,
    "bayer_gbrg8": cv2.COLOR_BayerGBRG2RGB,
    "bayer_grbg8": cv2.COLOR_BayerGRBG2RGB,
}
"""ROS Bayer pattern (top-left 2x2 cell) -> OpenCV conversion with the same pattern naming."""

SUPPORTED_ENCODINGS = tuple(_CHANNELS)
_COMPRESSED_FORMATS = ("jpeg", "jpg", "png")
_JPEG_SOI = b"\xff\xd8"
_JPEG_EOI = b"\xff\xd9"
_EOI_SEARCH_BYTES = 4096


def _payload(data: Any) -> NDArray[np.uint8]:
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8)
    return np.frombuffer(data, dtype=np.uint8)


def decode_image_array(
    data: Any, height: int, width: int, step: int, encoding: str, is_bigendian: bool = False
) -> tuple[NDArray[Any], str]:
    """(image, output encoding) of raw pixel bytes; rows ``step`` bytes apart (padding allowed).

    Raises:
        UnsupportedEncodingError: an encoding outside ``SUPPORTED_ENCODINGS``.
        DecodeError: an empty image (width or height 0), step shorter than a row, or data shorter than
            the image. Sizes are checked against the data before anything is allocated, so a header
            claiming 100000 x 100000 pixels over a few bytes costs nothing.
    """
    name = _ALIASES.get(encoding, encoding).lower()
    if name not in _CHANNELS:
        raise UnsupportedEncodingError(
            f"image encoding {encoding!r} is not supported (supported: {', '.join(SUPPORTED_ENCODINGS)})"
        )
    bpp = _CHANNELS[name]
    row_bytes = width * bpp
    if height <= 0 or width <= 0:
        raise DecodeError(f"image size {width}x{height} is empty")
    if step < row_bytes:
        raise DecodeError(
            f"image step {step} is shorter than a row of {width} {encoding} pixels ({row_bytes} bytes)"
        )
    buf = _payload(data)
    needed = (height - 1) * step + row_bytes
    if buf.size < needed:
        raise DecodeError(f"image data has {buf.size} bytes, {needed} needed for {width}x{height} {encoding}")
    rows = np.ndarray((height, row_bytes), dtype=np.uint8, buffer=buf, strides=(step, 1))
    if name == "mono8":
        return np.ascontiguousarray(rows), "mono8"
    if name == "mono16":
        pixels = np.ascontiguousarray(rows).view(">u2" if is_bigendian else "<u2")
        return pixels.astype(np.uint16, copy=False), "mono16"
    if name in _BAYER_TO_RGB:
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(rows), _BAYER_TO_RGB[name])), "rgb8"
    pixels = rows.reshape(height, width, bpp)
    if name == "rgb8":
        return np.ascontiguousarray(pixels), "rgb8"
    if name == "bgr8":
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels), cv2.COLOR_BGR2RGB)), "rgb8"
    if name == "rgba8":
        return np.ascontiguousarray(pixels[:, :, :3]), "rgb8"
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(pixels), cv2.COLOR_BGRA2RGB)), "rgb8"


def check_image(msg: Any) -> None:
    """Check a ``sensor_msgs/Image``'s sizes and encoding against its data without decoding a pixel.

    Raises:
        UnsupportedEncodingError, DecodeError: as ``decode_image`` would.
    """
    name = _ALIASES.get(str(msg.encoding), str(msg.encoding)).lower()
    if name not in _CHANNELS:
        raise UnsupportedEncodingError(
            f"image encoding {msg.encoding!r} is not supported (supported: {', '.join(SUPPORTED_ENCODINGS)})"
        )
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * _CHANNELS[name]
    if height <= 0 or width <= 0:
        raise DecodeError(f"image size {width}x{height} is empty")
    if step < row_bytes:
        raise DecodeError(
            f"image step {step} is shorter than a row of {width} {msg.encoding} pixels ({row_bytes} bytes)"
        )
    size = _payload(msg.data).size
    needed = (height - 1) * step + row_bytes
    if size < needed:
        raise DecodeError(f"image data has {size} bytes, {needed} needed for {width}x{height} {msg.encoding}")


def check_compressed_image(msg: Any) -> None:
    """Check a ``sensor_msgs/CompressedImage`` without decoding it: a supported format, some data, and a
    jpeg's end-of-image marker (``decode_compressed_image`` finds the rest).

    Raises:
        UnsupportedEncodingError, DecodeError: as ``decode_compressed_image`` would for these.
    """
    fmt = str(msg.format).lower()
    if fmt and not any(token in fmt for token in _COMPRESSED_FORMATS):
        raise UnsupportedEncodingError(f"compressed image format {msg.format!r} is not supported (jpeg, png)")
    buf = _payload(msg.data)
    if not buf.size:
        raise DecodeError(f"compressed image ({msg.format or 'no format'}) has no data")
    if buf[:2].tobytes() == _JPEG_SOI and _JPEG_EOI not in buf[-_EOI_SEARCH_BYTES:].tobytes():
        raise DecodeError(f"jpeg image ({buf.size} bytes) is truncated: no end-of-image marker")


def decode_image(msg: Any, topic: str, log_time_ns: int = 0) -> CameraFrame:
    """Decode a ``sensor_msgs/Image`` message object (no camera model attached).

    Raises:
        UnsupportedEncodingError: encoding other than mono8, mono16, rgb8, bgr8, rgba8, bgra8, bayer_*8.
        DecodeError: width or height 0, step shorter than a row, or data shorter than height x step.
    """
    image, encoding = decode_image_array(
        msg.data, int(msg.height), int(msg.width), int(msg.step), str(msg.encoding), bool(msg.is_bigendian)
    )
    return CameraFrame(
        stamp_ns=stamp_to_ns(msg.header.stamp),
        topic=topic,
        frame_id=str(msg.header.frame_id).lstrip("/"),
        image=image,
        encoding=encoding,
        log_time_ns=int(log_time_ns),
    )


def decode_compressed_image(msg: Any, topic: str, log_time_ns: int = 0) -> CameraFrame:
    """Decode a ``sensor_msgs/CompressedImage`` (jpeg or png, via ``cv2.imdecode``).

    Raises:
        UnsupportedEncodingError: a ``format`` naming another codec (e.g. ``h264``, ``compressedDepth``).
        DecodeError: corrupt or truncated data.
    """
    fmt = str(msg.format).lower()
    if fmt and not any(token in fmt for token in _COMPRESSED_FORMATS):
        raise UnsupportedEncodingError(f"compressed image format {msg.format!r} is not supported (jpeg, png)")
    buf = _payload(msg.data)
    if buf[:2].tobytes() == _JPEG_SOI and _JPEG_EOI not in buf[-_EOI_SEARCH_BYTES:].tobytes():
        raise DecodeError(f"jpeg image ({buf.size} bytes) is truncated: no end-of-image marker")
    image = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if image is None:
        raise DecodeError(
            f"compressed image ({msg.format or 'no format'}, {buf.size} bytes) is corrupt or truncated"
        )
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    elif image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3:
        encoding = "rgb8"
        image = image.astype(np.uint8, copy=False)
    else:
        encoding = "mono16" if image.dtype == np.uint16 else "mono8"
    return CameraFrame(
        stamp_ns=stamp_to_ns(msg.header.stamp),
        topic=topic,
        frame_id=str(msg.header.frame_id).lstrip("/"),
        image=np.asarray(image),
        encoding=encoding,
        log_time_ns=int(log_time_ns),
    )
