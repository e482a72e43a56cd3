"""Long fuzz run: the properties of tests/test_fuzz_decoders.py with a large example budget.

    .venv/bin/python benchmarks/fuzz_long.py MINUTES [--examples N]

Runs each property in turn (non-derandomised, a fresh random seed each round) until MINUTES have
passed; prints examples run per property and every failure (hypothesis's minimal example).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("minutes", type=float)
    parser.add_argument("--examples", type=int, default=2000, help="examples per property per round")
    args = parser.parse_args()
    os.environ["FLEETCAL_FUZZ_EXAMPLES"] = str(args.examples)
    from tests import test_fuzz_decoders as fz

    real_logs = [fz.SHARED_DATA / "logs" / name for name in fz.REAL_LOGS] if fz.SHARED_DATA.is_dir() else None
    properties = {
        "pointcloud2": fz.test_fuzz_pointcloud2,
        "image": fz.test_fuzz_image,
        "compressed_image": fz.test_fuzz_compressed_image,
        "camera_info": fz.test_fuzz_camera_info,
        "tf": fz.test_fuzz_tf,
    }
    deadline = time.monotonic() + 60 * args.minutes
    failures: list[str] = []
    rounds = 0
    while time.monotonic() < deadline:
        rounds += 1
        for name, prop in [*properties.items(), ("readers", None)]:
            if time.monotonic() >= deadline:
                break
            try:
                if prop is None:
                    if real_logs is None:
                        continue
                    fz.test_fuzz_readers_on_mutated_real_logs(real_logs)
                else:
                    prop()
            except Exception as err:
                failures.append(f"{name}: {type(err).__name__}: {err}\n{traceback.format_exc()[-2000:]}")
                print(f"FAILURE in {name}: {type(err).__name__}: {err}", flush=True)
        print(f"round {rounds}: " + ", ".join(f"{k} {v}" for k, v in sorted(fz.EXECUTIONS.items())), flush=True)
    total = sum(fz.EXECUTIONS.values())
    print(f"\n{args.minutes:g} min, {rounds} rounds, {total} executions:")
    for name, count in sorted(fz.EXECUTIONS.items()):
        print(f"  {name:18s} {count}")
    print(f"failures: {len(failures)}")
    for failure in failures:
        print(failure)
    return 1 if failures else 0


if __name__ == "__main__":
    raise SystemExit(main())
