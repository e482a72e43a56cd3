"""``fleetcal inspect`` through ``workflows.cli.main`` and the installed console script."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fleetcal.readers.open import open_log
from fleetcal.workflows.cli import main
from fleetcal.workflows.inspect_log import inspect_log
from tests.test_readers import (
    FORMATS,
    MS,
    T0_NS,
    _bad_inputs,
    _intact_prefix,
    sample_entries,
    write_log,
    write_mcap,
)

Capsys = pytest.CaptureFixture[str]
JSON_KEYS = {"paths", "format", "start_ns", "end_ns", "topics", "lidar_topics", "camera_topics", "tf",
             "undecodable_topics", "lidar_scans", "problems"}


def _json(capsys: Capsys, argv: list[str]) -> dict:
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 1
    result = json.loads(out)
    assert isinstance(result, dict)
    return result


@pytest.mark.parametrize("kind", FORMATS)
def test_json_report_of_every_format(kind: str, tmp_path: Path, capsys: Capsys) -> None:
    entries = sample_entries(kind)
    path = write_log(kind, tmp_path, entries)
    result = _json(capsys, ["inspect", str(path), "--json"])
    assert set(result) == JSON_KEYS
    assert result["problems"] == []
    assert result["format"] == {"mcap-ros2": "mcap", "mcap-ros1": "mcap", "ros1": "ros1"}.get(kind, "ros2")
    assert result["paths"] == [str(path)]
    assert result["start_ns"] == T0_NS
    assert result["end_ns"] == entries[-1].log_time_ns
    topics = {t["name"]: t for t in result["topics"]}
    assert {n: t["count"] for n, t in topics.items()} == {
        "/tf_static": 1, "/lidar/points": 5, "/cam/image_raw": 5, "/cam/camera_info": 5, "/chatter": 10}
    assert topics["/lidar/points"]["type"] == "sensor_msgs/msg/PointCloud2"
    assert topics["/lidar/points"]["rate_hz"] == pytest.approx(10.0)
    assert topics["/chatter"]["rate_hz"] == pytest.approx(20.0)
    assert topics["/tf_static"]["rate_hz"] is None
    assert topics["/lidar/points"]["frame_id"] == "lidar"
    assert topics["/cam/image_raw"]["frame_id"] == "cam_optical"
    assert topics["/chatter"]["frame_id"] is None
    assert topics["/tf_static"]["frame_id"] is None
    assert result["lidar_topics"] == ["/lidar/points"]
    assert result["camera_topics"] == ["/cam/image_raw"]
    assert result["tf"] == [{"parent": "base_link", "child": "lidar", "static": True},
                            {"parent": "lidar", "child": "cam_optical", "static": True}]
    assert result["undecodable_topics"] == []
    scan = result["lidar_scans"]["/lidar/points"]
    assert scan["points"] == 50 and scan["channels"] == []  # x, y, z only
    assert scan["point_times"] == "none" and scan["time_range_s"] is None


def test_human_report_lists_table_span_sensors_and_tf(tmp_path: Path, capsys: Capsys) -> None:
    path = write_log("mcap-ros2", tmp_path, sample_entries("mcap-ros2"))
    assert main(["inspect", str(path)]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    out = captured.out
    row = next(line for line in out.splitlines() if line.startswith("/lidar/points"))
    assert row.split() == ["/lidar/points", "sensor_msgs/msg/PointCloud2", "5", "10.00", "lidar"]
    assert "time span: 2023-11-14T22:13:20.000Z .. 2023-11-14T22:13:20.455Z (0.455 s;" in out
    assert "lidar topics: /lidar/points" in out
    assert "camera topics: /cam/image_raw (info: /cam/camera_info)" in out
    assert "  base_link -> lidar (static)" in out
    assert "undecodable topics: none" in out


def test_dynamic_tf_edges_and_several_files(tmp_path: Path, capsys: Capsys) -> None:
    from tests.test_readers import Entry, store_for, tf_message

    store = store_for("ros1")
    first = sample_entries("ros1") + [
        Entry("/tf", "tf2_msgs/msg/TFMessage", T0_NS + i * 10 * MS,
              tf_message(store, T0_NS + i * 10 * MS, [("odom", "base_link")])) for i in range(30)]
    a = write_log("ros1", tmp_path, sorted(first, key=lambda e: e.log_time_ns), "a")
    b = write_log("ros1", tmp_path, sample_entries("ros1", T0_NS + 10_000 * MS), "b")
    result = _json(capsys, ["inspect", str(a), str(b), "--json"])
    assert result["paths"] == [str(a), str(b)]
    assert {"parent": "odom", "child": "base_link", "static": False} in result["tf"]
    topics = {t["name"]: t for t in result["topics"]}
    assert topics["/tf"]["count"] == 30
    assert topics["/tf"]["rate_hz"] == pytest.approx(100.0)
    assert topics["/chatter"]["count"] == 20
    assert result["end_ns"] == T0_NS + 10_000 * MS + 455 * MS


@pytest.mark.parametrize("case", ["missing", "empty", "random", "png", "folder", "extension"])
def test_bad_input_is_one_error_line_exit_1(case: str, tmp_path: Path, capsys: Capsys) -> None:
    path = next(p for name, p, _, _ in _bad_inputs(tmp_path) if name == case)
    assert main(["inspect", str(path)]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    assert str(path) in lines[0]
    assert "Traceback" not in captured.err


def test_no_log_argument_is_a_usage_error(capsys: Capsys) -> None:
    with pytest.raises(SystemExit) as info:
        main(["inspect"])
    assert info.value.code == 2
    assert capsys.readouterr().err.startswith("error: ")


def test_truncated_mcap_reports_then_fails_unless_allowed(tmp_path: Path, capsys: Capsys) -> None:
    full = write_mcap(tmp_path / "full.mcap", sample_entries("mcap-ros2", scans=40), chunk_size=2048)
    data = full.read_bytes()
    cut = len(data) // 2
    damaged = tmp_path / "cut.mcap"
    damaged.write_bytes(data[:cut])
    recovered, intact_end = _intact_prefix(full, cut)
    expected = f"recovered {recovered} messages, lost {cut - intact_end} bytes"

    assert main(["inspect", str(damaged)]) == 1
    captured = capsys.readouterr()
    assert "lidar topics: /lidar/points" in captured.out
    err_lines = captured.err.splitlines()
    assert len(err_lines) == 1 and err_lines[0].startswith("error: ") and expected in err_lines[0]

    result = _json(capsys, ["inspect", str(damaged), "--json", "--allow-truncated"])
    assert sum(t["count"] for t in result["topics"]) == recovered
    assert main(["inspect", str(damaged), "--allow-truncated"]) == 0
    captured = capsys.readouterr()
    assert captured.err.startswith("warning: ") and expected in captured.err


def test_undecodable_topic_is_listed_not_fatal(tmp_path: Path, capsys: Capsys) -> None:
    from tests.test_readers import test_mcap_type_without_definition_is_listed_undecodable as make_vendor

    make_vendor(tmp_path)
    path = tmp_path / "vendor.mcap"
    result = _json(capsys, ["inspect", str(path), "--json"])
    assert result["undecodable_topics"] == ["/velodyne_packets"]
    topics = {t["name"]: t for t in result["topics"]}
    assert topics["/velodyne_packets"] == {
        "name": "/velodyne_packets", "type": "velodyne_msgs/msg/VelodyneScan", "count": 1, "rate_hz": None,
        "frame_id": None,
    }
    assert main(["inspect", str(path)]) == 0
    assert "  /velodyne_packets (velodyne_msgs/msg/VelodyneScan)" in capsys.readouterr().out


def test_report_object_matches_reader(tmp_path: Path) -> None:
    path = write_log("ros2-sqlite3", tmp_path, sample_entries("ros2-sqlite3"))
    with open_log(path) as reader:
        report = inspect_log(reader)
    assert report.message_count == 26
    assert report.camera_info_topics == {"/cam/image_raw": "/cam/camera_info"}
    assert report.duration_s == pytest.approx(0.455)
    assert report.truncation is None


def _console_script() -> str:
    candidate = Path(sys.executable).with_name("fleetcal")
    if candidate.exists():
        return str(candidate)
    found = shutil.which("fleetcal")
    if found is None:
        pytest.skip("the fleetcal console script is not installed (pip install -e .)")
    return found


def test_console_script_subprocess(tmp_path: Path) -> None:
    script = _console_script()
    path = write_log("mcap-ros2", tmp_path, sample_entries("mcap-ros2"))
    ok = subprocess.run([script, "inspect", str(path), "--json"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["lidar_topics"] == ["/lidar/points"]
    missing = subprocess.run([script, "inspect", str(tmp_path / "nope.bag")], capture_output=True, text=True,
                             timeout=120)
    assert missing.returncode == 1
    expected = f"error: no such file or directory: {tmp_path / 'nope.bag'}"
    assert missing.stderr.strip().splitlines() == [expected]
    usage = subprocess.run([script, "inspect"], capture_output=True, text=True, timeout=120)
    assert usage.returncode == 2


@pytest.mark.parametrize("deskewed", [False, True])
def test_lidar_point_times_are_described(deskewed: bool, tmp_path: Path, capsys: Capsys) -> None:
    """A simulated lidar that does not de-skew carries a sweep of firing times (0..0.1 s); one that does
    carries zeros; both are named, in the JSON and in the text."""
    from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

    log = tmp_path / "sim.mcap"
    simulate_log(log, SimulationOptions(frames=2, beams=16, columns=256, width=64, height=48, deskew=deskewed))
    scan = _json(capsys, ["inspect", str(log), "--json"])["lidar_scans"]["/lidar/points"]
    assert "time" in scan["channels"] and scan["points"] > 1000
    if deskewed:
        assert scan["point_times"] == "constant" and scan["time_range_s"] == [0.0, 0.0]
    else:
        assert scan["point_times"] == "sweep"
        assert scan["time_range_s"][0] == pytest.approx(0.0, abs=1e-3)
        assert scan["time_range_s"][1] == pytest.approx(0.1, abs=2e-3)
    assert main(["inspect", str(log)]) == 0
    text = capsys.readouterr().out
    assert ("used as stamped" if deskewed else "move each point by its firing time") in text


def test_real_lidar_times_from_another_clock_are_flagged(shared_data: Path, capsys: Capsys) -> None:
    logs = shared_data / "logs"
    rig1 = _json(capsys, ["inspect", str(logs / "pjlab_road_rig1"), "--json"])["lidar_scans"]
    assert rig1["/top_center_lidar/points"]["point_times"] == "foreign"  # 21.9 million s from the stamps
    kitti = _json(capsys, ["inspect", str(logs / "kitti_2011_09_26.mcap"), "--json"])["lidar_scans"]
    assert [s["point_times"] for s in kitti.values()] == ["none"]
