"""Configuration: defaults, TOML, environment and CLI precedence, typed conversion, errors, round trip."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10
    import tomli as tomllib

from fleetcal.pipeline import config as config_module
from fleetcal.pipeline.config import (
    Config,
    config_from_dict,
    config_to_dict,
    load_config,
    to_toml,
    write_toml,
)
from fleetcal.pipeline.errors import ConfigError


def test_defaults() -> None:
    config = load_config(env={})
    assert config.calibration.particles == 200
    assert config.calibration.metric == "gom"
    assert config.engine.workers is None and config.engine.batch_size == 32
    assert config.io.pairing_tolerance_ns == 50_000_000
    assert config.mapping.channels == "none"


def test_precedence_file_then_env_then_cli(tmp_path: Path) -> None:
    path = tmp_path / "fleetcal.toml"
    path.write_text(
        "[calibration]\nparticles = 50\nsearch_deg = 3\nfeature = 'normals'\n"
        "[engine]\nbatch_size = 8\nworkers = 3\n"
    )
    env = {
        "FLEETCAL_CALIBRATION__PARTICLES": "80",
        "FLEETCAL_ENGINE__WORKERS": "none",
        "FLEETCAL_IO__ALLOW_TRUNCATED": "yes",
        "FLEETCAL_MAPPING__VOXEL_M": "0.5",
        "FLEETCAL_VERBOSE": "ignored: not a section__key variable",
        "HOME": "/root",
    }
    config = load_config(path, env=env, overrides={"calibration.particles": 120, "engine.batch_size": None})
    assert config.calibration.particles == 120
    assert config.calibration.search_deg == 3.0 and isinstance(config.calibration.search_deg, float)
    assert config.calibration.feature == "normals"
    assert config.engine.batch_size == 8
    assert config.engine.workers is None
    assert config.io.allow_truncated is True
    assert config.mapping.voxel_m == 0.5


@pytest.mark.parametrize(
    "env, match",
    [
        (
            {"FLEETCAL_CALIBRATION__PARTICLES": "many"},
            r"FLEETCAL_CALIBRATION__PARTICLES.*calibration\.particles",
        ),
        ({"FLEETCAL_CALIBRATION__METRIC": "mi"}, r"calibration\.metric.*gom, nmi, levinson"),
        ({"FLEETCAL_CALIBRATION__NOPE": "1"}, r"unknown config key calibration\.nope"),
        ({"FLEETCAL_NOSECTION__KEY": "1"}, r"unknown config section 'nosection'"),
        ({"FLEETCAL_IO__ALLOW_TRUNCATED": "maybe"}, r"io\.allow_truncated.*boolean"),
        ({"FLEETCAL_MAPPING__VOXEL_M": "nan"}, r"mapping\.voxel_m.*finite"),
        ({"FLEETCAL_CALIBRATION__PARTICLES": "0"}, r"calibration\.particles: must be >= 1"),
    ],
)
def test_bad_environment_values_name_the_key(env: dict[str, str], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_config(env=env)


@pytest.mark.parametrize(
    "text, match",
    [
        ("[calibration]\nparticles = 'ten'\n", r"calibration\.particles.*expected an integer"),
        ("[calibration]\nparticles = true\n", r"calibration\.particles.*boolean"),
        ("[calibration]\nsearch_m = -1.0\n", r"calibration\.search_m: must be >= 0"),
        ("[engine]\nscheduler = 'localhost'\n", r"engine\.scheduler.*tcp://HOST:PORT"),
        ("[calibraton]\nparticles = 1\n", r"unknown config section 'calibraton'"),
        ("calibration = 3\n", r"\[calibration\] must be a table"),
        ("[calibration\n", r"invalid TOML"),
    ],
)
def test_bad_files_name_the_key(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(path, env={})


def test_missing_file_and_bad_override() -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config("/nonexistent/fleetcal.toml", env={})
    with pytest.raises(ConfigError, match=r"section\.key"):
        load_config(env={}, overrides={"particles": 3})
    with pytest.raises(ConfigError, match=r"command line.*calibration\.frames"):
        load_config(env={}, overrides={"calibration.frames": "3"})


def test_write_toml_round_trips_and_is_atomic(tmp_path: Path) -> None:
    config = load_config(
        env={"FLEETCAL_ENGINE__SCHEDULER": "tcp://10.0.0.1:8786"},
        overrides={"calibration.search_deg": 2.5, "calibration.feature": "range", "mapping.k": 12},
    )
    path = write_toml(config, tmp_path / "config.toml")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.toml"]
    parsed = tomllib.loads(path.read_text())
    assert parsed["engine"]["scheduler"] == "tcp://10.0.0.1:8786"
    assert "workers" not in parsed["engine"]
    assert load_config(path, env={}) == config
    assert config_from_dict(parsed) == config
    assert config_to_dict(config)["engine"]["workers"] is None


def test_write_toml_failure_leaves_no_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(_: Config) -> str:
        raise ConfigError("cannot serialise")

    monkeypatch.setattr(config_module, "to_toml", broken)
    with pytest.raises(ConfigError):
        write_toml(Config(), tmp_path / "config.toml")
    assert list(tmp_path.iterdir()) == []


def test_strings_with_quotes_survive_the_round_trip(tmp_path: Path) -> None:
    config = Config()
    config.engine.scheduler = 'tcp://host:1 "quoted" \\ back'
    text = to_toml(config)
    assert tomllib.loads(text)["engine"]["scheduler"] == config.engine.scheduler


def test_new_fields_and_lists_convert_by_type(monkeypatch: pytest.MonkeyPatch) -> None:
    @dataclass
    class Extra:
        names: list[str] = field(default_factory=lambda: ["a"])
        weights: list[float] = field(default_factory=list)
        limit: int | None = None

    @dataclass
    class BigConfig(Config):
        extra: Extra = field(default_factory=Extra)

    monkeypatch.setattr(config_module, "Config", BigConfig)
    config = load_config(
        env={
            "FLEETCAL_EXTRA__NAMES": "x, y",
            "FLEETCAL_EXTRA__WEIGHTS": "1, 2.5",
            "FLEETCAL_EXTRA__LIMIT": "7",
        }
    )
    assert isinstance(config, BigConfig)
    assert config.extra.names == ["x", "y"] and config.extra.weights == [1.0, 2.5] and config.extra.limit == 7
    assert tomllib.loads(to_toml(config))["extra"] == {"names": ["x", "y"], "weights": [1.0, 2.5], "limit": 7}


def test_gradient_settings_follow_the_viewpoint() -> None:
    """The solver's ``auto``: the lidar's own sphere (least squares, neighbours across rings) in every box,
    exploring only in wide ones; the paper's camera sphere (Algorithm 1, nearest-by-angle neighbours) where
    code asks for it; explicit choices win. These are solver internals, not user settings."""
    from fleetcal.workflows.calibrate import solver_config

    solver = solver_config(Config())
    assert (solver.viewpoint, solver.fit, solver.neighbours_on("lidar")) == ("lidar", "lsq", "sampling")
    assert not solver.explores and not solver.wide_box
    solver = solver_config(load_config(env={"FLEETCAL_CALIBRATION__SEARCH_M": "1.0"}))
    assert (solver.viewpoint, solver.fit, solver.neighbours_on("lidar")) == ("lidar", "lsq", "sampling")
    assert solver.explores and solver.wide_box
    assert solver.neighbours_on("camera") == "angle"  # Levinson's depth jumps stay on the camera sphere
    camera = replace(solver, gradient_viewpoint="camera")
    assert (camera.viewpoint, camera.fit, camera.neighbours_on("camera")) == ("camera", "paper", "angle")
    camera = replace(camera, neighbours_by="sampling")
    assert (camera.viewpoint, camera.fit, camera.neighbours_on("camera")) == ("camera", "paper", "sampling")
    with pytest.raises(ConfigError, match="neighbours_by"):
        replace(solver, neighbours_by="rings").validate()
    with pytest.raises(ConfigError, match="ring_smoothing"):
        replace(solver, ring_smoothing_fraction=0.0).validate()


def test_solver_internals_are_not_user_settings() -> None:
    """Settings of the solver's internals are rejected in the user configuration (exit 2 from the CLI)."""
    for key in ("GRADIENT_VIEWPOINT", "RING_SMOOTHING", "CONFIRM_REPEATS", "KEEP_FRACTION", "EXPLORE"):
        with pytest.raises(ConfigError, match=key.lower()):
            load_config(env={f"FLEETCAL_CALIBRATION__{key}": "1"})


def test_translation_setting_reaches_the_solver_and_a_zero_box_holds_it() -> None:
    from fleetcal.workflows.calibrate import solver_config

    assert solver_config(Config()).translation == "auto"
    assert not solver_config(Config()).holds_translation
    held = load_config(env={"FLEETCAL_CALIBRATION__TRANSLATION": "hold"})
    assert solver_config(held).holds_translation
    zero_box = solver_config(load_config(env={"FLEETCAL_CALIBRATION__SEARCH_M": "0"}))
    zero_box.validate()
    assert zero_box.holds_translation
    with pytest.raises(ConfigError, match=r"calibration\.translation.*auto, estimate, hold"):
        load_config(env={"FLEETCAL_CALIBRATION__TRANSLATION": "free"})
    with pytest.raises(ConfigError, match="translation"):
        replace(solver_config(Config()), translation="free").validate()


def test_calibrate_keeps_a_dozen_options_of_its_own() -> None:
    """``calibrate`` has at most 12 options besides the ones every command, or every command that reads logs,
    takes; the camera-to-camera affine mode is its own command."""
    from fleetcal.workflows.cli import build_parser, common_options, log_options

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    common = {s for parent in (common_options(), log_options()) for a in parent._actions for s in a.option_strings}
    own = [a for a in sub.choices["calibrate"]._actions if a.option_strings and not set(a.option_strings) & common
           and "--help" not in a.option_strings]
    assert len(own) <= 12, [a.option_strings for a in own]
    args = parser.parse_args(["calibrate-cameras", "x.mcap", "--camera", "/a", "--camera", "/b", "--out", "o"])
    assert args.camera == ["/a", "/b"]
    with pytest.raises(SystemExit):
        parser.parse_args(["calibrate", "x.mcap", "--out", "o", "--camera-camera"])


def test_point_times_setting_reaches_the_config() -> None:
    assert Config().calibration.point_times is True
    assert load_config(env={}).calibration.point_times is True
    assert load_config(env={"FLEETCAL_CALIBRATION__POINT_TIMES": "false"}).calibration.point_times is False


def test_rectified_topics_setting_reaches_the_config() -> None:
    assert Config().io.rectified_topics == []
    env = {"FLEETCAL_IO__RECTIFIED_TOPICS": "/c/image,/d/image"}
    assert load_config(env=env).io.rectified_topics == ["/c/image", "/d/image"]
