"""fleetcal: targetless lidar-camera calibration (GOM) and MC-GICP mapping for robot fleet logs.

The layers are ``fleetcal.readers`` (logs -> typed frames), ``fleetcal.pipeline`` (core types),
``fleetcal.stages`` (per-frame work and aggregation) and ``fleetcal.workflows`` (recipes and the CLI).
The names below are the scripting API; they are imported on first use so that ``import fleetcal``
stays cheap.
"""

from __future__ import annotations

from importlib import import_module, metadata
from typing import TYPE_CHECKING, Any

try:
    __version__ = metadata.version("fleetcal")
except metadata.PackageNotFoundError:  # running from a checkout that was never installed
    __version__ = "0+unknown"

_API = {
    "open_log": "fleetcal.workflows.api",
    "calibrate": "fleetcal.workflows.api",
    "map_log": "fleetcal.workflows.api",
    "process_log": "fleetcal.workflows.api",
}

__all__ = ["__version__", "calibrate", "map_log", "open_log", "process_log"]

if TYPE_CHECKING:
    from fleetcal.workflows.api import calibrate, map_log, open_log, process_log


def __getattr__(name: str) -> Any:
    if name in _API:
        return getattr(import_module(_API[name]), name)
    raise AttributeError(f"module 'fleetcal' has no attribute {name!r}")
