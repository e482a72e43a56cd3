"""``fleetcal map``: lidar odometry and a voxel map with (Multi-Channel) GICP."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from fleetcal.workflows.cli import COMMANDS, emit_json, log_options

EXAMPLES = """examples:
  fleetcal map drive.mcap --out map/                         # lidar topic detected, GICP
  fleetcal map drive.bag --lidar /velodyne_points --channels intensity --out map/   # MC-GICP
  fleetcal map rgbd.mcap --channels color --voxel 0.02 --out map/

One recording is mapped in-process (scans prepared on a second thread while the previous one is
registered) unless --workers or --scheduler asks for dask workers.
"""


def register(sub: Any, common: argparse.ArgumentParser) -> None:
    p = sub.add_parser(
        "map", parents=[common, log_options()], help=COMMANDS["map"], description=__doc__,
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    p.add_argument("logs", nargs="+", metavar="LOG", help="log file(s) of one recording")
    p.add_argument("--lidar", metavar="TOPIC", help="PointCloud2 topic (default: the only one)")
    p.add_argument("--channels", help="none (GICP, the default) | intensity | color | combined (MC-GICP)")
    p.add_argument("--voxel", type=float, metavar="M", help="registration voxel size, metres")
    p.add_argument("--map-voxel", type=float, metavar="M", help="map voxel size, metres")
    p.add_argument("--max-corr", type=float, metavar="M", help="largest correspondence distance, metres")
    p.add_argument("--no-tf-odometry", action="store_true", help="ignore /tf odometry as the initial guess")
    p.add_argument("--no-deskew", action="store_true",
                   help="do not de-skew scans by their per-point times (clouds the driver already de-skewed)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fleetcal.pipeline.engine import Engine
    from fleetcal.pipeline.errors import UsageError
    from fleetcal.workflows import mapping
    from fleetcal.workflows.common import MAP_OUTPUTS, config_from_args, open_logs, prepare_out_dir, write_config
    from fleetcal.workflows.frame_sources import STAGE_WARMUPS
    from fleetcal.workflows.sensors import resolve_lidar

    if args.channels is not None and args.channels not in mapping.CHANNEL_MODES:
        raise UsageError(f"unknown --channels {args.channels!r}; expected one of {', '.join(mapping.CHANNEL_MODES)}")
    config = config_from_args(args, {
        "mapping.channels": args.channels, "mapping.voxel_m": args.voxel, "mapping.map_voxel_m": args.map_voxel,
        "mapping.max_corr_m": args.max_corr, "mapping.use_tf_odometry": False if args.no_tf_odometry else None,
        "mapping.deskew": False if args.no_deskew else None,
        "io.allow_truncated": True if args.allow_truncated else None,
    })  # fmt: skip
    out_dir = prepare_out_dir(args.out, MAP_OUTPUTS)
    with open_logs(args.logs, config, quiet=args.quiet) as reader:
        lidar = resolve_lidar(reader, args.lidar)
        workers = mapping.mapping_workers(config)
        with Engine(scheduler=config.engine.scheduler, workers=workers, quiet=args.quiet,
                    warmups=STAGE_WARMUPS) as engine:
            outcome = mapping.run_mapping(args.logs, reader, lidar, config, engine)
    write_config(config, out_dir)
    mapping.write_mapping(outcome, out_dir)
    result = {"out": str(out_dir), **outcome.summary()}
    if args.json:
        emit_json(result)
    else:
        s = outcome.summary()
        print(f"{s['scans']} scans, path {s['path_length_m']:.1f} m, mean fitness {s['mean_fitness'] or 0:.3f}, "
              f"{len(s['failed_pairs'])} failed and {len(s['degenerate_pairs'])} degenerate pairs, "
              f"{len(s['implausible_motion'])} implausible motions, "
              f"{s['map_points']} map points"
              + (f", {s['deskewed_scans']} scans de-skewed" if s["deskewed_scans"] else ""))  # fmt: skip
        print(f"wrote {out_dir}/trajectory.parquet, map.parquet, report/map_top.png", file=sys.stderr)
    for line in outcome.warnings():
        print(f"warning: {line}", file=sys.stderr)
    if outcome.scans_skipped:
        print(f"warning: skipped {outcome.scans_skipped} unusable scans (empty, NaN, beyond io.max_range_m or "
              "undecodable)", file=sys.stderr)
    return 0
