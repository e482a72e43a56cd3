"""``fleetcal process``: calibrate, colourise, map and write everything back for one log."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from fleetcal.workflows.cli import COMMANDS, emit_json, log_options

EXAMPLES = """examples:
  fleetcal process drive.mcap --out out/drive
  fleetcal process drive.bag --config fleetcal.toml --out out/drive --json
"""


def register(sub: Any, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser(
        "process", parents=[common, log_options()], help=COMMANDS["process"],
        description=__doc__, epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("logs", nargs="+", metavar="LOG", help="log file(s) of one recording")
    p.add_argument("--channels", help="mapping channels: none | intensity | color | combined (default combined)")
    p.add_argument("--frames", type=int, metavar="N", help="calibration frames")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fleetcal.workflows.common import PROCESS_OUTPUTS, calibration_notes, config_from_args, prepare_out_dir, table
    from fleetcal.workflows.process import process_log, writeback_path

    config = config_from_args(args, {
        "mapping.channels": args.channels or "combined", "calibration.frames": args.frames,
        "io.allow_truncated": True if args.allow_truncated else None,
    })  # fmt: skip
    out_dir = prepare_out_dir(args.out, (*PROCESS_OUTPUTS, writeback_path(args.logs[0], Path(args.out)).name))
    result = process_log(args.logs, out_dir, config, workers=config.engine.workers,
                         scheduler=config.engine.scheduler, quiet=args.quiet)  # fmt: skip
    if args.json:
        emit_json(result.to_json())
        return 0
    rows = [[c["camera_topic"], c["verdict"], f"{c['initial_score']:.4f}", f"{c['score']:.4f}",
             f"{c['change_deg']:.2f}", f"{100 * c['change_m']:.1f}"] for c in result.calibrations]  # fmt: skip
    print(table(rows, ["camera", "verdict", "initial", "score", "change deg", "change cm"]))
    for line in calibration_notes(result.calibrations):
        print(line)
    if result.mapping:
        m = result.mapping
        print(f"map: {m['scans']} scans ({m['channels']}), path {m['path_length_m']:.1f} m, {m['map_points']} points")
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {out_dir} ({result.runtime_s:.1f} s)", file=sys.stderr)
    return 0
