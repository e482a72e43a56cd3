"""``fleetcal simulate`` / ``fleetcal demo`` end to end: logs open with the readers, truth is right,
output is deterministic, bad arguments get a one-line error."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.transforms import apply, from_xyz_rpy, invert
from fleetcal.readers.frames import iter_camera_frames, iter_lidar_frames, load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.workflows.cli import main
from fleetcal.workflows.inspect_log import inspect_log
from fleetcal.workflows.simulator.truth import load_truth, truth_path_for
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

TINY = {"frames": 2, "beams": 16, "columns": 256, "width": 96, "height": 64}


def _files(path: Path) -> dict[str, bytes]:
    if path.is_dir():
        return {p.name: p.read_bytes() for p in sorted(path.iterdir())}
    return {path.name: path.read_bytes()}


def _log_name(fmt: str) -> str:
    return {"mcap": "sim.mcap", "ros1": "sim.bag", "ros2": "sim_bag"}[fmt]


# ---------------------------------------------------------------- truth is right: edges line up
def _lidar_intensity_edges(frame) -> np.ndarray:
    """Per point: largest intensity step (0..1) to its left/right neighbour in the same ring."""
    B, C = frame.organized_shape
    grid = np.full(B * C, np.nan)
    grid[frame.organized_index] = frame.channels["intensity"]
    grid = grid.reshape(B, C)
    steps = np.stack([np.abs(grid - np.roll(grid, 1, 1)), np.abs(grid - np.roll(grid, -1, 1))])
    steps = np.where(np.isnan(steps), -1.0, steps).max(axis=0).clip(0) / 255.0
    return steps.ravel()[frame.organized_index]


def _image_gradient(image: np.ndarray) -> np.ndarray:
    grey = cv2.GaussianBlur(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY).astype(np.float32), (0, 0), 0.5)
    return np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))


@pytest.fixture(scope="module", params=["street", "open"])
def edge_log(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("edges") / f"{request.param}.mcap"
    opts = SimulationOptions(frames=4, scene=request.param, organized=True, width=960, height=540, seed=3)
    result = simulate_log(out, opts)
    return Path(result.log_path), load_truth(result.truth_path)


def test_lidar_intensity_edges_meet_image_edges_only_at_true_extrinsic(edge_log) -> None:
    """Edge-correlation score: Pearson correlation of the lidar intensity step at each point with the
    image gradient magnitude where the point projects (camera motion between the scan and image stamps
    compensated with the log's /tf). Maximal at the true T_camera_lidar; lower after 1 deg about any axis,
    5 cm across the optical axis, or 10 cm along it (a 5 cm shift along the optical axis of a forward camera
    moves points 5 m away by < 2 px, inside the score's noise; test_simulator checks it with depth)."""
    log_path, truth = edge_log
    pair = truth["pairs"][0]
    with open_log(log_path) as reader:
        scans = list(iter_lidar_frames(reader, truth["lidar_topic"]))
        images = list(iter_camera_frames(reader, pair["camera_topic"]))
        tree = load_tf_tree(reader)
    assert len(scans) == 4 and len(images) == 4
    data: list[tuple[np.ndarray, np.ndarray, np.ndarray, CameraModel, np.ndarray]] = []
    for scan in scans:
        image = min(images, key=lambda im: abs(im.stamp_ns - scan.stamp_ns))
        assert 10e6 <= image.stamp_ns - scan.stamp_ns <= 30e6  # real pairing offsets
        T_odom_lidar_scan = tree.lookup("odom", truth["lidar_frame"], scan.stamp_ns)
        T_odom_lidar_image = tree.lookup("odom", truth["lidar_frame"], image.stamp_ns)
        motion = invert(T_odom_lidar_image) @ T_odom_lidar_scan
        points = scan.points_xyz.astype(np.float64)
        camera = image.camera
        assert camera is not None
        data.append((points, _lidar_intensity_edges(scan), _image_gradient(image.image), camera, motion))

    def score(T_camera_lidar: np.ndarray) -> float:
        edges, grads = [], []
        for points, e, G, camera, motion in data:
            uv, ok = camera.project(apply(T_camera_lidar @ motion, points))
            px = np.rint(uv[ok]).astype(int)
            edges.append(e[ok])
            grads.append(G[px[:, 1].clip(0, camera.height - 1), px[:, 0].clip(0, camera.width - 1)])
        return float(np.corrcoef(np.concatenate(edges), np.concatenate(grads))[0, 1])

    T_true = pair["T_camera_lidar"]
    at_truth = score(T_true)
    assert at_truth > 0.2
    for axis, step in [(0, 0.05), (1, 0.05), (2, 0.10), (3, 1.0), (4, 1.0), (5, 1.0)]:
        for sign in (1.0, -1.0):
            delta = np.zeros(6)
            delta[axis] = sign * step
            assert score(from_xyz_rpy(*delta) @ T_true) < at_truth - 0.01, (axis, sign)
    assert score(pair["T_camera_lidar_in_log"]) < at_truth - 0.1


# ---------------------------------------------------------------- logs, formats, determinism
@pytest.mark.parametrize(
    ("fmt", "compressed", "fisheye"), [("mcap", False, False), ("ros1", True, False), ("ros2", False, True)]
)
def test_formats_open_and_inspect_detects_lidar_cameras_and_perturbed_tf(
    tmp_path: Path, fmt: str, compressed: bool, fisheye: bool
) -> None:
    opts = SimulationOptions(fmt=fmt, cameras=2, compressed=compressed, fisheye=fisheye, **TINY)  # type: ignore[arg-type]
    result = simulate_log(tmp_path / _log_name(fmt), opts)
    truth = load_truth(result.truth_path)
    assert Path(result.truth_path) == truth_path_for(tmp_path / _log_name(fmt))
    with open_log(result.log_path) as reader:
        assert reader.format == fmt
        report = inspect_log(reader)
        tree = load_tf_tree(reader)
        images = list(iter_camera_frames(reader, truth["pairs"][1]["camera_topic"]))
    suffix = "/compressed" if compressed else ""
    assert report.lidar_topics == ["/lidar/points"]
    assert report.camera_topics == [f"/camera_0/image_raw{suffix}", f"/camera_1/image_raw{suffix}"]
    assert {(e.parent, e.child, e.static) for e in report.tf} == {
        ("base_link", "lidar", True),
        ("lidar", "camera_0_optical", True),
        ("lidar", "camera_1_optical", True),
        ("odom", "base_link", False),
    }
    counts = {t.name: t.count for t in report.topics}
    assert counts["/lidar/points"] == 2 and counts[f"/camera_1/image_raw{suffix}"] == len(images) == 2
    assert images[0].camera is not None and images[0].camera.distortion_model == (
        "equidistant" if fisheye else "plumb_bob"
    )
    assert images[0].image.shape == (64, 96, 3)
    for pair in truth["pairs"]:
        T_log = invert(tree.lookup("lidar", pair["camera_frame"]))
        np.testing.assert_allclose(T_log, pair["T_camera_lidar_in_log"], atol=1e-6)
    # odometry in the log matches the truth trajectory (map = first scan's lidar frame)
    T0 = tree.lookup("odom", "lidar", truth["trajectory"][0]["stamp_ns"])
    for entry in truth["trajectory"]:
        T = tree.lookup("odom", "lidar", entry["stamp_ns"])
        np.testing.assert_allclose(invert(T0) @ T, entry["T_map_lidar"], atol=1e-6)


def test_organized_and_unorganized_logs_agree(tmp_path: Path) -> None:
    frames = {}
    for organized in (True, False):
        opts = SimulationOptions(organized=organized, seed=5, **TINY)  # type: ignore[arg-type]
        result = simulate_log(tmp_path / f"org_{organized}.mcap", opts)
        with open_log(result.log_path) as reader:
            frames[organized] = list(iter_lidar_frames(reader, "/lidar/points"))
    for org, flat in zip(frames[True], frames[False], strict=True):
        assert org.organized_shape == (16, 256) and flat.organized_shape is None
        assert org.stamp_ns == flat.stamp_ns and org.n_points == flat.n_points > 500
        np.testing.assert_array_equal(org.points_xyz, flat.points_xyz)
        for name in ("intensity", "ring", "time"):
            np.testing.assert_array_equal(org.channels[name], flat.channels[name])
        assert org.organized_index is not None
        np.testing.assert_array_equal(org.organized_index // 256, org.channels["ring"])
        assert org.dropped_points == 16 * 256 - org.n_points


def test_cli_rosette_lidar_log_points_stay_in_its_cone_and_change_every_scan(tmp_path: Path) -> None:
    """``--lidar rosette`` (6 lines x 500 samples here): every point within the 35.2 deg half-angle cone
    ahead of the lidar, with its line as ``ring``; consecutive scans sample different directions (a
    non-repetitive pattern), and the truth file names the pattern."""
    log = tmp_path / "livox.mcap"
    assert main(["simulate", str(log), "--lidar", "rosette", "--beams", "6", "--columns", "500", "--frames", "2",
                 "--image-size", "96x64", "--skewed", "-q"]) == 0
    with open_log(log) as reader:
        scans = list(iter_lidar_frames(reader, "/lidar/points"))
    assert len(scans) == 2
    directions = []
    for scan in scans:
        p = scan.points_xyz.astype(np.float64)
        unit = p / np.linalg.norm(p, axis=1, keepdims=True)
        assert scan.n_points > 1000
        assert np.degrees(np.arccos(unit[:, 0])).max() <= 35.2 + 1e-3
        assert set(np.unique(scan.channels["ring"]).tolist()) <= set(range(6))
        assert scan.channels["time"].min() >= 0.0 and scan.channels["time"].max() < 0.1  # skewed: firing times
        directions.append(unit)
    nearest_deg = np.degrees(cKDTree(directions[0]).query(directions[1])[0])
    assert np.median(nearest_deg) > 0.05  # not the same rays again (a repeating pattern: range noise only)
    assert load_truth(truth_path_for(log))["lidar"]["pattern"] == "rosette"


def test_cli_rolled_lidar_sees_the_ground_level_through_its_tf(tmp_path: Path) -> None:
    """``--lidar-roll 30``: the log's ``base_link -> lidar`` turns 30 deg about x, and the scan's ground
    points, carried into ``base_link`` through it, lie level at z = 0 (in the lidar frame they lie on a plane
    tilted by 30 deg): the truth and the casting agree on the mount."""
    log = tmp_path / "rolled.mcap"
    assert main(["simulate", str(log), "--lidar-roll", "30", "--scene", "open", "--frames", "1",
                 "--image-size", "96x64", "--beams", "32", "--columns", "512", "-q"]) == 0
    with open_log(log) as reader:
        scan = next(iter_lidar_frames(reader, "/lidar/points"))
        T_base_lidar = load_tf_tree(reader).lookup("base_link", "lidar")
    roll_deg = np.degrees(np.arctan2(T_base_lidar[2, 1], T_base_lidar[2, 2]))
    assert roll_deg == pytest.approx(30.0, abs=1e-6)
    points_base = apply(T_base_lidar, scan.points_xyz.astype(np.float64))
    ground = np.abs(points_base[:, 2]) < 0.3
    assert ground.mean() > 0.5  # the yard is mostly flat ground
    assert abs(np.median(points_base[ground, 2])) < 0.02
    normal_lidar = np.linalg.svd(scan.points_xyz[ground] - scan.points_xyz[ground].mean(0))[2][2]
    assert np.degrees(np.arccos(abs(normal_lidar[2]))) == pytest.approx(30.0, abs=1.0)
    assert load_truth(truth_path_for(log))["lidar"]["roll_deg"] == 30.0


def test_cli_camera_clocks_reach_the_truth_file(tmp_path: Path) -> None:
    """``--time-offset-ms 30 --readout-ms 20``: every camera's truth pair carries 0.03 s and 0.02 s; a truth
    file without the keys reads back as synchronised global-shutter cameras."""
    log = tmp_path / "clocks.mcap"
    assert main(["simulate", str(log), "--cameras", "2", "--frames", "1", "--image-size", "96x64", "--beams", "16",
                 "--columns", "256", "--speed", "10", "--time-offset-ms", "30", "--readout-ms", "20", "-q"]) == 0
    raw = json.loads(truth_path_for(log).read_text())
    assert [(p["time_offset_s"], p["readout_s"]) for p in raw["pairs"]] == [(0.03, 0.02)] * 2
    truth = load_truth(truth_path_for(log))
    assert [(p["time_offset_s"], p["readout_s"]) for p in truth["pairs"]] == [(0.03, 0.02)] * 2
    for pair in raw["pairs"]:
        del pair["time_offset_s"], pair["readout_s"]
    bare = tmp_path / "bare.truth.json"
    bare.write_text(json.dumps(raw))
    assert [(p["time_offset_s"], p["readout_s"]) for p in load_truth(bare)["pairs"]] == [(0.0, 0.0)] * 2


@pytest.mark.parametrize("fmt", ["mcap", "ros1", "ros2"])
def test_same_seed_gives_byte_identical_logs(tmp_path: Path, fmt: str) -> None:
    """Same options, same bytes (log and truth); the camera clocks' zero values, given, are the defaults."""
    outputs = []
    clocks = {"time_offset_ms": 0.0, "readout_ms": 0.0}
    for run, seed, extra in (("a", 11, {}), ("b", 11, {}), ("c", 12, {}), ("d", 11, clocks)):
        folder = tmp_path / run
        opts = SimulationOptions(fmt=fmt, seed=seed, **TINY, **extra)  # type: ignore[arg-type]
        simulate_log(folder / _log_name(fmt), opts)
        outputs.append((_files(folder / _log_name(fmt)), truth_path_for(folder / _log_name(fmt)).read_bytes()))
    assert outputs[0] == outputs[1] == outputs[3]
    assert outputs[0][0] != outputs[2][0] and outputs[0][1] != outputs[2][1]


# ---------------------------------------------------------------- command line
def test_cli_simulate_json_and_truth_schema(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli.mcap"
    rc = main(
        [
            "simulate",
            str(out),
            "--frames",
            "3",
            "--beams",
            "32",
            "--columns",
            "512",
            "--image-size",
            "64x48",
            "--scene",
            "corridor",
            "--perturb-deg",
            "3",
            "--perturb-m",
            "0.2",
            "--seed",
            "2",
            "--max-range",
            "4",
            "--json",
            "-q",
        ]
    )
    assert rc == 0
    result = json.loads(capsys.readouterr().out)
    assert result["lidar_scans"] == 3 and result["scene"] == "corridor" and Path(result["log_path"]) == out
    truth = json.loads((tmp_path / "cli.truth.json").read_text())
    assert {"lidar_topic", "lidar_frame", "pairs", "trajectory", "scene", "seed", "format"} <= set(truth)
    assert set(truth["pairs"][0]) == {
        "camera_topic",
        "camera_frame",
        "T_camera_lidar",
        "T_camera_lidar_in_log",
        "time_offset_s",
        "readout_s",
    }
    assert (truth["pairs"][0]["time_offset_s"], truth["pairs"][0]["readout_s"]) == (0.0, 0.0)
    assert [e["stamp_ns"] for e in truth["trajectory"]] == [
        1_700_000_000_000_000_000 + k * 100_000_000 for k in range(3)
    ]
    np.testing.assert_allclose(truth["trajectory"][0]["T_map_lidar"], np.eye(4), atol=1e-12)
    # 1.5 m/s in the corridor: 0.3 m after 0.2 s
    assert np.linalg.norm(np.asarray(truth["trajectory"][2]["T_map_lidar"])[:3, 3]) == pytest.approx(0.3, abs=1e-6)
    # --max-range 4: no return beyond 4 m (the 3 m corridor is otherwise seen to 20+ m along its axis)
    assert truth["lidar"]["max_range_m"] == 4.0
    with open_log(out) as reader:
        ranges = np.concatenate(
            [np.linalg.norm(f.points_xyz, axis=1) for f in iter_lidar_frames(reader, "/lidar/points")]
        )
    assert ranges.size > 3 * 5000 and 3.5 < ranges.max() <= 4.0


def test_truth_schema_matches_shared_data(shared_data: Path, tmp_path: Path) -> None:
    reference = json.loads((shared_data / "logs" / "kitti_2011_09_26.truth.json").read_text())
    simulate_log(tmp_path / "s.mcap", SimulationOptions(**TINY))  # type: ignore[arg-type]
    ours = json.loads((tmp_path / "s.truth.json").read_text())
    assert {"lidar_topic", "lidar_frame", "pairs"} <= set(reference) & set(ours)
    assert set(ours["pairs"][0]) - set(reference["pairs"][0]) == {"time_offset_s", "readout_s"}
    assert set(reference["pairs"][0]) <= set(ours["pairs"][0])
    assert (
        np.asarray(ours["pairs"][0]["T_camera_lidar"]).shape
        == np.asarray(reference["pairs"][0]["T_camera_lidar"]).shape
        == (4, 4)
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--beams", "0"], "--beams"),
        (["--frames", "-3"], "--frames"),
        (["--frames", "0"], "--frames"),
        (["--scene", "moon"], "--scene"),
        (["--cameras", "0"], "--cameras"),
        (["--format", "zip"], "--format"),
        (["--speed", "-1"], "--speed"),
        (["--image-size", "big"], "--image-size"),
        (["--max-range", "0"], "--max-range"),
        (["--fisheye", "--panorama"], "--panorama"),
        (["--panorama", "--rectified"], "--rectified"),
        (["--fisheye", "--wide-angle"], "--wide-angle"),
        (["--lidar", "rosette", "--beams", "64"], "--beams"),
        (["--lidar", "rosette", "--organized"], "organised"),
        (["--lidar", "flash"], "--lidar"),
        (["--lidar-roll", "200"], "--lidar-roll"),
        (["--time-offset-ms", "nan"], "--time-offset-ms"),
        (["--time-offset-ms", "5000"], "--time-offset-ms"),
        (["--readout-ms", "-1"], "--readout-ms"),
        (["--readout-ms", "fast"], "--readout-ms"),
    ],
)
def test_cli_nonsense_arguments_get_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    try:  # argparse exits; a check across options (rosette lines) returns the usage error's code
        rc = main(["simulate", str(tmp_path / "x.mcap"), *args])
    except SystemExit as exc:
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and message in err and err.count("\n") == 1
    assert not list(tmp_path.iterdir())


def test_demo_runs_and_reports_initial_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(
        [
            "demo",
            "--out",
            str(tmp_path),
            "--frames",
            "3",
            "--beams",
            "32",
            "--columns",
            "512",
            "--image-size",
            "320x180",
            "--workers",
            "0",
            "-q",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0
    assert "2.00 deg" in out and "10.00 cm" in out  # initial (log tf) vs truth, default perturbation
    assert "process    ok" in out
    assert (tmp_path / "out" / "calibration.parquet").is_file() and (tmp_path / "out" / "result.json").is_file()
    assert (tmp_path / "demo.mcap").is_file() and (tmp_path / "demo.truth.json").is_file()
