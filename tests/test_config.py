"""Configuration: defaults, TOML, environment and CLI precedence, typed conversion, errors, round trip."""

from __future__ import annotations

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
    assert config.mapping.channels == "intensity"


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
        ({"FLEETCAL_CALIBRATION__CONFIRM_REPEATS": "-1"}, r"calibration\.confirm_repeats: must be >= 0"),
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
    """``auto``: the lidar's own sphere (least squares, neighbours across rings) in every box, exploring
    only in wide ones; the paper's camera sphere (Algorithm 1, nearest-by-angle neighbours) on request;
    explicit choices win."""
    from fleetcal.workflows.calibrate import solver_config

    config = Config()
    assert config.calibration.gradient_viewpoint == "auto"
    solver = solver_config(config)
    assert (solver.viewpoint, solver.fit, solver.neighbours_on("lidar")) == ("lidar", "lsq", "sampling")
    assert not solver.explores and not solver.wide_box
    config.calibration.search_m = 1.0
    solver = solver_config(config)
    assert (solver.viewpoint, solver.fit, solver.neighbours_on("lidar")) == ("lidar", "lsq", "sampling")
    assert solver.explores and solver.wide_box
    assert solver.neighbours_on("camera") == "angle"  # Levinson's depth jumps stay on the camera sphere
    config.calibration.gradient_viewpoint = "camera"
    solver = solver_config(config)
    assert (solver.viewpoint, solver.fit, solver.neighbours_on("camera")) == ("camera", "paper", "angle")
    config.calibration.gradient_viewpoint = "camera"
    config.calibration.gradient_neighbours = "sampling"
    config.calibration.gradient_fit = "lsq"
    solver = solver_config(config)
    assert (solver.viewpoint, solver.fit, solver.neighbours_on("camera")) == ("camera", "lsq", "sampling")
    with pytest.raises(ConfigError, match="neighbours_by"):
        replace(solver, neighbours_by="rings").validate()


def test_confirm_repeats_reaches_the_solver() -> None:
    from fleetcal.workflows.calibrate import solver_config

    assert solver_config(Config()).confirm_repeats == 3
    config = load_config(env={"FLEETCAL_CALIBRATION__CONFIRM_REPEATS": "0"})
    assert solver_config(config).confirm_repeats == 0


def test_ring_smoothing_reaches_the_solver_and_rejects_other_values() -> None:
    from fleetcal.workflows.calibrate import solver_config

    assert solver_config(Config()).ring_smoothing == "auto"
    config = load_config(env={"FLEETCAL_CALIBRATION__RING_SMOOTHING": "off"})
    assert solver_config(config).ring_smoothing == "off"
    with pytest.raises(ConfigError, match=r"calibration\.ring_smoothing.*auto, on, off"):
        load_config(env={"FLEETCAL_CALIBRATION__RING_SMOOTHING": "maybe"})
    with pytest.raises(ConfigError, match="ring_smoothing"):
        replace(solver_config(Config()), ring_smoothing_fraction=0.0).validate()


def test_translation_flag_reaches_the_solver_and_a_zero_box_holds_it() -> None:
    from fleetcal.workflows.calibrate import solver_config
    from fleetcal.workflows.cli import build_parser
    from fleetcal.workflows.cmd_calibrate import overrides

    parser = build_parser()
    assert solver_config(Config()).translation == "auto"
    assert not solver_config(Config()).holds_translation
    held = overrides(parser.parse_args(["calibrate", "x.mcap", "--out", "o", "--translation", "hold"]))
    assert solver_config(load_config(env={}, overrides=held)).holds_translation
    zero_box = solver_config(load_config(env={"FLEETCAL_CALIBRATION__SEARCH_M": "0"}))
    zero_box.validate()
    assert zero_box.holds_translation
    with pytest.raises(ConfigError, match=r"calibration\.translation.*auto, estimate, hold"):
        load_config(env={"FLEETCAL_CALIBRATION__TRANSLATION": "free"})
    with pytest.raises(ConfigError, match="translation"):
        replace(solver_config(Config()), translation="free").validate()
    with pytest.raises(SystemExit):
        parser.parse_args(["calibrate", "x.mcap", "--out", "o", "--translation", "free"])


def test_no_point_times_flag_reaches_the_config() -> None:
    from fleetcal.workflows.cli import build_parser
    from fleetcal.workflows.cmd_calibrate import overrides

    parser = build_parser()
    on = overrides(parser.parse_args(["calibrate", "x.mcap", "--out", "o"]))
    off = overrides(parser.parse_args(["calibrate", "x.mcap", "--out", "o", "--no-point-times"]))
    assert Config().calibration.point_times is True
    assert load_config(env={}, overrides=on).calibration.point_times is True
    assert load_config(env={}, overrides=off).calibration.point_times is False


def test_rectified_topic_flags_and_environment_reach_the_config() -> None:
    from fleetcal.workflows.cli import build_parser
    from fleetcal.workflows.cmd_calibrate import overrides

    parser = build_parser()
    args = parser.parse_args(["calibrate", "x.mcap", "--out", "o", "--rectified-topic", "/a/image",
                              "--rectified-topic", "/b/image"])
    assert Config().io.rectified_topics == []
    assert load_config(env={}, overrides=overrides(args)).io.rectified_topics == ["/a/image", "/b/image"]
    none = overrides(parser.parse_args(["calibrate", "x.mcap", "--out", "o"]))
    assert load_config(env={}, overrides=none).io.rectified_topics == []
    env = {"FLEETCAL_IO__RECTIFIED_TOPICS": "/c/image,/d/image"}
    assert load_config(env=env).io.rectified_topics == ["/c/image", "/d/image"]
