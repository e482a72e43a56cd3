"""Helpers shared by the command modules: config from flags, opening logs, output folders."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from fleetcal.pipeline.config import Config, load_config, write_toml
from fleetcal.pipeline.errors import InputError, UsageError
from fleetcal.readers.base import LogReader
from fleetcal.readers.open import open_log, truncation_of

CAMERA_AXIS_NAMES = {"x": "x (image right)", "y": "y (image down)", "z": "z (optical axis)"}


def config_from_args(args: argparse.Namespace, overrides: dict[str, Any]) -> Config:
    """Defaults < ``--config`` TOML < ``FLEETCAL_*`` environment < command-line flags."""
    engine = {
        "engine.scheduler": getattr(args, "scheduler", None),
        "engine.workers": getattr(args, "workers", None),
    }
    return load_config(getattr(args, "config", None), overrides={**engine, **overrides})


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


def prepare_out_dir(out: str | None) -> Path:
    if not out:
        raise UsageError("--out DIR is required")
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"cannot create output folder {out}: {err.strerror}") from err
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
