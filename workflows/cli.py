"""The ``fleetcal`` command line: a thin layer that parses arguments, runs a workflow and turns
errors into one-line messages and exit codes (0 ok, 1 processing/input error, 2 usage error).

Each command lives in its own module ``workflows/cmd_<name>.py`` exposing
``register(subparsers, common) -> None``; that parser sets ``func(args) -> int``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import sys
from collections.abc import Sequence
from typing import Any

from fleetcal.pipeline.errors import FleetcalError, UsageError

COMMANDS = {
    "demo": "simulate a sample log, process it, print accuracy vs truth",
    "simulate": "write a synthetic log with exact ground truth + OUT.truth.json",
    "inspect": "topics, types, counts, rates, time span, frame ids, lidar/camera topics and tf tree",
    "calibrate": "lidar-camera extrinsics without targets (GOM)",
    "calibrate-cameras": "affine map between two cameras' images (GOM)",
    "map": "GICP (or MC-GICP) odometry and voxel map",
    "process": "calibrate + colourise + map + write back one log",
    "batch": "process many logs; a manifest records each one",
}
"""Command name -> its one-line help (a command's module is imported only when it is the one run)."""

EPILOG = """examples:
  fleetcal demo --out /tmp/fleetcal-demo
  fleetcal simulate /tmp/street.mcap --frames 20 --seed 1
  fleetcal inspect /tmp/street.mcap
  fleetcal calibrate /tmp/street.mcap --out /tmp/calib
  fleetcal map /tmp/street.mcap --channels intensity --out /tmp/map
"""


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose errors are one line and exit 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"error: {message} (see '{self.prog} --help')\n")
        raise SystemExit(2)


def common_options() -> argparse.ArgumentParser:
    """Options every command takes."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help="print one JSON object (the result) on stdout")
    common.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    common.add_argument("-v", "--verbose", action="count", default=0, help="debug logging (-vv: tracebacks)")
    common.add_argument("--config", metavar="TOML", help="configuration file (fleetcal.toml)")
    common.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on an existing dask cluster")
    common.add_argument("--workers", type=int, default=None,
                        help="local dask workers (0: in-process; default: in-process for calibrate, "
                             "calibrate-cameras and map, one per core for process and batch)")
    return common


def log_options() -> argparse.ArgumentParser:
    """Options of the commands that read logs and write results (calibrate, calibrate-cameras, map, process)."""
    options = argparse.ArgumentParser(add_help=False)
    options.add_argument("--allow-truncated", action="store_true", help="use what is intact of a truncated log")
    options.add_argument("--out", required=True, metavar="DIR", help="output folder")
    return options


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``only`` (a command's name, or "" for none) just that command's options
    are built and the others are listed by name and help (``fleetcal map --help`` imports no other command)."""
    parser = _Parser(
        prog="fleetcal",
        description="Targetless lidar-camera calibration (GOM) and MC-GICP mapping for robot fleet logs.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    common = common_options()
    for name, help_text in COMMANDS.items():
        if only is not None and name != only:
            sub.add_parser(name, help=help_text)
            continue
        importlib.import_module(f"fleetcal.workflows.cmd_{name.replace('-', '_')}").register(sub, common)
    return parser


def emit_json(result: Any) -> None:
    """Print one JSON object on stdout."""
    sys.stdout.write(json.dumps(result, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return str(obj)


def main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(words[0] if words and words[0] in COMMANDS else "")
    args = parser.parse_args(words)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    level = logging.DEBUG if args.verbose else logging.WARNING
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if not args.verbose:
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")
        for noisy in ("distributed", "dask", "bokeh", "tornado", "numba"):
            logging.getLogger(noisy).setLevel(logging.ERROR)
    try:
        return int(args.func(args))
    except UsageError as err:
        sys.stderr.write(f"error: {err}\n")
        return 2
    except FleetcalError as err:
        if args.verbose > 1:
            raise
        sys.stderr.write(f"error: {err}\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted\n")
        return 130
    except MemoryError:
        sys.stderr.write("error: out of memory\n")
        return 1
    except OSError as err:
        if args.verbose > 1:
            raise
        sys.stderr.write(f"error: {err.strerror or err}: {err.filename or ''}".rstrip(": ") + "\n")
        return 1
    except Exception as err:
        if args.verbose > 1:
            raise
        sys.stderr.write(f"error: internal error ({type(err).__name__}: {err}); rerun with -vv for details\n")
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
