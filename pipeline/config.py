"""Typed configuration: dataclass sections loaded from TOML, environment and CLI overrides.

Precedence (lowest first): the defaults below, a TOML file (``--config fleetcal.toml``), environment
variables ``FLEETCAL_<SECTION>__<KEY>=value`` (e.g. ``FLEETCAL_CALIBRATION__PARTICLES=100``), then
overrides from the command line (``{"calibration.particles": 100}``; ``None`` values are ignored so
unset argparse options do not override).

To add a setting, add a typed field with a default to its section dataclass (supported types:
``bool``, ``int``, ``float``, ``str``, ``Literal[...]`` of str, ``list[int|float|str]`` and
``X | None``), and, if it has a range, a check in that section's ``validate``. To add a section, add a
dataclass and a field of that type on ``Config``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import types
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10
    import tomli as tomllib

from fleetcal.pipeline.errors import ConfigError

__all__ = [
    "CalibrationConfig",
    "Config",
    "EngineConfig",
    "IoConfig",
    "MappingConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "to_toml",
    "write_toml",
]

ENV_PREFIX = "FLEETCAL_"
COMMAND_LINE = "command line"
"""The source named for ``load_config``'s ``overrides`` in its errors."""


@dataclass
class IoConfig:
    """Reading logs.

    Attributes:
        pairing_tolerance_ns: largest lidar/camera stamp difference for a pair, ns.
        allow_truncated: read what is left of a truncated log instead of failing.
        rectified_topics: image topics whose images are rectified although their names do not say so
            (ROS names them ``image_rect``...): projected with the CameraInfo's P and R, no distortion.
        max_range_m: lidar points farther than this from the sensor are dropped at decode (counted in
            ``LidarFrame.dropped_points``), metres. The default, 1000 m, is above the longest range any
            automotive or survey lidar on fleet robots reports (600 m and less), so it removes only
            corrupt values (1e30, denormal garbage) that would otherwise reach voxel grids and KD-trees.
    """

    pairing_tolerance_ns: int = 50_000_000
    allow_truncated: bool = False
    rectified_topics: list[str] = field(default_factory=list)
    max_range_m: float = 1000.0

    def validate(self) -> None:
        _require(self.pairing_tolerance_ns >= 0, "io.pairing_tolerance_ns", "must be >= 0")
        _require(self.max_range_m > 0, "io.max_range_m", "must be > 0")


@dataclass
class EngineConfig:
    """Running per-frame stages (``pipeline.engine.Engine``).

    Attributes:
        workers: local worker processes (None: one per core; 0: in-process).
        scheduler: ``tcp://HOST:PORT`` of an existing dask scheduler (None: local).
        batch_size: frames per task.
        max_in_flight: tasks submitted at once (None: 2 per worker + 1).
        retries: times a failed task is retried.
    """

    workers: int | None = None
    scheduler: str | None = None
    batch_size: int = 32
    max_in_flight: int | None = None
    retries: int = 2

    def validate(self) -> None:
        _require(self.workers is None or self.workers >= 0, "engine.workers", "must be >= 0")
        _require(self.batch_size >= 1, "engine.batch_size", "must be >= 1")
        in_flight_ok = self.max_in_flight is None or self.max_in_flight >= 1
        _require(in_flight_ok, "engine.max_in_flight", "must be >= 1")
        _require(self.retries >= 0, "engine.retries", "must be >= 0")
        _require(
            self.scheduler is None or "://" in self.scheduler,
            "engine.scheduler",
            "must be an address like tcp://HOST:PORT",
        )


LIDAR_FEATURES = ("intensity", "range", "normals", "log_range")


def feature_names(spec: str) -> list[str]:
    """The lidar features of a spec: one of ``LIDAR_FEATURES`` or several joined by ``+``
    (``range+normals``).

    Raises:
        ConfigError: an unknown or repeated name.
    """
    names = [n.strip() for n in str(spec).split("+")]
    if any(n not in LIDAR_FEATURES for n in names) or len(set(names)) != len(names):
        reason = (f"unknown or repeated lidar feature in {spec!r}; expected one or several of "
                  f"{', '.join(LIDAR_FEATURES)} joined by '+'")
        raise ConfigError(f"bad value for calibration.feature: {reason}", "calibration.feature", reason)
    return names


@dataclass
class CalibrationConfig:
    """Targetless lidar-camera calibration (GOM paper).

    Attributes:
        metric: alignment metric.
        feature: lidar per-point feature (GOM section 3.1): ``auto`` (default) or one of ``LIDAR_FEATURES``
            or several joined by ``+`` (``range+normals``: each feature gets its own lidar gradients and the
            frame's score is their mean; about twice the runtime of one feature). ``auto`` (GOM) searches with
            ``range+normals`` unless the scans carry an intensity that varies and the frames show the image
            following it: its score falls significantly further than range+normals' when the pose turns
            off alignment (``stages.calibration.config.SolverConfig.feature_groups``; never on a one-frame
            log); the parquet's ``feature`` column says which was used. Other metrics: ``range+normals``.
        frames: lidar/camera pairs used, spread over the log (every pair where the log has fewer). Frames are
            the calibration's evidence: over 12 calibrations of simulated 16-beam drives, 40 frames landed 9
            within 0.3 deg / 10 cm and 1 beyond 0.5 deg, 10 frames 3 and 6, for 1.5-2x the time of 10
            (``benchmarks/bench_frames.py``, docs/accuracy.md "How many frames").
        particles: particle swarm size.
        iterations: particle swarm iterations.
        search_deg: half-width of the rotation search around the initial guess, degrees.
        search_m: half-width of the translation search, metres (0: the translation is held).
        translation: ``estimate`` (6 DoF), ``hold`` (rotation only, the translation kept at the initial
            guess's) or ``auto`` (default): estimated, but held where the seeded 6-DoF runs do not confirm
            one another and the box is within 5 deg / 0.5 m (the initial guess is trusted); evidence in
            ``stages.calibration.config.SolverConfig``.
        repeats: seeded optimiser runs (up to three more while no run confirms the best); their spread is
            the reported uncertainty.
        estimate_focal: also estimate a common scale of fx and fy.
        motion_compensation: move lidar points to the camera stamp with the log's /tf odometry.
        point_times: with ``motion_compensation``, a scan with a per-point time field (all within 0.5 s of
            its stamp) moves each point from its own capture time, with the lidar's velocity over the
            sweep from /tf; false: the whole scan from its stamp (for clouds the driver de-skewed but
            that still carry their firing times).
        camera_model: projection of the images: ``log`` (default: the CameraInfo's distortion model) or
            one that replaces it with the same K and D: ``plumb_bob``, ``rational_polynomial``,
            ``equidistant`` (fisheye), ``cylindrical`` (the GOM paper's panoramic model, eq. 6: u =
            fx * azimuth + cx, v = fy * y / sqrt(x^2 + z^2) + cy) or ``none`` (pinhole, D ignored).
        time_offset: ``fixed`` (default: the camera and lidar clocks agree) or ``estimate``: find the camera's
            clock minus the lidar's (``time_offset_s``), within +-``time_range_s``, from how the rig's motion
            differs between frames (turns, speed changes); ``unobservable`` where it does not.
        readout: ``fixed`` (default: ``readout_s``) or ``estimate``: find one rolling-shutter readout for the
            cameras, within 0 to 2 x ``time_range_s``.
        readout_s: known rolling-shutter readouts, first to last image row, seconds: ``"0.03"`` for every
            camera, ``"/cam/image_raw=0.03"`` for one topic (later entries win); unnamed cameras: 0 (global
            shutter).
        time_range_s: half-width of the clock offset's search, seconds.
    """

    metric: Literal["gom", "nmi", "levinson"] = "gom"
    feature: str = "auto"
    frames: int = 40
    particles: int = 200
    iterations: int = 100
    search_deg: float = 5.0
    search_m: float = 0.5
    translation: Literal["auto", "estimate", "hold"] = "auto"
    repeats: int = 2
    estimate_focal: bool = False
    motion_compensation: bool = True
    point_times: bool = True
    camera_model: Literal["log", "plumb_bob", "rational_polynomial", "equidistant", "cylindrical", "none"] = "log"
    time_offset: Literal["fixed", "estimate"] = "fixed"
    readout: Literal["fixed", "estimate"] = "fixed"
    readout_s: list[str] = field(default_factory=list)
    time_range_s: float = 0.05

    def readout_of(self, topic: str) -> float:
        """The known rolling-shutter readout of the camera on ``topic`` (``readout_s``), seconds."""
        value = 0.0
        for entry in self.readout_s:
            name, sep, seconds = entry.rpartition("=")
            if not sep or name == topic:
                value = float(seconds)
        return value

    def validate(self) -> None:
        if self.feature != "auto":
            feature_names(self.feature)
        for entry in self.readout_s:
            seconds = entry.rpartition("=")[2]
            try:
                ok = 0.0 <= float(seconds) <= 1.0
            except ValueError:
                ok = False
            _require(ok, "calibration.readout_s", f"entries are SECONDS or TOPIC=SECONDS in [0, 1], got {entry!r}")
        _require(0 < self.time_range_s <= 1.0, "calibration.time_range_s", "must be in (0, 1] s")
        _require(self.frames >= 1, "calibration.frames", "must be >= 1")
        _require(self.particles >= 1, "calibration.particles", "must be >= 1")
        _require(self.iterations >= 1, "calibration.iterations", "must be >= 1")
        _require(0 <= self.search_deg <= 180, "calibration.search_deg", "must be in [0, 180]")
        _require(self.search_m >= 0, "calibration.search_m", "must be >= 0")
        _require(self.repeats >= 1, "calibration.repeats", "must be >= 1")


@dataclass
class MappingConfig:
    """Lidar odometry and mapping (MC-GICP).

    Attributes:
        channels: per-point channels used by the registration: ``none`` is GICP, the others MC-GICP. With
            these settings MC-GICP gave GICP's trajectory wherever measured: the real KITTI drive at 8-28 %
            more time per scan, the simulated poster corridor (texture alone fixes the motion along its
            walls) 100 % drift either way; there it holds the motion only with 0.05 m voxels and a keyframe
            every 0.1 m (``stages.registration.odometry.run_odometry``), 4-5 % drift.
        voxel_m: voxel size of the downsampling, metres.
        k: neighbours for the GICP covariances.
        max_corr_m: largest correspondence distance, metres.
        max_iterations: registration iterations per scan.
        map_voxel_m: voxel size of the written map, metres.
        robust_kernel: none | huber | cauchy on the registration residuals.
        use_tf_odometry: initial guesses from the log's /tf odometry when it has one.
        deskew: move each point of a scan with per-point times (``time`` channel) from its firing time
            to the scan stamp with the odometry's motion (``stages.registration.deskew``). Turn it off
            for clouds already de-skewed by their driver that still carry firing times.
        first_motion_max_m: without /tf odometry, the largest motion between the first two scans looked
            for (their registration's first, coarse pass), metres (``run_odometry``); 0: no coarse pass.
        max_speed_m_s: odometry faster than this between two scans is implausible: the scan is warned
            about and counted (``implausible_motion`` in the summary), m/s. The default, 70 m/s (252 km/h),
            is above the top speed of the road vehicles that carry lidars.
    """

    channels: Literal["none", "intensity", "color", "combined"] = "none"
    voxel_m: float = 0.25
    k: int = 20
    max_corr_m: float = 1.0
    max_iterations: int = 30
    map_voxel_m: float = 0.1
    robust_kernel: Literal["none", "huber", "cauchy"] = "cauchy"
    use_tf_odometry: bool = True
    deskew: bool = True
    first_motion_max_m: float = 4.0
    max_speed_m_s: float = 70.0

    def validate(self) -> None:
        _require(self.voxel_m > 0, "mapping.voxel_m", "must be > 0")
        _require(self.k >= 3, "mapping.k", "must be >= 3")
        _require(self.max_corr_m > 0, "mapping.max_corr_m", "must be > 0")
        _require(self.max_iterations >= 1, "mapping.max_iterations", "must be >= 1")
        _require(self.map_voxel_m > 0, "mapping.map_voxel_m", "must be > 0")
        _require(self.first_motion_max_m >= 0, "mapping.first_motion_max_m", "must be >= 0")
        _require(self.max_speed_m_s > 0, "mapping.max_speed_m_s", "must be > 0")


@dataclass
class Config:
    """The whole configuration: one attribute per section (TOML table)."""

    io: IoConfig = field(default_factory=IoConfig)
    engine: EngineConfig = field(default_factory=EngineConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)

    def validate(self) -> None:
        """Check every section's ranges; raises ConfigError naming the key."""
        for f in dataclasses.fields(self):
            section = getattr(self, f.name)
            check = getattr(section, "validate", None)
            if check is not None:
                check()


def load_config(
    path: str | os.PathLike[str] | None = None,
    env: Mapping[str, str] | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> Config:
    """The effective configuration: defaults < TOML file < environment < overrides.

    Args:
        path: TOML file, or None for none.
        env: environment to read ``FLEETCAL_<SECTION>__<KEY>`` from (default ``os.environ``); other
            ``FLEETCAL_`` variables without ``__`` are ignored.
        overrides: ``{"section.key": value}``, e.g. from CLI flags; ``None`` values are skipped.

    Raises:
        ConfigError: unreadable/invalid TOML, an unknown section or key, a value of the wrong type
            or out of range; the message names the key and where it came from.
    """
    data: dict[str, dict[str, Any]] = {}
    if path is not None:
        data = _read_toml(Path(path))
    config = config_from_dict(data, source=str(path) if path is not None else "defaults")
    environ = os.environ if env is None else env
    for name, raw in sorted(environ.items()):
        if not name.startswith(ENV_PREFIX) or "__" not in name[len(ENV_PREFIX):]:
            continue
        section, _, key = name[len(ENV_PREFIX):].partition("__")
        _set(config, section.lower(), key.lower(), raw, source=f"environment variable {name}", from_text=True)
    for dotted, value in (overrides or {}).items():
        if value is None:
            continue
        section, sep, key = dotted.partition(".")
        if not sep:
            raise ConfigError(f"override {dotted!r} must be 'section.key'")
        _set(config, section, key, value, source=COMMAND_LINE, from_text=False)
    config.validate()
    return config


def config_from_dict(data: Mapping[str, Any], source: str = "dict") -> Config:
    """A Config from nested ``{section: {key: value}}`` (as TOML gives); validated.

    Raises:
        ConfigError: unknown section/key or bad value (the message names it and ``source``).
    """
    config = Config()
    for section, table in data.items():
        if not isinstance(table, Mapping):
            raise ConfigError(f"{source}: [{section}] must be a table, got {type(table).__name__}")
        for key, value in table.items():
            _set(config, section, key, value, source=source, from_text=False)
    config.validate()
    return config


def config_to_dict(config: Config) -> dict[str, dict[str, Any]]:
    """Nested ``{section: {key: value}}`` of every setting (None included)."""
    return {f.name: dataclasses.asdict(getattr(config, f.name)) for f in dataclasses.fields(config)}


def to_toml(config: Config) -> str:
    """TOML text of the config; settings that are None are written as comments (TOML has no null)."""
    lines: list[str] = ["# fleetcal effective configuration"]
    for section, table in config_to_dict(config).items():
        lines.append("")
        lines.append(f"[{section}]")
        for key, value in table.items():
            if value is None:
                lines.append(f"# {key} = (unset)")
            else:
                lines.append(f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def write_toml(config: Config, path: str | os.PathLike[str]) -> Path:
    """Write ``to_toml(config)`` to ``path`` atomically (temporary file in the folder, then rename).

    Raises:
        OSError: the file cannot be written; its ``filename`` is ``path`` (not the temporary file's).
    """
    final = Path(path)
    tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(to_toml(config), encoding="utf-8")
        os.replace(tmp, final)
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(final)) from err
    finally:
        if tmp.exists():
            tmp.unlink()
    return final


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError as err:
        raise ConfigError(f"config file not found: {path}") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: invalid TOML ({err})") from err
    except OSError as err:
        raise ConfigError(f"cannot read config file {path}: {err.strerror or err}") from err


def _set(config: Config, section: str, key: str, value: Any, *, source: str, from_text: bool) -> None:
    sections = {f.name for f in dataclasses.fields(config)}
    if section not in sections:
        known = ", ".join(sorted(sections))
        raise ConfigError(f"{source}: unknown config section {section!r} (known: {known})")
    obj = getattr(config, section)
    hints = typing.get_type_hints(type(obj))
    names = [f.name for f in dataclasses.fields(obj)]
    if key not in names:
        raise ConfigError(f"{source}: unknown config key {section}.{key} (known: {', '.join(names)})")
    try:
        converted = _convert(value, hints[key], from_text)
    except (TypeError, ValueError) as err:
        message = f"{source}: bad value {value!r} for {section}.{key}: {err}"
        raise ConfigError(message, f"{section}.{key}", str(err), source) from err
    setattr(obj, key, converted)


def _convert(value: Any, tp: Any, from_text: bool) -> Any:
    """``value`` as the settings' type ``tp`` (optional, Literal, list / tuple, bool, int, float, str); text from
    the environment or flags (``from_text``) is parsed, other values must already have the type."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return _to_optional(value, tp, from_text)
    if origin is Literal:
        text = value.strip() if from_text and isinstance(value, str) else value
        if text not in typing.get_args(tp):
            raise ValueError(f"expected one of {', '.join(map(str, typing.get_args(tp)))}")
        return text
    if origin in (list, tuple):
        return _to_list(value, typing.get_args(tp), from_text)
    scalar = _SCALARS.get(tp)
    if scalar is None:
        raise TypeError(f"unsupported config type {tp}")
    return scalar(value, from_text)


def _to_optional(value: Any, tp: Any, from_text: bool) -> Any:
    inner = [a for a in typing.get_args(tp) if a is not type(None)]
    if from_text and isinstance(value, str) and value.strip().lower() in ("", "none", "null"):
        return None
    if value is None:
        return None
    if len(inner) != 1:
        raise TypeError(f"unsupported config type {tp}")
    return _convert(value, inner[0], from_text)


def _to_list(value: Any, args: tuple[Any, ...], from_text: bool) -> list[Any]:
    item_tp = args[0] if args else str
    if from_text and isinstance(value, str):
        items: list[Any] = [v for v in (s.strip() for s in value.split(",")) if v]
    elif isinstance(value, (list, tuple)):
        items = list(value)
    else:
        raise TypeError(f"expected a list, got {type(value).__name__}")
    return [_convert(v, item_tp, from_text) for v in items]


def _to_bool(value: Any, from_text: bool) -> bool:
    if isinstance(value, bool):
        return value
    if from_text and isinstance(value, str):
        text = value.strip().lower()
        if text in ("1", "true", "yes", "on"):
            return True
        if text in ("0", "false", "no", "off"):
            return False
    raise ValueError("expected a boolean (true/false)")


def _to_int(value: Any, from_text: bool) -> int:
    if isinstance(value, bool):
        raise TypeError("expected an integer, got a boolean")
    if isinstance(value, int):
        return value
    if from_text and isinstance(value, str):
        return int(value.strip().replace("_", ""))
    raise TypeError(f"expected an integer, got {type(value).__name__}")


def _to_float(value: Any, from_text: bool) -> float:
    if isinstance(value, bool):
        raise TypeError("expected a number, got a boolean")
    if isinstance(value, (int, float)):
        number = float(value)
    elif from_text and isinstance(value, str):
        number = float(value.strip())
    else:
        raise TypeError(f"expected a number, got {type(value).__name__}")
    if not math.isfinite(number):
        raise ValueError("expected a finite number")
    return number


def _to_str(value: Any, from_text: bool) -> str:
    if not isinstance(value, str):
        raise TypeError(f"expected a string, got {type(value).__name__}")
    return value


_SCALARS: dict[Any, Callable[[Any, bool], Any]] = {bool: _to_bool, int: _to_int, float: _to_float, str: _to_str}
"""Converters of the settings' scalar types."""


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise ConfigError(f"cannot write {type(value).__name__} value {value!r} to TOML")


def _require(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"bad value for {key}: {message}", key, message)
