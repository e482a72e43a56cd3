"""``fleetcal calibrate``: targetless lidar-camera extrinsic calibration (GOM + particle swarm)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from fleetcal.workflows.cli import emit_json

EXAMPLES = """examples:
  fleetcal calibrate drive.mcap --out calib/                     # topics detected, initial guess from tf
  fleetcal calibrate drive.bag --lidar /velodyne_points --camera /cam0/image_raw --out calib/
  fleetcal calibrate rig.bag --joint --out calib/                # all cameras, one unknown lidar pose
  fleetcal calibrate drive.mcap --initial "0 -0.08 -0.27 -90 0 -90" --search-deg 10 --search-m 1 --out calib/
"""


def register(sub: Any, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser(
        "calibrate", parents=[common], help="lidar-camera extrinsics without targets (GOM)",
        description=__doc__, epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("logs", nargs="+", metavar="LOG", help="log file(s) of one recording")
    p.add_argument("--lidar", metavar="TOPIC", help="PointCloud2 topic (default: the only one)")
    p.add_argument("--camera", action="append", metavar="TOPIC", help="image topic; repeat for several")
    p.add_argument("--metric", choices=["gom", "nmi", "levinson"])
    p.add_argument("--feature", metavar="NAME[+NAME]",
                   help="lidar feature: intensity, range, normals, log_range, or several joined by '+' "
                        "(scores averaged), e.g. range+normals")
    p.add_argument("--frames", type=int, metavar="N", help="paired frames spread over the log")
    p.add_argument("--search-deg", type=float, metavar="D", help="rotation search half-width, degrees")
    p.add_argument("--search-m", type=float, metavar="M", help="translation search half-width, metres")
    p.add_argument("--initial", metavar='"x y z roll pitch yaw"', help="T_camera_lidar guess (m, deg)")
    p.add_argument("--joint", action="store_true", help="all cameras at once (camera-camera tf from the log)")
    p.add_argument(
        "--camera-camera",
        action="store_true",
        help="affine map between two --camera images (GOM 3.2.2) -> camera_camera.parquet",
    )
    p.add_argument("--gradient-viewpoint", choices=["auto", "camera", "lidar"],
                   help="lidar gradients on the camera's sphere at the initial guess (paper) or on the lidar's own, "
                        "carried to the camera; auto (default): the lidar's")
    p.add_argument("--gradient-fit", choices=["auto", "paper", "lsq"],
                   help="lidar gradient: Algorithm 1 or least squares; auto (default): lsq with the lidar viewpoint")
    p.add_argument("--gradient-neighbours", choices=["auto", "angle", "sampling"],
                   help="sphere neighbours: nearest by angle (paper) or across rings too; auto (default): "
                        "across rings with the lidar viewpoint, unless sparse rings cross the image slanted > 30 deg")
    p.add_argument("--explore", choices=["auto", "on", "off"],
                   help="GOM swarm explores on image gradients blurred 3x more for its first 30 iterations; "
                        "auto (default): on for --search-deg above 5 or --search-m above 0.5")
    p.add_argument("--ring-smoothing", choices=["auto", "on", "off"],
                   help="GOM also scores image gradients smoothed across the lidar's rings (a third of their "
                        "spacing); auto (default): on where that exceeds the image blur (sparse rings)")
    p.add_argument("--translation", choices=["auto", "estimate", "hold"],
                   help="estimate the translation, or hold it at the initial guess's (rotation only); auto "
                        "(default): held where the seeded runs disagree on it from a trusted start (box within "
                        "5 deg / 0.5 m)")
    p.add_argument("--no-motion-compensation", action="store_true", help="ignore /tf odometry")
    p.add_argument("--no-point-times", action="store_true",
                   help="move each scan by its stamp, not each point by its time field (de-skewed clouds)")
    p.add_argument("--camera-model", choices=["log", "plumb_bob", "rational_polynomial", "equidistant",
                                              "cylindrical", "none"],
                   help="image projection: the CameraInfo's (log, default) or this model with its K and D "
                        "(cylindrical: the GOM paper's panoramic model)")
    p.add_argument("--rectified-topic", action="append", metavar="TOPIC",
                   help="image topic that carries rectified images though its name does not say so (ROS: "
                        "image_rect...); projected with the CameraInfo's P and R; repeat for several")
    p.add_argument("--estimate-focal", action="store_true", help="also estimate a focal length scale")
    p.add_argument("--particles", type=int, metavar="N", help="particle swarm size (default 200)")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--repeats", type=int, metavar="N",
                   help="seeded runs; their spread is the uncertainty (one run in a box wider than 5 deg / 0.5 m is "
                   "suspect: nothing confirms it)")
    p.add_argument("--confirm-repeats", type=int, metavar="N",
                   help="extra seeded runs while none confirms the best (default 3; 0: none)")
    p.add_argument("--allow-truncated", action="store_true", help="use what is intact of a truncated log")
    p.add_argument("--no-report", action="store_true", help="skip the report PNGs")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.set_defaults(func=run)


def overrides(args: argparse.Namespace) -> dict[str, Any]:
    return {
        "calibration.metric": args.metric,
        "calibration.feature": args.feature,
        "calibration.frames": args.frames,
        "calibration.search_deg": args.search_deg,
        "calibration.search_m": args.search_m,
        "calibration.translation": args.translation,
        "calibration.particles": args.particles,
        "calibration.seed": args.seed,
        "calibration.repeats": args.repeats,
        "calibration.confirm_repeats": args.confirm_repeats,
        "calibration.gradient_viewpoint": args.gradient_viewpoint,
        "calibration.explore": args.explore,
        "calibration.ring_smoothing": args.ring_smoothing,
        "calibration.camera_model": args.camera_model,
        "calibration.gradient_fit": args.gradient_fit,
        "calibration.gradient_neighbours": args.gradient_neighbours,
        "calibration.estimate_focal": True if args.estimate_focal else None,
        "calibration.motion_compensation": False if args.no_motion_compensation else None,
        "calibration.point_times": False if args.no_point_times else None,
        "io.allow_truncated": True if args.allow_truncated else None,
        "io.rectified_topics": args.rectified_topic,
    }


def run(args: argparse.Namespace) -> int:
    from fleetcal.pipeline.engine import Engine
    from fleetcal.workflows import calibrate as recipe
    from fleetcal.workflows.common import (
        calibration_notes,
        config_from_args,
        open_logs,
        prepare_out_dir,
        table,
        write_config,
    )
    from fleetcal.workflows.sensors import resolve_cameras, resolve_lidar

    config = config_from_args(args, overrides(args))
    if args.camera_camera:
        from fleetcal.workflows.calibrate_cameras import run_cli

        return run_cli(args, config)
    out_dir = prepare_out_dir(args.out)
    with open_logs(args.logs, config, quiet=args.quiet) as reader:
        lidar = resolve_lidar(reader, args.lidar)
        cameras = resolve_cameras(reader, args.camera)
        engine = Engine(scheduler=config.engine.scheduler, workers=config.engine.workers, quiet=args.quiet)
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
