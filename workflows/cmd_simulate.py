"""``fleetcal simulate OUT``: write a synthetic log with exact ground truth and ``<OUT stem>.truth.json``.

The vehicle drives a loop round the scene (street: a city block; corridor: a ring of 3 m corridors with
poster-covered walls; open: a yard with painted ground) with a 10 Hz spinning (or rosette) lidar and 10 Hz
cameras fired 10-30 ms after each scan. ``/tf_static`` carries the calibration perturbed by
``--perturb-deg`` / ``--perturb-m`` (random axis and direction, seeded). ``--time-offset-ms`` sets the cameras'
clock minus the lidar clock and ``--readout-ms`` their rolling-shutter readout (default 0 and 0: synchronised
global-shutter cameras). The truth file holds the exact ``T_camera_lidar``, the perturbed one, each camera's
``time_offset_s`` and ``readout_s`` and the lidar trajectory. The same arguments always give byte-identical files.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from fleetcal.pipeline.errors import ConfigError, UsageError
from fleetcal.workflows.cli import COMMANDS, emit_json
from fleetcal.workflows.simulator.lidar import DEFAULT_LAYOUT, LIDAR_PATTERNS, MAX_ROSETTE_LINES, SUPPORTED_BEAMS
from fleetcal.workflows.simulator.scene import SCENES
from fleetcal.workflows.simulator.truth import MAX_CAMERAS
from fleetcal.workflows.simulator.write import (
    MAX_READOUT_MS,
    MAX_TIME_OFFSET_MS,
    SimulationOptions,
    simulate_log,
)

EXAMPLES = """examples:
  fleetcal simulate /tmp/street.mcap --frames 20 --seed 1
  fleetcal simulate /tmp/corridor.bag --format ros1 --scene corridor --beams 32 --cameras 2
  fleetcal simulate /tmp/poster_wall.mcap --scene corridor --frames 50 --max-range 20
  fleetcal simulate /tmp/yard --format ros2 --scene open --compressed --fisheye
  fleetcal simulate /tmp/drift.mcap --perturb-deg 3 --perturb-m 0.2 --organized --json
  fleetcal simulate /tmp/livox.mcap --lidar rosette --skewed
  fleetcal simulate /tmp/vlp16_wide.mcap --beams 16 --wide-angle
  fleetcal simulate /tmp/late_camera.mcap --speed 10 --time-offset-ms 30 --readout-ms 20
"""


def _int_range(lo: int, hi: int) -> Any:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{value} is out of range {lo}..{hi}")
        return value

    return parse


def _float_range(lo: float, hi: float) -> Any:
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not lo <= value <= hi:  # also rejects nan
            raise argparse.ArgumentTypeError(f"{value} is out of range {lo}..{hi}")
        return value

    return parse


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT, e.g. 1280x720") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"image size {w}x{h} is out of range 16..8192 a side")
    return w, h


def add_simulation_arguments(parser: argparse.ArgumentParser, frames: int, size: str) -> None:
    """The options shared by ``simulate`` and ``demo``."""
    _add_log_arguments(parser, frames)
    _add_lidar_arguments(parser)
    _add_camera_arguments(parser, size)


def _add_log_arguments(parser: argparse.ArgumentParser, frames: int) -> None:
    """The log: its format, length, scene, seed, speed and what it carries besides the sensors."""
    parser.add_argument(
        "--format",
        choices=("mcap", "ros1", "ros2"),
        default="mcap",
        help="mcap file, ROS 1 .bag or ROS 2 bag folder (default mcap)",
    )
    parser.add_argument(
        "--frames",
        type=_int_range(1, 100_000),
        default=frames,
        help=f"lidar scans at 10 Hz (default {frames})",
    )
    parser.add_argument("--scene", choices=SCENES, default="street", help="default street")
    parser.add_argument("--seed", type=_int_range(0, 2**63 - 1), default=0, help="default 0")
    parser.add_argument(
        "--speed",
        type=_float_range(0.0, 60.0),
        default=None,
        metavar="M_S",
        help="vehicle speed in m/s (default: street 8, corridor 1.5, open 5)",
    )
    parser.add_argument(
        "--perturb-deg",
        type=_float_range(0.0, 45.0),
        default=2.0,
        metavar="D",
        help="rotation error of the calibration written to /tf_static (default 2)",
    )
    parser.add_argument(
        "--perturb-m",
        type=_float_range(0.0, 2.0),
        default=0.1,
        metavar="M",
        help="translation error of the calibration written to /tf_static (default 0.1)",
    )
    parser.add_argument("--no-tf-static", action="store_true",
                        help="write no /tf_static (no mount of the lidar or the cameras): calibration then "
                             "finds its own start")
    parser.add_argument("--no-odometry", action="store_true",
                        help="write no /tf odometry (odom -> base_link): calibration then moves the scans by "
                             "fleetcal's own odometry")
    parser.add_argument(
        "--compressed",
        action="store_true",
        help="CompressedImage jpeg on /camera_N/image_raw/compressed instead of rgb8 Image",
    )


def _add_lidar_arguments(parser: argparse.ArgumentParser) -> None:
    """The lidar: its pattern, layout, mount, range and motion distortion."""
    parser.add_argument(
        "--lidar",
        choices=LIDAR_PATTERNS,
        default="spinning",
        help="spinning (rings x columns, default) or rosette (a forward-looking non-repetitive Livox-like "
        "lidar, 70.4 deg circular field of view: --beams laser lines x --columns samples per scan)",
    )
    parser.add_argument(
        "--lidar-roll",
        type=_float_range(-180.0, 180.0),
        default=0.0,
        metavar="DEG",
        help="lidar mounted rolled about its forward axis by DEG degrees (default 0: level)",
    )
    parser.add_argument(
        "--beams",
        type=_int_range(1, max(SUPPORTED_BEAMS)),
        default=None,
        help=f"spinning: rings, one of {', '.join(map(str, SUPPORTED_BEAMS))} (default "
        f"{DEFAULT_LAYOUT['spinning'][0]}); rosette: laser lines, 1..{MAX_ROSETTE_LINES} (default "
        f"{DEFAULT_LAYOUT['rosette'][0]})",
    )
    parser.add_argument(
        "--columns",
        type=_int_range(64, 4096),
        default=None,
        help=f"spinning: firings per revolution (default {DEFAULT_LAYOUT['spinning'][1]}); rosette: samples per "
        f"line and scan (default {DEFAULT_LAYOUT['rosette'][1]}, as a Livox Avia with the default lines)",
    )
    parser.add_argument(
        "--max-range",
        type=_float_range(1.0, 1000.0),
        default=100.0,
        metavar="M",
        help="lidar max range in m (default 100; 20 keeps the corridor's ends out of sight)",
    )
    parser.add_argument(
        "--organized",
        action="store_true",
        help="organised point clouds (height = beams, NaN where no return)",
    )
    parser.add_argument(
        "--skewed",
        action="store_true",
        help="motion distortion: cast each lidar column from the pose at its firing time and "
        "report it in the lidar frame of that time (default: de-skewed scans, every point "
        "at the scan stamp pose)",
    )


def _add_camera_arguments(parser: argparse.ArgumentParser, size: str) -> None:
    """The cameras: how many, their size, lens, mount and clock."""
    parser.add_argument(
        "--cameras",
        type=_int_range(1, MAX_CAMERAS),
        default=1,
        help=f"cameras looking forward, left, right, back, ... (1..{MAX_CAMERAS}, default 1)",
    )
    parser.add_argument(
        "--image-size",
        type=_size,
        default=_size(size),
        metavar="WxH",
        help=f"camera resolution (default {size})",
    )
    parser.add_argument("--camera-yaw", type=_float_range(-180.0, 180.0), default=0.0, metavar="DEG",
                        help="every camera turned DEG degrees left of its usual direction (default 0)")
    parser.add_argument("--camera-roll", type=_float_range(-180.0, 180.0), default=0.0, metavar="DEG",
                        help="every camera rolled DEG degrees about its optical axis (default 0: upright)")
    lens = parser.add_mutually_exclusive_group()
    lens.add_argument("--fisheye", action="store_true", help="equidistant fisheye cameras instead of pinhole")
    lens.add_argument("--panorama", action="store_true",
                      help="cylindrical 360 deg panoramas (the GOM paper's Ladybug model) instead of pinhole")
    lens.add_argument("--rectified", action="store_true",
                      help="rectified stereo images on /camera_N/image_rect (no distortion, a 1.5 deg R in the "
                           "CameraInfo) instead of raw pinhole")
    lens.add_argument("--wide-angle", action="store_true",
                      help="wide-angle cameras (fx = 0.70 x width) with a real lens's strong plumb_bob barrel "
                           "distortion, D = -0.4398 0.2329 -0.0011 0.00021 -0.073, whose model folds over "
                           "before the image's corners, instead of the mild pinhole")
    parser.add_argument(
        "--time-offset-ms",
        type=_float_range(-MAX_TIME_OFFSET_MS, MAX_TIME_OFFSET_MS),
        default=0.0,
        metavar="MS",
        help="every camera's clock minus the lidar clock, ms: an image stamped t shows the scene at lidar "
        "time t - MS (default 0)",
    )
    parser.add_argument(
        "--readout-ms",
        type=_float_range(0.0, MAX_READOUT_MS),
        default=0.0,
        metavar="MS",
        help="rolling shutter: every camera exposes its rows top to bottom over MS ms, the stamp being the "
        "first row's time (default 0: global shutter)",
    )


def options_from_args(args: argparse.Namespace) -> SimulationOptions:
    width, height = args.image_size
    opts = SimulationOptions(
        fmt=args.format,
        frames=args.frames,
        scene=args.scene,
        lidar=args.lidar,
        lidar_roll_deg=args.lidar_roll,
        camera_yaw_deg=args.camera_yaw,
        camera_roll_deg=args.camera_roll,
        tf_static=not args.no_tf_static,
        **{name: value for name in ("beams", "columns") if (value := getattr(args, name)) is not None},
        cameras=args.cameras,
        fisheye=args.fisheye,
        panorama=args.panorama,
        rectified=args.rectified,
        wide_angle=args.wide_angle,
        compressed=args.compressed,
        organized=args.organized,
        speed_m_s=args.speed,
        perturb_deg=args.perturb_deg,
        perturb_m=args.perturb_m,
        seed=args.seed,
        max_range_m=args.max_range,
        deskew=not args.skewed,
        odometry=not args.no_odometry,
        time_offset_ms=args.time_offset_ms,
        readout_ms=args.readout_ms,
        width=width,
        height=height,
    )
    try:
        opts.validate()
    except ConfigError as err:
        raise UsageError(str(err)) from err
    return opts


def register(subparsers: Any, common: argparse.ArgumentParser) -> None:
    """Add the ``simulate`` command."""
    parser = subparsers.add_parser(
        "simulate",
        parents=[common],
        help=COMMANDS["simulate"],
        description=__doc__,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "out",
        metavar="OUT",
        help="output log: a .mcap file, a .bag file (--format ros1) or a folder (--format ros2)",
    )
    add_simulation_arguments(parser, frames=20, size="1280x720")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Simulate and write; prints a summary (or one JSON object with ``--json``)."""
    opts = options_from_args(args)
    result = simulate_log(args.out, opts, quiet=args.quiet)
    if args.json:
        emit_json(result.to_json())
    else:
        sys.stdout.write(
            f"wrote {result.log_path} ({result.format}, {result.scene}, seed {result.seed}): "
            f"{result.lidar_scans} scans on {result.lidar_topic}, {result.camera_images} images on "
            f"{', '.join(result.camera_topics)}, {result.messages} messages, {result.duration_s:.1f} s, "
            f"{result.distance_m:.1f} m driven, in {result.runtime_s:.1f} s\n"
            f"truth: {result.truth_path}\n"
        )
    return 0
