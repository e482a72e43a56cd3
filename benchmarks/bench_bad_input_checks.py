"""Cost of the bad-input checks on clean runs over the shared real logs.

Measured per lidar scan of the shared logs (``../shared/data/logs``; every PointCloud2 message):

- ``gather_ms``: the x, y, z gather of ``decode_pointcloud2`` (numba kernel ``gather_xyz_f32``) with the
  range check (points beyond ``io.max_range_m`` dropped), against ``gather_no_range_ms``, the same pass
  without it (finite and non-zero only: a copy of the kernel as it was before the check);
- ``decode_ms``: the whole ``decode_pointcloud2`` (layout checked by ``check_pointcloud2``, channels copied).

Per log, once per command: ``check_tf_ms`` (bad tf entries, tf not a tree: ``readers.frames.check_tf``) and
``out_check_ms`` (``workflows.common.prepare_out_dir``: a probe file written and removed).

Then ``fleetcal map`` of the KITTI odometry sequence (51 scans, in-process engine) is timed once, and the
checks' added time over its 51 scans is given as a share of it.

Usage: ``python benchmarks/bench_bad_input_checks.py [--repeat 5]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fleetcal.pipeline.numba_flags import NJIT_FLAGS
from fleetcal.readers.decode.pointcloud2 import MAX_RANGE_M, check_pointcloud2, decode_pointcloud2
from fleetcal.readers.decode.pointcloud2_kernels import gather_xyz_f32
from fleetcal.readers.frames import POINTCLOUD2, check_tf
from fleetcal.readers.open import open_log
from fleetcal.workflows.cli import main
from fleetcal.workflows.common import prepare_out_dir

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "logs"
LOGS = ["kitti_odometry_00_scans_50-100.mcap", "kitti_2011_09_26.mcap", "nuscenes_n015.bag", "pjlab_road_rig1",
        "pjlab_road_rig2", "outdoor_scan_pair.mcap"]  # fmt: skip
MAP_LOG = "kitti_odometry_00_scans_50-100.mcap"


@njit(**NJIT_FLAGS)
def gather_no_range(
    words: np.ndarray, height: int, width: int, row_words: int, step_words: int, x_word: int, y_word: int,
    z_word: int, points_out: np.ndarray, valid_out: np.ndarray,
) -> int:  # fmt: skip
    """``gather_xyz_f32`` without the range check: valid = finite and not all zero."""
    kept = 0
    for r in range(height):
        row = r * row_words
        for c in range(width):
            base = row + c * step_words
            x = words[base + x_word]
            y = words[base + y_word]
            z = words[base + z_word]
            ok = np.isfinite(x) and np.isfinite(y) and np.isfinite(z) and (x != 0.0 or y != 0.0 or z != 0.0)
            valid_out[r * width + c] = ok
            if ok:
                points_out[kept, 0] = x
                points_out[kept, 1] = y
                points_out[kept, 2] = z
                kept += 1
    return kept


def _best_ms(fn: Any, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def gather_times(msg: Any, repeat: int) -> tuple[float, float, int]:
    """(with range check ms, without ms, points) of one scan's x, y, z gather (best of ``repeat``)."""
    layout = check_pointcloud2(msg)
    offsets = {str(f.name): int(f.offset) // 4 for f in msg.fields if f.name in ("x", "y", "z")}
    n = layout.height * layout.width
    words = layout.data[: (layout.height - 1) * layout.row_step + layout.width * layout.point_step].view(np.float32)
    args = (words, layout.height, layout.width, layout.row_step // 4, layout.point_step // 4,
            offsets["x"], offsets["y"], offsets["z"])  # fmt: skip
    points, valid = np.empty((n, 3), np.float32), np.empty(n, np.bool_)
    with_range = _best_ms(lambda: gather_xyz_f32(*args, points, valid, MAX_RANGE_M), repeat)
    without = _best_ms(lambda: gather_no_range(*args, points, valid), repeat)
    return with_range, without, n


def main_bench(repeat: int) -> None:
    total_added_ms = {}
    for name in LOGS:
        path = DATA / name
        with open_log(path) as reader:
            topics = [t for t, info in reader.topics.items() if info.msgtype == POINTCLOUD2]
            msgs = [reader.deserialize(raw) for raw in reader.messages(topics=topics)]
            check_tf_ms = _best_ms(lambda: check_tf(reader), repeat)
        rows = [gather_times(m, repeat) for m in msgs]
        decode_ms = [_best_ms(lambda: decode_pointcloud2(m, "/l"), repeat) for m in msgs]  # noqa: B023
        with tempfile.TemporaryDirectory() as tmp:
            out_ms = _best_ms(lambda: prepare_out_dir(tmp, ("config.toml",)), repeat)
        with_range = np.array([r[0] for r in rows])
        without = np.array([r[1] for r in rows])
        points = int(np.mean([r[2] for r in rows]))
        added = float(np.sum(with_range - without))
        total_added_ms[name] = added + check_tf_ms + out_ms
        print(f"{name}: {len(msgs)} scans of ~{points} points; gather {with_range.mean():.3f} ms with the range "
              f"check, {without.mean():.3f} ms without (+{100 * (with_range.sum() / without.sum() - 1):.1f} %); "
              f"decode {np.mean(decode_ms):.2f} ms/scan; check_tf {check_tf_ms:.2f} ms; out check {out_ms:.2f} ms; "
              f"added per run {total_added_ms[name]:.2f} ms")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        code = main(["map", str(DATA / MAP_LOG), "--workers", "0", "-q", "--out", tmp])
        map_s = time.perf_counter() - t0
    print(f"fleetcal map {MAP_LOG} (--workers 0): exit {code}, {map_s:.1f} s; the checks add "
          f"{total_added_ms[MAP_LOG]:.1f} ms = {100 * total_added_ms[MAP_LOG] / 1e3 / map_s:.3f} % of it")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    main_bench(parser.parse_args().repeat)
