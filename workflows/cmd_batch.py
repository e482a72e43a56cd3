"""``fleetcal batch``: process many logs in parallel (one dask task per log), with a manifest and a
fleet summary of the calibration over time.

Writes ``DIR/<log stem>/`` per log (the outputs of ``fleetcal process``), ``DIR/manifest.parquet`` (one
row per log: path, out_dir, status ok|failed|skipped, error, started_ns, finished_ns, runtime_s,
log_start_ns, camera_topics, verdicts, scores, translations_held, translations_weak (lists, one per
lidar/camera pair), map_points; rewritten as each log finishes) and ``DIR/fleet.parquet`` (per rig,
``T_camera_lidar`` per log in time order and its change from the previous log, flagged as drift). Exit 0
only when every log succeeded.
"""

from __future__ import annotations

import argparse
import math
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from fleetcal.pipeline.errors import ProcessingError, UsageError
from fleetcal.workflows.cli import COMMANDS, emit_json

EXAMPLES = """examples:
  fleetcal batch "fleet/*.mcap" --out results/                 # quote the glob
  fleetcal batch logs.txt --out results/                        # one log per line, '#' comments
  fleetcal batch "fleet/**/*.bag" --out results/ --resume       # skip finished logs, redo partial ones
  fleetcal batch a.mcap b.mcap rosbag2_folder --out results/ --workers 2 --drift-deg 0.3
  fleetcal batch "fleet/*.mcap" --out results/ --scheduler tcp://10.0.0.5:8786 --json
"""


def register(sub: Any, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser(
        "batch", parents=[common], help=COMMANDS["batch"],
        description=__doc__, epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument(
        "inputs", nargs="+", metavar="GLOB|LIST",
        help="quoted glob(s), log paths (a ROS 2 bag folder is one log) or a .txt/.list file of logs",
    )  # fmt: skip
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--resume", action="store_true", help="skip complete log folders, redo partial ones")
    p.add_argument(
        "--drift-deg", type=float, default=0.5, metavar="D",
        help="rotation change between consecutive logs of a rig flagged as drift (default 0.5)",
    )  # fmt: skip
    p.add_argument(
        "--drift-m", type=float, default=0.05, metavar="M",
        help="translation change between consecutive logs of a rig flagged as drift (default 0.05)",
    )  # fmt: skip
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fleetcal.workflows import batch
    from fleetcal.workflows.common import config_from_args

    if not (math.isfinite(args.drift_deg) and args.drift_deg >= 0):
        raise UsageError(f"--drift-deg must be a number >= 0, got {args.drift_deg}")
    if not (math.isfinite(args.drift_m) and args.drift_m >= 0):
        raise UsageError(f"--drift-m must be a number >= 0, got {args.drift_m}")
    config = config_from_args(args, {})
    result = batch.run_batch(
        args.inputs,
        Path(args.out),
        config,
        resume=args.resume,
        scheduler=config.engine.scheduler,
        workers=config.engine.workers,
        drift_deg=args.drift_deg,
        drift_m=args.drift_m,
        quiet=args.quiet,
    )
    if args.json:
        emit_json(result.to_json())
    else:
        print(logs_table(result))
        if result.fleet:
            print()
            print(fleet_table(result.fleet, args.drift_deg, args.drift_m))
        print(
            f"wrote {result.manifest_path}, {result.fleet_path} in {result.runtime_s:.1f} s", file=sys.stderr
        )
    failed = result.count("failed")
    if failed:
        raise ProcessingError(f"{failed} of {len(result.outcomes)} logs failed (see {result.manifest_path})")
    return 0


def logs_table(result: Any) -> str:
    """One line per log: folder, status, time, per-camera verdicts, map points, error."""
    from fleetcal.workflows.common import table

    rows = []
    for o in result.outcomes:
        verdicts = " ".join(f"{v}({s:.3f})" for v, s in zip(o.verdicts, o.scores, strict=False)) or "-"
        runtime = f"{o.runtime_s:.1f}" if o.runtime_s is not None else "-"
        points = str(o.map_points) if o.map_points is not None else "-"
        rows.append([Path(o.out_dir).name, o.status, runtime, verdicts, points, o.error or ""])
    return table(rows, ["log", "status", "time s", "verdicts (score)", "map points", "error"])


def fleet_table(fleet: list[dict[str, Any]], drift_deg: float, drift_m: float) -> str:
    """Per rig and log in time order: T_camera_lidar, change from the previous log, drift flag."""
    from fleetcal.workflows.common import table

    rows = []
    for r in fleet:
        start = (
            datetime.fromtimestamp(r["log_start_ns"] / 1e9, tz=timezone.utc).strftime("%Y-%m-%d %H:%M:%S")
            if r["log_start_ns"] is not None
            else "-"
        )
        change = f"{r['change_deg']:.2f} / {100 * r['change_m']:.1f}" if r["change_deg"] is not None else "-"
        rows.append([
            f"{r['lidar_frame']}->{r['camera_frame']}", Path(r["out_dir"]).name, start, r["verdict"] or "-",
            f"{r['tx_m']:.3f} {r['ty_m']:.3f} {r['tz_m']:.3f}" + _translation_mark(r),
            f"{r['roll_deg']:.2f} {r['pitch_deg']:.2f} {r['yaw_deg']:.2f}", change,
            "DRIFT" if r["drift"] else "",
        ])  # fmt: skip
    header = ["rig", "log", "start (UTC)", "verdict", "t xyz m", "rpy deg", "change deg / cm", "drift"]
    flagged = sum(bool(r["drift"]) for r in fleet)
    footer = f"\n{flagged} drift flag(s) (> {drift_deg} deg or > {100 * drift_m:.1f} cm)"
    if any(r.get("translation_held") for r in fleet):
        footer += "\nheld: the translation is the log's own (the scene did not fix it), not a measurement"
    if any(r.get("translation_weak_axes") and not r.get("translation_held") for r in fleet):
        footer += ("\nrough(axes): the log fixes the translation only weakly along those axes of the camera; a "
                   "change there may be noise")
    return table(rows, header) + footer


def _translation_mark(row: dict[str, Any]) -> str:
    """What follows a fleet row's translation: `` held``, `` rough(x,z)`` or nothing."""
    if row.get("translation_held"):
        return " held"
    return f" rough({row['translation_weak_axes']})" if row.get("translation_weak_axes") else ""
