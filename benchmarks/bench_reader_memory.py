"""Peak memory while streaming a ~1 GB MCAP through ``open_log(...).messages()``.

Writes a temporary MCAP of PointCloud2-sized raw payloads (120k points x 16 bytes = 1.92 MB each,
~520 messages, ~1 GB; incompressible random bytes, zstd chunks), then iterates every message through
the fleetcal reader in a fresh child process and reports its peak RSS (``ru_maxrss``). The target is
< 300 MB. The file is deleted afterwards.

    .venv/bin/python benchmarks/bench_reader_memory.py [--gb 1.0] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

POINTS = 120_000
POINT_STEP = 16
LIMIT_MB = 300.0


def write_big_mcap(path: Path, total_bytes: int) -> int:
    """Write ``total_bytes`` of payload as PointCloud2-sized raw messages; returns the message count."""
    from mcap.writer import CompressionType, Writer

    payload = POINTS * POINT_STEP
    count = max(1, total_bytes // payload)
    rng = np.random.default_rng(0)
    blocks = [rng.integers(0, 256, payload, dtype=np.uint8).tobytes() for _ in range(4)]
    with path.open("wb") as stream:
        writer = Writer(stream, chunk_size=4 * 1024 * 1024, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="fleetcal-bench")
        schema = writer.register_schema("sensor_msgs/msg/PointCloud2", "ros2msg", b"")
        channel = writer.register_channel("/lidar/points", "cdr", schema)
        for i in range(count):
            stamp_ns = 1_700_000_000_000_000_000 + i * 100_000_000
            writer.add_message(channel, stamp_ns, blocks[i % len(blocks)], stamp_ns)
        writer.finish()
    return count


def iterate(path: str) -> None:
    """Child process: stream every message, print count, bytes, seconds and peak RSS (MB)."""
    from fleetcal.readers.open import open_log

    start = time.perf_counter()
    count = 0
    total = 0
    with open_log(path) as reader:
        for raw in reader.messages():
            count += 1
            total += len(raw.data)
    seconds = time.perf_counter() - start
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"{count} {total} {seconds:.3f} {peak_mb:.1f}")


def main() -> int:
    formatter = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=formatter)
    parser.add_argument("--gb", type=float, default=1.0, help="payload size of the test log in GB")
    parser.add_argument("--dir", default=None, help="folder for the temporary log (default: system temp)")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        iterate(args.child)
        return 0
    with tempfile.TemporaryDirectory(dir=args.dir) as folder:
        path = Path(folder) / "big.mcap"
        t0 = time.perf_counter()
        written = write_big_mcap(path, int(args.gb * 1e9))
        size_mb = path.stat().st_size / 1e6
        print(f"wrote {path.name}: {written} messages, {size_mb:.0f} MB in {time.perf_counter() - t0:.1f} s")
        root = str(Path(__file__).resolve().parents[1])
        env = {**os.environ, "PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}
        out = subprocess.run([sys.executable, __file__, "--child", str(path)], check=True,
                             capture_output=True, text=True, env=env).stdout.split()
    count, total, seconds, peak_mb = int(out[0]), int(out[1]), float(out[2]), float(out[3])
    print(f"read {count} messages, {total / 1e6:.0f} MB payload in {seconds:.2f} s "
          f"({total / 1e6 / seconds:.0f} MB/s)")
    verdict = "OK" if peak_mb < LIMIT_MB else "OVER LIMIT"
    print(f"peak RSS while iterating: {peak_mb:.1f} MB (limit {LIMIT_MB:.0f} MB) {verdict}")
    return 0 if peak_mb < LIMIT_MB and count == written else 1


if __name__ == "__main__":
    raise SystemExit(main())
