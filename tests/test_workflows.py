"""End-to-end workflows on a small simulated log: calibrate, map, process; the Parquet contract of
DESIGN.md; the write-back tf equals calibration.parquet; CLI errors are one line with the right code."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from fleetcal.pipeline.transforms import from_quat, invert, rotation_error_deg, translation_error_m
from fleetcal.readers.decode import decode_tf
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration.uncertainty import OBJECTIVE_BIAS_DEG
from fleetcal.workflows.cli import main

SMALL_CONFIG = """
[calibration]
frames = 3
particles = 60
iterations = 30
feature = "range"

[mapping]
voxel_m = 0.4
"""

CALIBRATION_COLUMNS = {
    "lidar_topic": pa.string(), "camera_topic": pa.string(), "lidar_frame": pa.string(),
    "camera_frame": pa.string(), "metric": pa.string(), "feature": pa.string(),
    "tx_m": pa.float64(), "ty_m": pa.float64(), "tz_m": pa.float64(), "qx": pa.float64(), "qy": pa.float64(),
    "qz": pa.float64(), "qw": pa.float64(), "roll_deg": pa.float64(), "pitch_deg": pa.float64(),
    "yaw_deg": pa.float64(), "score": pa.float64(), "initial_score": pa.float64(), "frames_used": pa.int64(),
    "runtime_s": pa.float64(), "verdict": pa.string(), "verdict_reason": pa.string(),
    "std_rx_deg": pa.float64(), "std_ry_deg": pa.float64(), "std_rz_deg": pa.float64(),
    "std_tx_m": pa.float64(), "std_ty_m": pa.float64(), "std_tz_m": pa.float64(), "initialisation": pa.string(),
    "initial_candidates": pa.int64(), "time_offset_s": pa.float64(), "time_offset_std_s": pa.float64(),
    "readout_s": pa.float64(), "readout_std_s": pa.float64(), "motion_source": pa.string(),
}  # fmt: skip
TRAJECTORY_COLUMNS = {
    "stamp_ns": pa.int64(), "tx_m": pa.float64(), "ty_m": pa.float64(), "tz_m": pa.float64(),
    "qx": pa.float64(), "qy": pa.float64(), "qz": pa.float64(), "qw": pa.float64(), "fitness": pa.float64(),
    "rmse_m": pa.float64(), "iterations": pa.int32(),
}  # fmt: skip
MAP_COLUMNS = {"x_m": pa.float32(), "y_m": pa.float32(), "z_m": pa.float32(), "intensity": pa.float32(),
               "r": pa.uint8(), "g": pa.uint8(), "b": pa.uint8()}  # fmt: skip


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("sim")
    log = root / "street.mcap"
    code = main(["simulate", str(log), "--frames", "6", "--beams", "32", "--columns", "1024",
                 "--image-size", "640x360", "--seed", "3", "-q"])  # fmt: skip
    assert code == 0
    (root / "small.toml").write_text(SMALL_CONFIG)
    return log


@pytest.fixture(scope="module")
def processed(sim_log: Path) -> Path:
    out = sim_log.parent / "out"
    code = main(["process", str(sim_log), "--out", str(out), "--config", str(sim_log.parent / "small.toml"),
                 "--workers", "0", "-q"])  # fmt: skip
    assert code == 0
    return out


def _schema(path: Path) -> dict[str, pa.DataType]:
    return {f.name: f.type for f in pq.read_schema(path)}


def test_parquet_contract(processed: Path) -> None:
    assert _schema(processed / "calibration.parquet") == CALIBRATION_COLUMNS
    assert _schema(processed / "trajectory.parquet") == TRAJECTORY_COLUMNS
    assert _schema(processed / "map.parquet") == MAP_COLUMNS
    frames = _schema(processed / "frames.parquet")
    assert {"topic", "stamp_ns", "n_points", "width", "height", "score_initial", "score_final"} <= set(frames)
    pandas = pytest.importorskip("pandas")
    calib = pandas.read_parquet(processed / "calibration.parquet")
    assert len(calib) == 1 and calib.loc[0, "frames_used"] == 3
    result = json.loads((processed / "result.json").read_text())["calibrations"][0]
    assert calib.loc[0, "verdict"] == result["verdict"] and calib.loc[0, "initialisation"] == "tf"
    assert calib.loc[0, "initial_candidates"] == 0
    rotation = calib.loc[0, ["std_rx_deg", "std_ry_deg", "std_rz_deg"]].to_numpy(dtype=float)
    translation = calib.loc[0, ["std_tx_m", "std_ty_m", "std_tz_m"]].to_numpy(dtype=float)
    assert np.all(rotation >= OBJECTIVE_BIAS_DEG)  # at least the objective's own bias
    assert np.all(translation > 0)  # estimated, or held where the 6-DoF runs disagreed: their spread
    assert np.isnan(calib.loc[0, "time_offset_s"]) and calib.loc[0, "motion_source"] in ("tf", "none")
    q = calib.loc[0, ["qx", "qy", "qz", "qw"]].to_numpy(dtype=float)
    assert abs(np.linalg.norm(q) - 1) < 1e-9


def test_process_outputs_are_complete(processed: Path, sim_log: Path) -> None:
    names = {p.name for p in processed.iterdir()}
    assert {"calibration.parquet", "frames.parquet", "trajectory.parquet", "map.parquet", "config.toml",
            "result.json", "street.fleetcal.mcap", "report"} <= names  # fmt: skip
    assert not [n for n in names if ".tmp" in n]
    report = {p.name for p in (processed / "report").iterdir()}
    assert {"map_top.png", "overlay_before_camera_0_image_raw.png", "overlay_after_camera_0_image_raw.png"} <= report
    result = json.loads((processed / "result.json").read_text())
    assert result["mapping"]["scans"] == 6
    trajectory = pq.read_table(processed / "trajectory.parquet").to_pandas()
    truth = json.loads(sim_log.with_name("street.truth.json").read_text())
    T_true = [np.asarray(t["T_map_lidar"]) for t in truth["trajectory"]]
    T_est = [from_quat(r[["tx_m", "ty_m", "tz_m"]].to_numpy(float), r[["qx", "qy", "qz", "qw"]].to_numpy(float))
             for _, r in trajectory.iterrows()]  # fmt: skip
    assert len(T_est) == len(T_true)
    final_error = translation_error_m(T_est[-1], T_true[-1])
    path = sum(translation_error_m(a, b) for a, b in itertools.pairwise(T_true))
    assert path > 2.0
    assert final_error / path < 0.02


def test_writeback_tf_equals_calibration_table(processed: Path, sim_log: Path) -> None:
    calib = pq.read_table(processed / "calibration.parquet").to_pylist()[0]
    T_camera_lidar = from_quat([calib["tx_m"], calib["ty_m"], calib["tz_m"]],
                               [calib["qx"], calib["qy"], calib["qz"], calib["qw"]])  # fmt: skip
    with open_log(processed / "street.fleetcal.mcap") as out, open_log(sim_log) as original:
        assert out.topics["/lidar/points"].count == original.topics["/lidar/points"].count
        assert {"/fleetcal/map", "/fleetcal/trajectory", "/fleetcal/overlay/camera_0/image_raw"} <= set(out.topics)
        found = []
        for raw in out.messages(topics=["/tf_static"]):
            for _, parent, child, T in decode_tf(out.deserialize(raw)):
                if (parent, child) == (calib["lidar_frame"], calib["camera_frame"]):
                    found.append(T)
    assert found, "calibrated tf missing from the write-back"
    assert np.allclose(found[-1], invert(T_camera_lidar), atol=1e-9)


def test_calibrate_and_map_commands(sim_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "calib"
    code = main(["calibrate", str(sim_log), "--config", str(sim_log.parent / "small.toml"), "--out", str(out),
                 "--json", "-q", "--no-report"])  # fmt: skip
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    pair = result["pairs"][0]
    truth = json.loads(sim_log.with_name("street.truth.json").read_text())["pairs"][0]
    T_in_log = np.asarray(truth["T_camera_lidar_in_log"])
    assert np.allclose(pair["T_camera_lidar"], np.asarray(pair["T_camera_lidar"]))
    assert rotation_error_deg(np.asarray(pair["T_camera_lidar"]), T_in_log) == pytest.approx(pair["change_deg"])
    assert pair["score"] >= pair["initial_score"]
    code = main(["map", str(sim_log), "--channels", "none", "--workers", "0", "--out", str(tmp_path / "m"), "--json",
                 "-q"])  # fmt: skip
    assert code == 0
    mapped = json.loads(capsys.readouterr().out)
    assert mapped["scans"] == 6 and mapped["map_points"] > 1000 and mapped["channels"] == "none"


def test_calibration_notes_name_suspects_held_and_rough_translations() -> None:
    from fleetcal.workflows.common import calibration_notes

    pairs = [
        {"camera_topic": "/a", "verdict_reason": "flat optimum", "translation_held": False, "translation_std_m": 0.6},
        {"camera_topic": "/b", "verdict_reason": "", "translation_held": True, "translation_std_m": None},
        {"camera_topic": "/c", "verdict_reason": "", "translation_held": False, "translation_std_m": 0.31},
        {"camera_topic": "/d", "verdict_reason": "", "translation_held": False, "translation_std_m": 0.026},
    ]
    assert calibration_notes(pairs) == [
        "/a: suspect: flat optimum",
        "/b: rotation only: the translation is held at the initial guess's",
        "/c: the seeded runs spread 31 cm in translation (RMS from the estimate): treat the translation as rough",
    ]
    joint = [dict(pairs[2], camera_topic=topic) for topic in ("/front", "/back")]
    assert calibration_notes(joint) == [
        "all 2 cameras: the seeded runs spread 31 cm in translation (RMS from the estimate): treat the translation "
        "as rough"]
    weak = {"camera_topic": "/e", "verdict_reason": "", "translation_held": False, "translation_std_m": 0.03,
            "weak_translation_axes": ["x", "z"], "translation_axes_frame": "cam_e_optical"}
    assert calibration_notes([weak, dict(weak, camera_topic="/f", translation_held=True)]) == [
        "/e: the log fixes the translation only weakly along x (image right), z (optical axis) of cam_e_optical: "
        "treat those components as rough",
        "/f: rotation only: the translation is held at the initial guess's"]
    sparse = {"camera_topic": "/g", "verdict_reason": "", "translation_held": False, "translation_std_m": 0.03,
              "sparse_rings": True, "ring_spacing_deg": 1.334}
    assert calibration_notes([sparse, dict(sparse, camera_topic="/h", translation_held=True),
                              dict(sparse, camera_topic="/i", verdict_reason="flat optimum"),
                              dict(sparse, camera_topic="/j", sparse_rings=False, ring_spacing_deg=0.36)]) == [
        "/g: the lidar's rings lie 1.33 deg apart: on rigs this sparse the translation has come out 18-36 cm off "
        "with every check passing (nuScenes, simulated 16 and 32 beams): treat it as rough",
        "/h: rotation only: the translation is held at the initial guess's",
        "/i: suspect: flat optimum"]


def test_calibrate_with_the_translation_held_says_so_and_keeps_the_camera_centre(
        sim_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--search-m 0``: rotation only; the table says so and calibration.parquet keeps the camera's centre
    in the lidar frame where the log's tf puts it."""
    out = tmp_path / "held"
    code = main(["calibrate", str(sim_log), "--config", str(sim_log.parent / "small.toml"), "--out", str(out),
                 "-q", "--no-report", "--search-m", "0"])  # fmt: skip
    assert code == 0
    assert "rotation only: the translation is held at the initial guess's" in capsys.readouterr().out
    row = pq.read_table(out / "calibration.parquet").to_pylist()[0]
    T_est = from_quat([row["tx_m"], row["ty_m"], row["tz_m"]], [row["qx"], row["qy"], row["qz"], row["qw"]])
    truth = json.loads(sim_log.with_name("street.truth.json").read_text())["pairs"][0]
    T_in_log = np.asarray(truth["T_camera_lidar_in_log"])
    np.testing.assert_allclose(invert(T_est)[:3, 3], invert(T_in_log)[:3, 3], atol=1e-6)
    assert rotation_error_deg(T_est, T_in_log) > 0.1  # the rotation was estimated


def test_clock_offset_of_a_straight_steady_drive_is_reported_unobservable(
        sim_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The simulated street's first scans run straight at a steady 8 m/s: every frame moves alike, so a clock
    offset is a translation along the drive and nothing in the log tells it apart; the result says so rather
    than give a number, and the translation's deviation grows by the offset range times the speed."""
    out = tmp_path / "clock"
    config = tmp_path / "estimate.toml"  # the small solver, the translation always estimated (never held)
    config.write_text(SMALL_CONFIG.replace("[calibration]\n", "[calibration]\ntranslation = \"estimate\"\n"))
    code = main(["calibrate", str(sim_log), "--config", str(config), "--out", str(out),
                 "--json", "-q", "--no-report", "--time-offset", "estimate"])  # fmt: skip
    assert code == 0
    pair = json.loads(capsys.readouterr().out)["pairs"][0]
    assert pair["time_offset_s"] == pair["time_offset_std_s"] == "unobservable"
    assert pair["readout_s"] == 0.0 and pair["readout_std_s"] is None and pair["motion_source"] == "tf"
    assert not pair["translation_held"]
    row = pq.read_table(out / "calibration.parquet").to_pylist()[0]
    assert np.isnan(row["time_offset_s"]) and np.isinf(row["time_offset_std_s"])
    assert row["std_tz_m"] > 0.05 * 8.0 / np.sqrt(3) * 0.9  # +-50 ms at 8 m/s along the optical axis
    assert pair["verdict"] == "suspect"


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["map", "{log}", "--channels", "rainbow", "--out", "{tmp}"], 2, "unknown --channels 'rainbow'"),
        (["calibrate", "{log}", "--initial", "1 2 3", "--out", "{tmp}"], 2, "--initial must be 6"),
        (["calibrate", "{log}", "--camera", "/nope", "--out", "{tmp}"], 1, "camera topic /nope is not in the log"),
        (["calibrate", "{log}", "--lidar", "/camera_0/image_raw", "--out", "{tmp}", "--frames", "1"], 1,
         "expected sensor_msgs/msg/PointCloud2"),
        (["calibrate", "{log}", "--initial", "0 0 -50 0 0 0", "--frames", "1", "--out", "{tmp}"],
         1, "sees no lidar points"),
        (["map", "{tmp}/missing.mcap", "--out", "{tmp}"], 1, "missing.mcap"),
        (["calibrate", "{log}"], 2, "--out"),
    ],
)  # fmt: skip
def test_cli_errors_are_one_line(
    sim_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], code: int, message: str
) -> None:
    argv = [a.format(log=sim_log, tmp=tmp_path) for a in args] + ["-q"]
    try:
        got = main(argv)
    except SystemExit as exit_:
        got = int(exit_.code or 0)
    err = capsys.readouterr().err.strip().splitlines()
    assert got == code
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err


def _calibrate_json(capsys: pytest.CaptureFixture[str], argv: list[str]) -> dict:
    assert main([*argv, "--json", "-q", "--no-report"]) == 0
    return json.loads(capsys.readouterr().out)


def test_auto_feature_is_the_one_the_images_follow_and_the_table_says_which(
    sim_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The simulator paints its images with the reflectivity the lidar returns as intensity: the default
    ``auto`` feature calibrates with intensity there, and ``calibration.parquet`` names it. From the log's tf
    (2 deg / 10 cm off), with this small solver and the log's 6 frames: 0.54 deg, as with ``--feature intensity``
    (``range``: 4.4 deg, further off than the start)."""
    config = tmp_path / "auto.toml"
    config.write_text(SMALL_CONFIG.replace('feature = "range"\n', "").replace("frames = 3", "frames = 6"))
    result = _calibrate_json(capsys, ["calibrate", str(sim_log), "--config", str(config), "--out", str(tmp_path / "c")])
    truth = json.loads(sim_log.with_name("street.truth.json").read_text())["pairs"][0]
    T = np.asarray(result["pairs"][0]["T_camera_lidar"])
    assert pq.read_table(tmp_path / "c" / "calibration.parquet").column("feature").to_pylist() == ["intensity"]
    assert rotation_error_deg(T, np.asarray(truth["T_camera_lidar"])) <= 0.6


def test_calibrate_kitti_from_log_tf(shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Default settings, initial guess from the log's tf (2 deg / 12.7 cm off): <= 0.3 deg, <= 10 cm (measured
    0.176 deg / 3.8 cm). Two street scenes fix the camera's y (height) firmly; the 64 rings lie 0.36 deg apart."""
    truth = json.loads((shared_data / "logs" / "kitti_2011_09_26.truth.json").read_text())["pairs"][0]
    result = _calibrate_json(capsys, ["calibrate", str(shared_data / "logs" / "kitti_2011_09_26.mcap"),
                                      "--out", str(tmp_path)])  # fmt: skip
    T = np.asarray(result["pairs"][0]["T_camera_lidar"])
    assert rotation_error_deg(T, np.asarray(truth["T_camera_lidar"])) <= 0.3
    assert translation_error_m(T, np.asarray(truth["T_camera_lidar"])) <= 0.10
    pair = result["pairs"][0]
    assert pair["verdict"] == "recalibrated" and pair["score"] > pair["initial_score"]
    assert pair["verdict_reason"] == "" and pair["agreeing_repeats"] >= 1
    assert "y" not in pair["weak_translation_axes"], pair["translation_profile"]
    assert pair["ring_spacing_deg"] == pytest.approx(0.36, abs=0.03) and not pair["sparse_rings"]


def test_calibrate_nuscenes_joint_with_ego_motion(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Six cameras, one unknown lidar pose, ego-motion from /tf, defaults (the lidar viewpoint, picked
    for this 32-beam lidar's sparse rings): <= 0.6 deg (0.53); without ego-motion, worse (0.99)."""
    log = shared_data / "logs" / "nuscenes_n015.bag"
    truth = json.loads((shared_data / "logs" / "nuscenes_n015.truth.json").read_text())["pairs"]
    cameras = [a for p in truth for a in ("--camera", p["camera_topic"])]
    T_true = {p["camera_topic"]: np.asarray(p["T_camera_lidar"]) for p in truth}

    def worst(result: dict) -> float:
        return max(rotation_error_deg(np.asarray(p["T_camera_lidar"]), T_true[p["camera_topic"]])
                   for p in result["pairs"])  # fmt: skip

    compensated = _calibrate_json(capsys, ["calibrate", str(log), *cameras, "--joint", "--out", str(tmp_path / "a")])
    assert all(p["motion_compensated"] for p in compensated["pairs"]) and len(compensated["pairs"]) == 6
    assert all(p["sparse_rings"] and p["ring_slant_deg"] < 5.0 for p in compensated["pairs"])  # level 1.33-deg rings
    monkeypatch.setenv("FLEETCAL_CALIBRATION__MOTION_COMPENSATION", "false")
    monkeypatch.setenv("FLEETCAL_CALIBRATION__REPEATS", "1")  # the control: one seeded run shows the loss
    raw = _calibrate_json(capsys, ["calibrate", str(log), *cameras, "--joint", "--out", str(tmp_path / "b")])
    assert worst(compensated) <= 0.6
    assert worst(raw) > worst(compensated)


@pytest.mark.parametrize("model", ["log", "cylindrical", "equidistant", "none"])
def test_camera_model_flag_replaces_the_camera_infos_projection(sim_log: Path, model: str) -> None:
    """``calibration.camera_model`` keeps the CameraInfo's size, K and D and replaces its projection (``log``: as
    logged, plumb_bob in the simulator); a cylindrical panorama projects by azimuth."""
    from fleetcal.pipeline.config import Config
    from fleetcal.readers.frames import load_tf_tree
    from fleetcal.workflows.calibrate import collect_frames
    config = Config()
    config.calibration.frames = 1
    config.calibration.camera_model = model  # type: ignore[assignment]
    with open_log(sim_log) as reader:
        col = collect_frames(reader, "/lidar/points", "/camera_0/image_raw", config, load_tf_tree(reader))
    camera = col.frames[0].camera
    assert camera.distortion_model == ("plumb_bob" if model == "log" else model)
    assert (camera.width, camera.height) == (640, 360)
    if model == "cylindrical":
        az = np.radians(30.0)
        uv, ok = camera.project(np.array([[10 * np.sin(az), 0.0, 10 * np.cos(az)]]))
        assert ok[0] and uv[0, 0] == pytest.approx(camera.fx * az + camera.cx)
