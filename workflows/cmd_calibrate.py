"""``fleetcal calibrate``: targetless lidar-camera extrinsic calibration (GOM + particle swarm)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from fleetcal.workflows.cli import COMMANDS, emit_json, log_options

EXAMPLES = """examples:
  fleetcal calibrate drive.mcap --out calib/                     # topics detected, initial guess from tf
  fleetcal calibrate drive.bag --lidar /velodyne_points --camera /cam0/image_raw --out calib/
  fleetcal calibrate rig.bag --joint --out calib/                # all cameras, one unknown lidar pose
  fleetcal calibrate drive.mcap --initial "0 -0.08 -0.27 -90 0 -90" --search-deg 10 --search-m 1 --out calib/
  fleetcal calibrate drive.mcap --time-offset estimate --out calib/    # also the camera's clock offset
"""


def register(sub: Any, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser(
        "calibrate", parents=[common, log_options()], help=COMMANDS["calibrate"],
        description=__doc__, epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("logs", nargs="+", metavar="LOG", help="log file(s) of one recording")
    p.add_argument("--lidar", metavar="TOPIC", help="PointCloud2 topic (default: the only one)")
    p.add_argument("--camera", action="append", metavar="TOPIC", help="image topic; repeat for several")
    p.add_argument("--metric", choices=["gom", "nmi", "levinson"])
    p.add_argument("--feature", metavar="auto|NAME[+NAME]",
                   help="lidar feature: auto (default: range+normals or intensity, whichever explains more of the "
                        "image's edges), intensity, range, normals, log_range, or several joined by '+' "
                        "(scores averaged)")
    p.add_argument("--frames", type=int, metavar="N", help="paired frames spread over the log")
    p.add_argument("--search-deg", type=float, metavar="D", help="rotation search half-width, degrees")
    p.add_argument("--search-m", type=float, metavar="M", help="translation search half-width, metres")
    p.add_argument("--initial", metavar='"x y z roll pitch yaw" | auto',
                   help='T_camera_lidar guess (m, deg); "auto": find one, as for a log without one')
    p.add_argument("--joint", action="store_true", help="all cameras at once (camera-camera tf from the log)")
    p.add_argument("--time-offset", choices=["fixed", "estimate"],
                   help="estimate the camera clock minus the lidar clock (needs a moving, turning rig)")
    p.add_argument("--readout", choices=["fixed", "estimate"],
                   help="estimate the rolling-shutter readout (fixed: calibration.readout_s, default 0)")
    p.add_argument("--no-report", action="store_true", help="skip the report PNGs")
    p.set_defaults(func=run)


def overrides(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "calibration.metric": args.metric,
        "calibration.feature": args.feature,
        "calibration.frames": args.frames,
        "calibration.search_deg": args.search_deg,
        "calibration.search_m": args.search_m,
        "calibration.time_offset": args.time_offset,
        "calibration.readout": args.readout,
        "io.allow_truncated": True if args.allow_truncated else None,
    }


def run(args: argparse.Namespace) -> int:
    from fleetcal.workflows import calibrate as recipe
    from fleetcal.workflows.common import (
        CALIBRATE_OUTPUTS,
        calibration_notes,
        config_from_args,
        open_logs,
        prepare_out_dir,
        table,
        write_config,
    )
    from fleetcal.workflows.sensors import resolve_cameras, resolve_lidar

    config = config_from_args(args, overrides(args))
    out_dir = prepare_out_dir(args.out, CALIBRATE_OUTPUTS)
    with open_logs(args.logs, config, quiet=args.quiet) as reader:
        lidar = resolve_lidar(reader, args.lidar)
        cameras = resolve_cameras(reader, args.camera)
        with recipe.calibration_engine(config, args.quiet) as engine:
            pairs = recipe.run_calibration(reader, lidar, cameras, config, args.initial, args.joint, args.quiet,
                                           engine)
    write_config(config, out_dir)
    recipe.write_calibration(pairs, config, out_dir)
    if not args.no_report:
        recipe.landscape(pairs[0], config, out_dir)
    summaries = [p.summary() for p in pairs]
    result = {"out": str(out_dir), "pairs": summaries}
    if args.json:
        emit_json(result)
    else:
        rows = [[p.camera_topic, p.result.verdict, f"{p.result.initial_score:.4f}", f"{p.result.score:.4f}",
                 f"{s['change_deg']:.2f}", f"{100 * s['change_m']:.1f}", f"{p.result.runtime_s:.1f}"]
                for p, s in ((p, p.summary()) for p in pairs)]  # fmt: skip
        print(table(rows, ["camera", "verdict", "initial", "score", "change deg", "change cm", "time s"]))
        for line in calibration_notes(summaries):
            print(line)
        print(f"wrote {out_dir}/calibration.parquet, frames.parquet, report/", file=sys.stderr)
    return 0
