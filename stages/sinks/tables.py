"""Parquet tables of DESIGN.md: exact column names and types, zstd, written atomically."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from fleetcal.stages.sinks.atomic import atomic_path

POSE_FIELDS: list[tuple[str, pa.DataType]] = [
    ("tx_m", pa.float64()),
    ("ty_m", pa.float64()),
    ("tz_m", pa.float64()),
    ("qx", pa.float64()),
    ("qy", pa.float64()),
    ("qz", pa.float64()),
    ("qw", pa.float64()),
]
"""Pose columns of every table that holds one (translation in metres, scalar-last quaternion)."""

RPY_FIELDS: list[tuple[str, pa.DataType]] = [
    ("roll_deg", pa.float64()),
    ("pitch_deg", pa.float64()),
    ("yaw_deg", pa.float64()),
]
"""The same rotation as xyz-extrinsic roll, pitch, yaw in degrees (beside ``POSE_FIELDS``)."""

STD_COLUMNS = tuple([f"std_r{axis}_deg" for axis in "xyz"] + [f"std_t{axis}_m" for axis in "xyz"])
"""Per-axis standard deviations of a calibration in its camera's axes: rotation (degrees) about, then
translation (metres) along x, y, z."""

CALIBRATION_SCHEMA = pa.schema(
    [
        ("lidar_topic", pa.string()),
        ("camera_topic", pa.string()),
        ("lidar_frame", pa.string()),
        ("camera_frame", pa.string()),
        ("metric", pa.string()),
        ("feature", pa.string()),
        *POSE_FIELDS,
        *RPY_FIELDS,
        ("score", pa.float64()),
        ("initial_score", pa.float64()),
        ("frames_used", pa.int64()),
        ("runtime_s", pa.float64()),
        ("verdict", pa.string()),
        ("verdict_reason", pa.string()),
        *[(name, pa.float64()) for name in STD_COLUMNS],
        ("initialisation", pa.string()),
        ("initial_candidates", pa.int64()),
        ("time_offset_s", pa.float64()),
        ("time_offset_std_s", pa.float64()),
        ("readout_s", pa.float64()),
        ("readout_std_s", pa.float64()),
        ("motion_source", pa.string()),
    ]
)
"""One row per lidar/camera pair: the extrinsic, its scores and verdict, per-axis standard deviations in the
camera's axes (rotation degrees, translation metres), where the initial guess came from (``tf``,
``initial``, ``motion`` or ``search``) with the starting poses a motion or search initialisation scored (0
otherwise), and the clock terms (NaN where not estimated) and the ego-motion source (``tf``, ``odometry``,
``none``)."""

FRAMES_SCHEMA = pa.schema(
    [
        ("topic", pa.string()),
        ("stamp_ns", pa.int64()),
        ("n_points", pa.int64()),
        ("width", pa.int32()),
        ("height", pa.int32()),
        ("camera_topic", pa.string()),
        ("score_initial", pa.float64()),
        ("score_final", pa.float64()),
    ]
)

TRAJECTORY_SCHEMA = pa.schema(
    [
        ("stamp_ns", pa.int64()),
        *POSE_FIELDS,
        ("fitness", pa.float64()),
        ("rmse_m", pa.float64()),
        ("iterations", pa.int32()),
    ]
)

MAP_XYZ_FIELDS = [("x_m", pa.float32()), ("y_m", pa.float32()), ("z_m", pa.float32())]
MAP_CHANNEL_FIELDS = {"intensity": pa.float32(), "r": pa.uint8(), "g": pa.uint8(), "b": pa.uint8()}


_NUMPY_TYPES: dict[pa.DataType, type[np.generic]] = {
    pa.float32(): np.float32,
    pa.float64(): np.float64,
    pa.int32(): np.int32,
    pa.int64(): np.int64,
    pa.uint8(): np.uint8,
}
"""Arrow types whose arrays ``column`` builds from a NumPy buffer."""


def _fits(value: Any, dtype: pa.DataType) -> bool:
    """Whether ``value`` goes into a ``dtype`` column as it is (integers into integer columns; integers and
    floats into float columns; never a bool)."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if pa.types.is_integer(dtype):
        return isinstance(value, (int, np.integer))
    return isinstance(value, (int, float, np.integer, np.floating))


def column(values: Sequence[Any] | np.ndarray, dtype: pa.DataType) -> pa.Array:
    """An Arrow array of ``values`` as ``dtype`` (None: null). Numbers and strings go in through buffers
    (``pa.Array.from_buffers``), as ``pa.array`` imports pandas where it is installed (half a second on its
    first call, a twentieth of a short calibration); other values go through ``pa.array``."""
    if isinstance(values, np.ndarray) and values.ndim == 1 and dtype in _NUMPY_TYPES:
        data = np.ascontiguousarray(values, dtype=_NUMPY_TYPES[dtype])
        return pa.Array.from_buffers(dtype, data.shape[0], [None, pa.py_buffer(data)])
    items = list(values)
    present = np.array([v is not None for v in items], dtype=bool)
    validity = None if present.all() else pa.py_buffer(np.packbits(present, bitorder="little"))
    nulls = int(present.size - present.sum())
    if dtype in _NUMPY_TYPES and all(_fits(v, dtype) for v in items if v is not None):
        data = np.array([v if v is not None else 0 for v in items], dtype=_NUMPY_TYPES[dtype])
        return pa.Array.from_buffers(dtype, len(items), [validity, pa.py_buffer(data)], null_count=nulls)
    if dtype == pa.string() and all(isinstance(v, str) for v in items if v is not None):
        encoded = [v.encode() if v is not None else b"" for v in items]
        offsets = np.zeros(len(items) + 1, dtype=np.int32)
        offsets[1:] = np.cumsum([len(e) for e in encoded])
        buffers = [validity, pa.py_buffer(offsets), pa.py_buffer(b"".join(encoded))]
        return pa.Array.from_buffers(dtype, len(items), buffers, null_count=nulls)
    return pa.array(items, type=dtype)


def write_rows(rows: Sequence[Mapping[str, Any]], schema: pa.Schema, path: str | Path) -> Path:
    """Write dict rows with exactly ``schema``'s columns (missing keys become null) atomically."""
    columns = [column([row.get(field.name) for row in rows], field.type) for field in schema]
    table = pa.Table.from_arrays(columns, schema=schema)
    return write_table(table, path)


def write_table(table: pa.Table, path: str | Path) -> Path:
    """Write a pyarrow table as zstd Parquet via a temporary file renamed on success."""
    final = Path(path)
    with atomic_path(final) as tmp:
        pq.write_table(table, tmp, compression="zstd")
    return final


def map_table(points_xyz: np.ndarray, channels: Mapping[str, np.ndarray]) -> pa.Table:
    """``map.parquet`` table: float32 x_m, y_m, z_m (map frame) plus intensity / r, g, b when present."""
    pts = np.asarray(points_xyz, dtype=np.float32).reshape(-1, 3)
    arrays = [column(pts[:, i], pa.float32()) for i in range(3)]
    fields = [pa.field(name, dtype) for name, dtype in MAP_XYZ_FIELDS]
    for name, dtype in MAP_CHANNEL_FIELDS.items():
        if name in channels:
            values = np.asarray(channels[name])
            if dtype == pa.uint8():
                values = np.clip(np.rint(values), 0, 255).astype(np.uint8)
            else:
                values = values.astype(np.float32)
            arrays.append(column(values, dtype))
            fields.append(pa.field(name, dtype))
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields))
