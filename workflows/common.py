"""Helpers shared by the command modules: config from flags, opening logs, output folders."""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from fleetcal.pipeline.config import COMMAND_LINE, Config, load_config, write_toml
from fleetcal.pipeline.errors import ConfigError, InputError, UsageError
from fleetcal.readers.base import LogReader
from fleetcal.readers.open import open_log, truncation_of

REPORT_FOLDER = "report"
CALIBRATE_OUTPUTS = ("config.toml", "calibration.parquet", "frames.parquet")
MAP_OUTPUTS = ("config.toml", "trajectory.parquet", "map.parquet")
PROCESS_OUTPUTS = (*CALIBRATE_OUTPUTS, "trajectory.parquet", "map.parquet", "result.json")
"""File names each command writes in its ``--out`` folder (besides ``report/``)."""

CAMERA_AXIS_NAMES = {"x": "x (image right)", "y": "y (image down)", "z": "z (optical axis)"}


FLAG_OF_KEY = {
    "mapping.voxel_m": "--voxel",
    "mapping.map_voxel_m": "--map-voxel",
    "mapping.max_corr_m": "--max-corr",
    "mapping.use_tf_odometry": "--no-tf-odometry",
    "mapping.deskew": "--no-deskew",
}
"""Config key -> the flag that sets it, where the flag is not ``--`` + the key's name with ``-`` for ``_``."""


def flag_of(key: str) -> str:
    """The command-line flag that sets config key ``section.key`` (``calibration.search_deg`` -> ``--search-deg``)."""
    return FLAG_OF_KEY.get(key, "--" + key.partition(".")[2].replace("_", "-"))


def config_from_args(args: argparse.Namespace, overrides: dict[str, Any]) -> Config:
    """Defaults < ``--config`` TOML < ``FLEETCAL_*`` environment < command-line flags.

    Raises:
        UsageError: a value that a flag, the ``--config`` file or the environment gives is rejected (exit 2);
            a flag's value is named by the flag (``--frames -1: must be >= 1``).
    """
    given = {
        "engine.scheduler": getattr(args, "scheduler", None),
        "engine.workers": getattr(args, "workers", None),
        **overrides,
    }
    try:
        return load_config(getattr(args, "config", None), overrides=given)
    except ConfigError as err:
        from_flag = err.source in (None, COMMAND_LINE)
        value = given.get(err.key) if err.key and from_flag else None
        if value is None:
            raise UsageError(str(err)) from err
        raise UsageError(f"{flag_of(str(err.key))} {value}: {err.reason}") from err


def open_logs(paths: list[str], config: Config, quiet: bool = False) -> LogReader:
    """Open the log(s); a truncated log is read as far as it is intact only with io.allow_truncated."""
    reader = open_log(paths if len(paths) > 1 else paths[0], allow_truncated=config.io.allow_truncated)
    info = truncation_of(reader)
    if info is not None and not quiet:
        sys.stderr.write(
            f"warning: log is truncated: recovered {info.recovered_messages} messages, "
            f"lost {info.lost_bytes} bytes\n"
        )
    return reader


def prepare_out_dir(out: str | None, outputs: Iterable[str] = ("config.toml",)) -> Path:
    """The output folder ``out``, created and checked before any work: it is a folder (or can be made
    one), a file can be written in it, and none of the ``outputs`` (file names the command writes there)
    exists as a folder. Every message names ``out`` as the user gave it.

    Raises:
        UsageError: ``out`` is empty.
        InputError: ``out`` is a file, cannot be created or written, or an output name is taken by a folder.
    """
    if not out:
        raise UsageError("--out DIR is required")
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"cannot create output folder {out}: {err.strerror or err}") from err
    try:
        with tempfile.NamedTemporaryFile(dir=path, prefix=".fleetcal-write-check."):
            pass
    except OSError as err:
        raise InputError(f"cannot write in output folder {out}: {err.strerror or err}") from err
    for name in outputs:
        if (path / name).is_dir():
            raise InputError(f"cannot write {name} in output folder {out}: {path / name} is a folder")
    report = path / REPORT_FOLDER
    if report.exists() and not report.is_dir():
        raise InputError(f"cannot write the report in output folder {out}: {report} is not a folder")
    return path


def write_config(config: Config, out_dir: Path) -> Path:
    return write_toml(config, out_dir / "config.toml")


def calibration_notes(calibrations: list[dict[str, Any]], rough_spread_m: float = 0.15) -> list[str]:
    """Lines under a calibration table (``PairCalibration.summary()`` dicts): why a pair is ``suspect``,
    where its translation was held, where the seeded runs spread more than ``rough_spread_m`` in
    translation although the estimate was confirmed (e.g. nuScenes' 32 beams: 31 cm), where the lidar's rings are
    sparse (``sparse_rings``: its translation is rough even where every check passes), and which translation
    components the log fixes only weakly (``weak_translation_axes``, of the camera frame
    ``translation_axes_frame``). A note that holds for every one of several pairs (a ``--joint`` rig) is
    given once, for "all N cameras"."""
    topics_of: dict[str, list[str]] = {}  # note -> the pairs it holds for, in order
    for c in calibrations:
        notes = []
        if c.get("verdict_reason"):
            notes.append(f"suspect: {c['verdict_reason']}")
        if c.get("translation_held"):
            notes.append("rotation only: the translation is held at the initial guess's")
        spread_m = c.get("translation_std_m")
        if not c.get("verdict_reason") and spread_m is not None and spread_m > rough_spread_m:
            notes.append(f"the seeded runs spread {100 * spread_m:.0f} cm in translation (RMS from the estimate): "
                         "treat the translation as rough")
        if c.get("sparse_rings") and not c.get("verdict_reason") and not c.get("translation_held"):
            notes.append(f"the lidar's rings lie {c.get('ring_spacing_deg') or float('nan'):.2f} deg apart: on rigs "
                         "this sparse the translation has come out 18-36 cm off with every check passing "
                         "(nuScenes, simulated 16 and 32 beams): treat it as rough")
        weak = c.get("weak_translation_axes") or []
        if weak and not c.get("translation_held"):
            axes = ", ".join(CAMERA_AXIS_NAMES.get(a, a) for a in weak)
            notes.append(f"the log fixes the translation only weakly along {axes} of {c.get('translation_axes_frame')}"
                         ": treat those components as rough")
        for note in notes:
            topics_of.setdefault(note, []).append(str(c["camera_topic"]))
    lines = []
    for note, topics in topics_of.items():
        if len(calibrations) > 1 and len(topics) == len(calibrations):
            lines.append(f"all {len(topics)} cameras: {note}")
        else:
            lines.extend(f"{topic}: {note}" for topic in topics)
    return lines


def table(rows: list[list[str]], header: list[str]) -> str:
    """Plain-text table with aligned columns."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(str(h).ljust(w) for h, w in zip(header, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines.extend("  ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows)
    return "\n".join(lines)
