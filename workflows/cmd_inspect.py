"""``fleetcal inspect LOG [LOG ...]``: topics, types, counts, rates, time span, frame ids, lidar and
camera topics, tf edges, undecodable topics of a log, and the problems ``calibrate``, ``map`` and
``process`` will meet in it (undecodable messages, bad tf entries, a tf that is not a tree, a first
scan with no valid point or with points beyond ``io.max_range_m``), each also a ``warning:`` line.

A damaged MCAP is read as far as it is intact; the report is printed, then a line says how many
messages were recovered and how many bytes were lost. Without ``--allow-truncated`` that line is an
error (exit 1); with it, a warning (exit 0).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from fleetcal.pipeline.errors import TruncatedLogError
from fleetcal.readers.open import open_log
from fleetcal.workflows.cli import COMMANDS, emit_json
from fleetcal.workflows.inspect_log import format_report, inspect_log

EXAMPLES = """examples:
  fleetcal inspect drive.mcap
  fleetcal inspect run_0.bag run_1.bag            several files of one recording
  fleetcal inspect rosbag2_folder/ --json
  fleetcal inspect cut.mcap --allow-truncated     read what is intact of a damaged file
"""


def register(subparsers: Any, common: argparse.ArgumentParser) -> None:
    """Add the ``inspect`` command."""
    parser = subparsers.add_parser(
        "inspect",
        parents=[common],
        help=COMMANDS["inspect"],
        description=__doc__,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "logs", nargs="+", metavar="LOG",
        help="MCAP file, ROS 1 .bag, or ROS 2 bag folder; several files of one recording are merged",
    )
    parser.add_argument(
        "--allow-truncated", action="store_true",
        help="accept a damaged MCAP: report what is intact and exit 0 with a warning",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Inspect the logs and print the report; each problem the other commands will meet is also a
    ``warning:`` line on stderr (exit 0); 0 on success."""
    from fleetcal.workflows.common import config_from_args

    config = config_from_args(args, {})
    with open_log(args.logs, allow_truncated=True) as reader:
        report = inspect_log(reader, config.io.max_range_m)
    if args.json:
        emit_json(report.to_json())
    else:
        sys.stdout.write(format_report(report))
        sys.stdout.flush()
    for problem in report.problems:
        sys.stderr.write(f"warning: {problem}\n")
    truncation = report.truncation
    if truncation is None:
        return 0
    message = truncation.message(", ".join(report.paths))
    if args.allow_truncated:
        sys.stderr.write(f"warning: {message}\n")
        return 0
    raise TruncatedLogError(
        f"{message} (pass --allow-truncated to accept)",
        recovered_messages=truncation.recovered_messages,
        lost_bytes=truncation.lost_bytes,
    )
