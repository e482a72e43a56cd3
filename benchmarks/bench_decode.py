"""PointCloud2 decode throughput vs plain container iteration, for every log format.

Writes an N-frame log of M-point clouds (x, y, z float32, intensity float32, ring uint16, time
float64 in a 32-byte point) in each format (MCAP, ROS 1 bag, ROS 2 sqlite3, ROS 2 mcap, default
compression of ``LogWriter``) to a temporary folder, then prints per format:

- ``plain_s``: iterating the raw messages with the container library alone (mcap / rosbags), no
  deserialisation or decoding;
- ``ours_s``: ``readers.open.open_log`` + ``readers.frames.iter_lidar_frames`` (read, deserialise,
  decode to LidarFrame);
- ``overhead_%``: ``ours_s / plain_s - 1``;
- ``decode_MB/s``: PointCloud2 payload bytes / time spent in ``decode_pointcloud2`` alone.

Usage: ``python benchmarks/bench_decode.py [--frames 100] [--points 120000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import cast

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from fleetcal.readers.decode import decode_pointcloud2
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter

TOPIC = "/lidar/points"
FORMATS = {
    "mcap": ("mcap", {}, "log.mcap"),
    "ros1": ("ros1", {}, "log.bag"),
    "ros2-sqlite3": ("ros2", {"storage": "sqlite3"}, "log_sqlite3"),
    "ros2-mcap": ("ros2", {"storage": "mcap"}, "log_mcap"),
}


def make_scan(n_points: int, seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A 32-ring spinning-lidar-like scan: points (N, 3) float32 and intensity/ring/time channels."""
    rng = np.random.default_rng(seed)
    ring = np.arange(n_points) % 32
    azimuth = np.linspace(0, 2 * np.pi, n_points, endpoint=False)
    elevation = np.radians(-25 + ring * (40 / 31))
    rng_m = rng.uniform(2, 80, n_points)
    pts = np.stack(
        [
            rng_m * np.cos(elevation) * np.cos(azimuth),
            rng_m * np.cos(elevation) * np.sin(azimuth),
            rng_m * np.sin(elevation),
        ],
        axis=1,
    ).astype(np.float32)
    channels: dict[str, np.ndarray] = {
        "intensity": rng.uniform(0, 255, n_points).astype(np.float32),
        "ring": ring.astype(np.uint16),
        "time": (azimuth / (2 * np.pi) * 0.1).astype(np.float64),
    }
    return pts, channels


def write_log(path: Path, fmt: str, kwargs: dict[str, str], frames: int, n_points: int) -> int:
    """Write the benchmark log; returns the PointCloud2 payload bytes per frame."""
    pts, channels = make_scan(n_points)
    profile: rm.Profile = "ros1" if fmt == "ros1" else "ros2"
    payload = 0
    with LogWriter(path, fmt, **kwargs) as writer:  # type: ignore[arg-type]
        for i in range(frames):
            stamp = 1_000_000_000 + i * 100_000_000
            msg = rm.pointcloud2(
                stamp, "lidar", pts + np.float32(i * 0.01), channels, profile=profile, point_step=32
            )
            payload = int(msg.data.size)
            writer.write(TOPIC, "sensor_msgs/msg/PointCloud2", stamp, msg)
    return payload


def plain_iteration(path: Path, fmt: str) -> int:
    """Iterate raw message bytes with the container library only; returns bytes seen."""
    total = 0
    if fmt == "mcap":
        with path.open("rb") as stream:
            for _, _, message in make_reader(stream).iter_messages(topics=[TOPIC]):
                total += len(message.data)
        return total
    with AnyReader([path], default_typestore=rm.get_store("ros2")) as reader:
        conns = [c for c in reader.connections if c.topic == TOPIC]
        for _, _, data in reader.messages(connections=conns):
            total += len(data)
    return total


def ours(path: Path) -> tuple[int, float]:
    """open_log + deserialize + decode_pointcloud2; returns (points decoded, seconds in decode alone)."""
    from fleetcal.readers.open import open_log

    points = 0
    decode_s = 0.0
    with open_log(path) as reader:
        for raw in reader.messages(topics=[TOPIC]):
            msg = reader.deserialize(raw)
            t0 = time.perf_counter()
            frame = decode_pointcloud2(msg, TOPIC, raw.log_time_ns)
            decode_s += time.perf_counter() - t0
            points += frame.n_points
    return points, decode_s


def best_of(repeat: int, fn: Callable[[], object]) -> tuple[float, object]:
    best, result = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    return best, result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--points", type=int, default=120_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--formats", nargs="+", default=list(FORMATS), choices=list(FORMATS))
    parser.add_argument("--dir", help="folder for the temporary logs (default: system temp)")
    args = parser.parse_args()

    print(f"{args.frames} frames x {args.points} points x 32 B; best of {args.repeat}")
    print(f"{'format':<14}{'size_MB':>9}{'plain_s':>9}{'ours_s':>9}", end="")
    print(f"{'overhead_%':>12}{'decode_s':>10}{'decode_MB/s':>13}")
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        for name in args.formats:
            fmt, kwargs, filename = FORMATS[name]
            path = Path(tmp) / filename
            payload = write_log(path, fmt, kwargs, args.frames, args.points)
            size = sum(p.stat().st_size for p in ([path] if path.is_file() else path.rglob("*")))
            plain_s, _ = best_of(args.repeat, partial(plain_iteration, path, fmt))
            ours_s, result = best_of(args.repeat, partial(ours, path))
            points, decode_s = cast(tuple[int, float], result)
            assert points == args.frames * args.points, points
            mb = payload * args.frames / 1e6
            print(
                f"{name:<14}{size / 1e6:>9.0f}{plain_s:>9.3f}{ours_s:>9.3f}"
                f"{100 * (ours_s / plain_s - 1):>12.1f}{decode_s:>10.3f}{mb / decode_s:>13.0f}"
            )
            if path.is_dir():
                import shutil

                shutil.rmtree(path)
            else:
                path.unlink()


if __name__ == "__main__":
    main()
