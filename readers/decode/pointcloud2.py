"""``sensor_msgs/PointCloud2`` -> ``LidarFrame``, zero-copy over the payload.

The payload is viewed (``np.ndarray`` over the message buffer, no copy) through a structured dtype
built from the PointFields (offsets, ``itemsize = point_step``, byte order from ``is_bigendian``,
rows ``row_step`` apart); only the kept points' fields are copied out. x, y, z of the usual layout
(float32, native order, 4-byte aligned) are gathered and checked in one numba pass
(``pointcloud2_kernels``); other layouts use ``xyz_numpy``, which is also the tests' reference.

Channels: every field other than x, y, z, by its name, in native byte order. Special cases:
``intensity`` -> float32, ``ring`` -> uint16; a PCL-packed ``rgb``/``rgba`` field (float32 or
uint32 holding 0x00RRGGBB bits) -> ``r``, ``g``, ``b`` uint8 (the packed field is not kept);
per-point time (the first of ``time``, ``t``, ``timestamp``, ``offset_time``) -> ``time`` float64
seconds relative to the header stamp (integers are nanoseconds; values above 1e15 ns or 1e6 s are
taken as absolute and the stamp is subtracted); the original field stays under its own name.
Fields with ``count > 1`` become (N, count) channels (x, y, z must have count 1); ``count == 0``
is read as 1. Unnamed fields are padding.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.config import IoConfig
from fleetcal.pipeline.errors import DecodeError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.readers.decode.common import stamp_to_ns
from fleetcal.readers.decode.pointcloud2_kernels import gather_xyz_f32

POINTFIELD_DTYPES: dict[int, np.dtype[Any]] = {
    1: np.dtype(np.int8),
    2: np.dtype(np.uint8),
    3: np.dtype(np.int16),
    4: np.dtype(np.uint16),
    5: np.dtype(np.int32),
    6: np.dtype(np.uint32),
    7: np.dtype(np.float32),
    8: np.dtype(np.float64),
}
"""PointField datatype code (1..8) -> numpy dtype."""

MAX_RANGE_M: float = IoConfig.max_range_m
"""Default largest range of a kept point, metres (``io.max_range_m``; why this value: ``IoConfig``)."""

TIME_FIELDS = ("time", "t", "timestamp", "offset_time")
"""Per-point time fields, in order of preference, normalised into the ``time`` channel."""

_PACKED_COLOUR = ("rgb", "rgba")
_ABSOLUTE_NS = 1e15
_ABSOLUTE_S = 1e6
_TIME_PROBE_SAMPLES = 1024


def _record_dtype(msg: Any, point_step: int, big_endian: bool) -> tuple[np.dtype[Any], dict[str, int]]:
    """Structured dtype of one point and the count of each named field. Raises DecodeError."""
    order: Literal["<", ">"] = ">" if big_endian else "<"
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    counts: dict[str, int] = {}
    for field in msg.fields:
        name = str(field.name)
        code = int(field.datatype)
        if code not in POINTFIELD_DTYPES:
            raise DecodeError(f"PointCloud2 field {name!r} has unknown datatype code {code} (expected 1..8)")
        if not name:
            continue
        if name in counts:
            raise DecodeError(f"PointCloud2 has two fields named {name!r}")
        count = max(int(field.count), 1)
        offset = int(field.offset)
        base = POINTFIELD_DTYPES[code]
        if name in _PACKED_COLOUR and code in (6, 7):
            base = np.dtype(np.uint32)
        end = offset + base.itemsize * count
        if offset < 0 or end > point_step:
            raise DecodeError(
                f"PointCloud2 field {name!r} (bytes {offset}..{end}) lies past the end of a"
                f" {point_step}-byte point (point_step smaller than its fields)"
            )
        names.append(name)
        formats.append(base.newbyteorder(order) if count == 1 else (base.newbyteorder(order), (count,)))
        offsets.append(offset)
        counts[name] = count
    missing = [axis for axis in "xyz" if axis not in counts]
    if missing:
        raise DecodeError(
            f"PointCloud2 has no {', '.join(missing)} field (fields: {', '.join(counts) or 'none'})"
        )
    bad = [axis for axis in "xyz" if counts[axis] != 1]
    if bad:
        raise DecodeError(f"PointCloud2 field {bad[0]} has count {counts[bad[0]]}; x, y, z must have count 1")
    record = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})
    return record, counts


def _payload(data: Any) -> NDArray[np.uint8]:
    """The message payload as a flat uint8 array without copying."""
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8)
    return np.frombuffer(data, dtype=np.uint8)


def _time_channel(values: NDArray[Any], stamp_ns: int, copy: bool = True) -> NDArray[np.float64]:
    """Per-point time as float64 seconds relative to the header stamp.

    ``copy=False`` lets float64 seconds that need no change come back as ``values`` itself (for a
    caller that replaces ``values`` with the result).
    """
    if values.size == 0:
        return np.zeros(values.shape, dtype=np.float64)
    sample = values[:: max(1, values.size // _TIME_PROBE_SAMPLES)]
    if values.dtype.kind == "f":
        seconds = values.astype(np.float64, copy=copy)
        magnitudes = np.abs(sample.astype(np.float64))
        magnitudes = magnitudes[~np.isnan(magnitudes)]
        probe = float(np.median(magnitudes)) if magnitudes.size else 0.0
        if probe > _ABSOLUTE_NS:
            return np.asarray((seconds - stamp_ns) * 1e-9)
        if probe > _ABSOLUTE_S:
            return np.asarray(seconds - stamp_ns * 1e-9)
        return seconds
    ints = values.astype(np.int64)
    if float(np.median(np.abs(sample.astype(np.int64)))) > _ABSOLUTE_NS:
        ints = ints - stamp_ns
    return np.asarray(ints * 1e-9)


def xyz_numpy(
    x: NDArray[Any], y: NDArray[Any], z: NDArray[Any], max_range_m: float = MAX_RANGE_M
) -> tuple[NDArray[np.floating], NDArray[np.bool_]]:
    """(points (N_valid, 3), valid (N,)) from x, y, z columns (reference path): valid points are finite,
    within ``max_range_m`` of the origin (x*x + y*y + z*z in float64) and not all zero."""
    xyz_dtype = np.result_type(x.dtype, y.dtype, z.dtype).newbyteorder("=")
    if xyz_dtype.kind != "f":
        xyz_dtype = np.dtype(np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        range2 = np.square(x, dtype=np.float64)
        range2 += np.square(y, dtype=np.float64)
        range2 += np.square(z, dtype=np.float64)
        valid = range2 <= max_range_m * max_range_m
        del range2
        nonzero = x != 0
        nonzero |= y != 0
        nonzero |= z != 0
        valid &= nonzero
    n_valid = int(np.count_nonzero(valid))
    keep: NDArray[np.bool_] | slice = slice(None) if n_valid == valid.size else valid
    points_xyz = np.empty((n_valid, 3), dtype=xyz_dtype)
    points_xyz[:, 0] = x[keep]
    points_xyz[:, 1] = y[keep]
    points_xyz[:, 2] = z[keep]
    return points_xyz, valid


def _xyz_kernel(
    msg: Any, data: NDArray[np.uint8], height: int, width: int, row_step: int, point_step: int,
    max_range_m: float = MAX_RANGE_M,
) -> tuple[NDArray[np.floating], NDArray[np.bool_]] | None:
    """The numba path for the usual layout (little-endian float32 x, y, z on 4-byte boundaries), else None."""
    offsets = {str(f.name): (int(f.offset), int(f.datatype)) for f in msg.fields if f.name in ("x", "y", "z")}
    if (
        bool(msg.is_bigendian) != (sys.byteorder == "big")
        or any(code != 7 or offset % 4 for offset, code in offsets.values())
        or point_step % 4
        or row_step % 4
        or not data.flags.c_contiguous
        or data.ctypes.data % 4
    ):
        return None
    needed = (height - 1) * row_step + width * point_step
    words = data[:needed].view(np.float32)
    n = height * width
    points = np.empty((n, 3), dtype=np.float32)
    valid = np.empty(n, dtype=np.bool_)
    kept = gather_xyz_f32(
        words, height, width, row_step // 4, point_step // 4,
        offsets["x"][0] // 4, offsets["y"][0] // 4, offsets["z"][0] // 4, points, valid, float(max_range_m),
    )  # fmt: skip
    return (points if kept == n else points[:kept].copy()), valid


@dataclass(frozen=True)
class CloudLayout:
    """The checked layout of a PointCloud2 message (``check_pointcloud2``)."""

    height: int
    width: int
    point_step: int
    row_step: int
    record: np.dtype[Any]
    """Structured dtype of one point."""
    counts: dict[str, int]
    """Count of each named field."""
    data: NDArray[np.uint8]
    """The payload, not copied."""


def check_pointcloud2(msg: Any) -> CloudLayout:
    """The layout of a PointCloud2 message, checked against its payload without reading any point.

    Raises:
        DecodeError: unknown datatype code, a field past the end of a point, missing x/y/z, a
            row_step shorter than a row, or data shorter than height * width * point_step.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    n = height * width
    record, counts = _record_dtype(msg, max(point_step, 0), bool(msg.is_bigendian))
    if height == 1 or n == 0:
        row_step = max(row_step, width * point_step)
    if n and point_step <= 0:
        raise DecodeError(f"PointCloud2 point_step is {point_step}")
    if row_step < width * point_step:
        raise DecodeError(
            f"PointCloud2 row_step {row_step} is shorter than width {width} x point_step {point_step}"
        )
    data = _payload(msg.data)
    needed = (height - 1) * row_step + width * point_step if n else 0
    if data.size < needed:
        raise DecodeError(
            f"PointCloud2 data has {data.size} bytes, {needed} needed for {height}x{width}"
            f" points of {point_step} bytes"
        )
    return CloudLayout(height, width, point_step, row_step, record, counts, data)


def decode_pointcloud2(msg: Any, topic: str, log_time_ns: int = 0, max_range_m: float = MAX_RANGE_M) -> LidarFrame:
    """Decode a PointCloud2 message object (rosbags, ROS 1 or ROS 2) into a LidarFrame.

    NaN/infinite points, points farther than ``max_range_m`` (metres, ``io.max_range_m``: corrupt values
    such as 1e30) and all-zero (x = y = z = 0, "no return") points are dropped and counted in
    ``dropped_points``. Organised clouds (height > 1) keep ``organized_shape`` (height, width) and
    ``organized_index`` (flat grid index of each kept point). height or width 0 gives an empty frame.

    Raises:
        DecodeError: unknown datatype code, a field past the end of a point, missing x/y/z, a
            row_step shorter than a row, or data shorter than height * width * point_step.
    """
    stamp_ns = stamp_to_ns(msg.header.stamp)
    frame_id = str(msg.header.frame_id).lstrip("/")
    layout = check_pointcloud2(msg)
    height, width, point_step, row_step = layout.height, layout.width, layout.point_step, layout.row_step
    record, counts, data = layout.record, layout.counts, layout.data
    n = height * width
    if n:
        grid = np.ndarray((height, width), dtype=record, buffer=data, strides=(row_step, point_step))
    else:
        grid = np.zeros((0, 0), dtype=record)

    def column(name: str) -> NDArray[Any]:
        view = grid[name]
        return view.reshape((n, *view.shape[2:]))

    fast = _xyz_kernel(msg, data, height, width, row_step, point_step, max_range_m) if n else None
    if fast is None:
        points_xyz, valid = xyz_numpy(column("x"), column("y"), column("z"), max_range_m)
    else:
        points_xyz, valid = fast
    n_valid = points_xyz.shape[0]
    keep: NDArray[np.bool_] | slice = slice(None) if n_valid == n else valid

    channels = _channels(column, counts, keep, stamp_ns)
    organized = height > 1
    return LidarFrame(
        stamp_ns=stamp_ns,
        topic=topic,
        frame_id=frame_id,
        points_xyz=points_xyz,
        channels=channels,
        organized_shape=(height, width) if organized else None,
        organized_index=(np.flatnonzero(valid).astype(np.int64) if organized else None),
        dropped_points=n - n_valid,
        log_time_ns=int(log_time_ns),
    )


def _channels(column: Callable[[str], NDArray[Any]], counts: Mapping[str, int], keep: NDArray[np.bool_] | slice,
              stamp_ns: int) -> dict[str, NDArray[Any]]:
    """Every field but x, y, z of the points kept, in native byte order: a packed ``rgb`` / ``rgba`` split into
    r, g, b (uint8), ``intensity`` as float32, ``ring`` as uint16, and a ``time`` channel (s after the stamp)
    from the first per-point time field (``TIME_FIELDS``)."""
    channels: dict[str, NDArray[Any]] = {}
    for name in counts:
        if name in ("x", "y", "z"):
            continue
        values = column(name)[keep]
        values = values.astype(values.dtype.newbyteorder("="), copy=False)
        if name in _PACKED_COLOUR and values.dtype == np.uint32 and values.ndim == 1:
            channels["r"] = ((values >> 16) & 0xFF).astype(np.uint8)
            channels["g"] = ((values >> 8) & 0xFF).astype(np.uint8)
            channels["b"] = (values & 0xFF).astype(np.uint8)
            continue
        if name == "intensity":
            values = values.astype(np.float32, copy=False)
        elif name == "ring":
            values = values.astype(np.uint16, copy=False)
        channels[name] = np.ascontiguousarray(values)
    time_source = next((name for name in TIME_FIELDS if name in channels and channels[name].ndim == 1), None)
    if time_source is not None:
        channels["time"] = _time_channel(channels[time_source], stamp_ns, copy=time_source != "time")

    return channels
