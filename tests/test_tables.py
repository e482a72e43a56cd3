"""Parquet columns built from buffers: the values pyarrow's own conversion gives, nulls included."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from fleetcal.stages.sinks.tables import CALIBRATION_SCHEMA, column, write_rows


@pytest.mark.parametrize(
    ("values", "dtype"),
    [
        (["cam_front", None, "kamera_vorn", ""], pa.string()),
        ([None, None], pa.string()),
        ([1.5, None, np.float64(2.0), 3], pa.float64()),
        ([7, None, np.int64(-3)], pa.int64()),
        ([np.int32(4), 2], pa.int32()),
        ([None] * 9 + [0.25], pa.float32()),
        ([], pa.string()),
    ],
)
def test_column_holds_what_pyarrow_converts(values: list[object], dtype: pa.DataType) -> None:
    built = column(values, dtype)
    built.validate(full=True)
    assert built.type == dtype
    assert built.equals(pa.array(values, type=dtype))
    assert built.null_count == sum(v is None for v in values)


def test_column_keeps_nan_apart_from_null() -> None:
    built = column([math.nan, None, 1.0], pa.float64())
    assert built.null_count == 1
    assert math.isnan(built[0].as_py()) and built[1].as_py() is None


@pytest.mark.parametrize(("values", "dtype"), [([True, None], pa.int64()), ([1, "one"], pa.string())])
def test_column_refuses_values_of_another_type(values: list[object], dtype: pa.DataType) -> None:
    with pytest.raises((pa.ArrowTypeError, pa.ArrowInvalid)):
        column(values, dtype)


def test_rows_round_trip_through_parquet_with_missing_keys(tmp_path: Path) -> None:
    rows: list[dict[str, object]] = [{"camera_topic": "/cam/front", "score": 0.71, "frames_used": 3},
            {"camera_topic": "/cam/rear", "verdict": "suspect"}]
    path = write_rows(rows, CALIBRATION_SCHEMA, tmp_path / "calibration.parquet")
    table = pq.read_table(path)
    assert table.schema.equals(CALIBRATION_SCHEMA)
    for name in ("camera_topic", "verdict", "score", "frames_used", "lidar_topic"):
        assert table.column(name).to_pylist() == [row.get(name) for row in rows]


def test_writing_rows_does_not_import_pandas(tmp_path: Path) -> None:
    """pandas, where installed, costs half a second to import; the tables never need it."""
    script = (
        "import sys; from fleetcal.stages.sinks.tables import CALIBRATION_SCHEMA, write_rows; "
        f"write_rows([{{'camera_topic': 'c', 'score': None}}], CALIBRATION_SCHEMA, {str(tmp_path / 'c.parquet')!r}); "
        "print('pandas' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
