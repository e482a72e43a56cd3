"""``fleetcal calibrate-cameras``: affine map between two cameras' images (GOM paper 3.2.2)."""

from __future__ import annotations

import argparse
from typing import Any

from fleetcal.workflows.cli import COMMANDS, log_options

EXAMPLES = """examples:
  fleetcal calibrate-cameras rig.mcap --camera /cam_front/image_raw --camera /cam_side/image_raw --out cams/
"""


def register(sub: Any, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser(
        "calibrate-cameras", parents=[common, log_options()], help=COMMANDS["calibrate-cameras"],
        description=__doc__ + "\nThe first --camera is the base image, the second the moving one; the map is in raw "
        "pixels, moving -> base, one objective over the image pairs -> camera_camera.parquet.",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("logs", nargs="+", metavar="LOG", help="log file(s) of one recording")
    p.add_argument("--camera", action="append", required=True, metavar="TOPIC",
                   help="image topic: give exactly two, the base first")
    p.add_argument("--frames", type=int, metavar="N", help="image pairs spread over the log")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fleetcal.workflows.calibrate_cameras import run_cli
    from fleetcal.workflows.common import config_from_args

    config = config_from_args(args, {
        "calibration.frames": args.frames,
        "io.allow_truncated": True if args.allow_truncated else None,
    })  # fmt: skip
    return run_cli(args, config)
