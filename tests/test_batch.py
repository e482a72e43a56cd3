"""``fleetcal batch``: inputs, output folder names, manifest, failures, resume, fleet drift summary.

Fast tests inject a fake per-log recipe (a JSON "log" names the pose it calibrates to, or the error it
raises); the slow tests run the real ``process_log`` on tiny simulated logs, kill a batch midway with
SIGKILL and resume it.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from fleetcal.pipeline.config import Config, config_from_dict
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.transforms import from_xyz_rpy, to_quat, to_rpy_deg
from fleetcal.stages.sinks.tables import CALIBRATION_SCHEMA, write_rows
from fleetcal.workflows.batch import (
    FLEET_FILE,
    MANIFEST_FILE,
    ProcessSummary,
    fleet_summary,
    log_stem,
    plan_jobs,
    read_manifest,
    resolve_inputs,
    run_batch,
)
from fleetcal.workflows.cli import main

REPO = Path(__file__).resolve().parents[1]
START_NS = 1_700_000_000_000_000_000


# ------------------------------------------------------------------------------ fake per-log recipe
def _fake_log(path: Path, *, start_s: float = 0.0, pose: tuple[float, ...] = (0, 0, 0, 0, 0, 0),
              error: str | None = None, crash: bool = False, held: bool = False,
              weak: tuple[str, ...] = ()) -> Path:  # fmt: skip
    """A JSON file standing in for a log: the pose the fake recipe 'calibrates' (``held``: with the translation
    held; ``weak``: the axes it fixes the translation only weakly along), or its failure."""
    spec = {"start_ns": START_NS + int(start_s * 1e9), "pose": list(pose), "error": error, "crash": crash,
            "held": held, "weak": list(weak)}
    path.write_text(json.dumps(spec), encoding="utf-8")
    return path


def fake_process(paths: list[str], out_dir: Path, config: Config) -> ProcessSummary:
    """Reads the fake log, writes calibration.parquet and result.json (last), like process_log."""
    spec = json.loads(Path(paths[0]).read_text(encoding="utf-8"))
    (out_dir / "partial.txt").write_text("started", encoding="utf-8")
    if spec["error"]:
        raise InputError(spec["error"])
    if spec["crash"]:
        raise RuntimeError("boom")
    T = from_xyz_rpy(*spec["pose"])
    t, q = to_quat(T)
    rpy = to_rpy_deg(T)
    score = 0.5 + 0.01 * config.calibration.particles
    row = {
        "lidar_topic": "/lidar/points", "camera_topic": "/camera_0/image_raw", "lidar_frame": "lidar",
        "camera_frame": "camera_0_optical", "metric": "gom", "feature": "intensity",
        "tx_m": t[0], "ty_m": t[1], "tz_m": t[2], "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3],
        "roll_deg": rpy[0], "pitch_deg": rpy[1], "yaw_deg": rpy[2], "score": score, "initial_score": 0.4,
        "frames_used": 2, "runtime_s": 0.0,
    }  # fmt: skip
    write_rows([row], CALIBRATION_SCHEMA, out_dir / "calibration.parquet")
    calibration = {"camera_topic": row["camera_topic"], "verdict": "ok", "score": score,
                   "translation_held": spec["held"], "weak_translation_axes": spec.get("weak", [])}
    result = {
        "log_paths": paths, "out_dir": str(out_dir), "runtime_s": 0.0, "stage_times_s": {"calibration": 0.0},
        "calibrations": [calibration], "mapping": {"map_points": 1234}, "writeback_path": None,
        "log_start_ns": spec["start_ns"],
    }  # fmt: skip
    (out_dir / "result.json").write_text(json.dumps(result), encoding="utf-8")
    return ProcessSummary(spec["start_ns"], [calibration], 1234, {"calibration": 0.01, "mapping": 0.02})


CALLS: list[str] = []


def counting_process(paths: list[str], out_dir: Path, config: Config) -> ProcessSummary:
    CALLS.append(Path(paths[0]).name)
    return fake_process(paths, out_dir, config)


def _manifest(out: Path) -> dict[str, dict[str, Any]]:
    """The manifest's rows by log, read from one snapshot of the file: a running batch replaces it (atomically)
    while this reads, and a reader that opens it twice may mix two versions."""
    table = pq.read_table(pa.BufferReader((out / MANIFEST_FILE).read_bytes()))
    return {Path(r["out_dir"]).name: r for r in table.to_pylist()}


@pytest.fixture()
def fleet_logs(tmp_path: Path) -> Path:
    """Five fake logs: three of one rig with known pose changes (input order != time order), two bad."""
    logs = tmp_path / "logs"
    logs.mkdir()
    _fake_log(logs / "a.mcap", start_s=200, pose=(0.10, 0, 0, -90, 0.2, -90), weak=("x", "z"))  # 2nd: +0.2 deg
    _fake_log(logs / "b.mcap", start_s=100, pose=(0.10, 0, 0, -90, 0, -90))  # 1st in time
    _fake_log(logs / "c.mcap", start_s=300, pose=(0.16, 0, 0, -90, 0.2, -90), held=True)  # 3rd: +6 cm
    _fake_log(logs / "d.mcap", error="d.mcap is not a log (unknown file format)")
    _fake_log(logs / "e.mcap", crash=True)
    (logs / "a.truth.json").write_text("{}", encoding="utf-8")
    return logs


# ------------------------------------------------------------------------------------------ inputs
def test_inputs_from_globs_paths_and_list_files(tmp_path: Path) -> None:
    (tmp_path / "x.mcap").write_bytes(b"")
    (tmp_path / "y.bag").write_bytes(b"")
    (tmp_path / "x.truth.json").write_text("{}")
    bag = tmp_path / "drive_ros2"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}")
    (bag / "drive_ros2_0.db3").write_bytes(b"")
    found = resolve_inputs([str(tmp_path / "*")])
    assert found == [str(bag), str(tmp_path / "x.mcap"), str(tmp_path / "y.bag")]
    assert resolve_inputs([str(tmp_path / "**" / "*")]) == found  # files inside the bag folder = the folder
    assert resolve_inputs([str(bag / "metadata.yaml"), str(tmp_path / "x.mcap"), str(tmp_path / "x.mcap")]) == [
        str(bag), str(tmp_path / "x.mcap"),
    ]  # fmt: skip

    listing = tmp_path / "logs.txt"
    listing.write_text(f"# nightly\ny.bag  # relative to the list\n\n{tmp_path / 'x.mcap'}\nmissing.mcap\n")
    assert resolve_inputs([str(listing)]) == [
        str(tmp_path / "y.bag"), str(tmp_path / "x.mcap"), str(tmp_path / "missing.mcap"),
    ]  # fmt: skip
    with pytest.raises(InputError, match="no logs match"):
        resolve_inputs([str(tmp_path / "*.nothing")])


def test_refuses_an_output_folder_that_is_an_input_log(tmp_path: Path) -> None:
    bag = tmp_path / "drive"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}")
    with pytest.raises(InputError, match="would overwrite the log"):
        run_batch([str(tmp_path / "*")], tmp_path, Config(), workers=0, process_fn=fake_process)
    assert (bag / "metadata.yaml").is_file()


def test_output_folders_named_by_stem_and_deduplicated(tmp_path: Path) -> None:
    (tmp_path / "c" / "drive").mkdir(parents=True)
    paths = ["a/drive.mcap", "b/drive.bag", str(tmp_path / "c" / "drive"), "b/Drive.mcap", "other.mcap"]
    names = [Path(job.out_dir).name for job in plan_jobs(paths, tmp_path / "out")]
    assert names == ["drive", "drive-2", "drive-3", "Drive-4", "other"]
    assert log_stem(str(tmp_path / "c" / "drive" / "metadata.yaml")) == "drive"


# ----------------------------------------------------------------------------- manifest and fleet
def test_batch_records_every_log_and_flags_drift(fleet_logs: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    config = config_from_dict({"calibration": {"particles": 10}})
    result = run_batch([str(fleet_logs / "*.mcap")], out, config, workers=0, process_fn=fake_process)
    assert [o.status for o in result.outcomes] == ["ok", "ok", "ok", "failed", "failed"]
    assert not result.ok and result.count("failed") == 2

    rows = _manifest(out)
    assert set(rows) == {"a", "b", "c", "d", "e"}
    assert rows["d"]["error"] == "d.mcap is not a log (unknown file format)"
    assert rows["e"]["error"] == "internal error (RuntimeError: boom)"
    assert rows["a"]["status"] == "ok" and rows["a"]["error"] is None
    assert rows["a"]["verdicts"] == ["ok"] and rows["a"]["camera_topics"] == ["/camera_0/image_raw"]
    assert rows["a"]["scores"] == pytest.approx([0.6])  # the config reached the recipe
    assert rows["a"]["map_points"] == 1234 and rows["a"]["log_start_ns"] == START_NS + 200 * 10**9
    for row in rows.values():
        assert row["started_ns"] <= row["finished_ns"] and row["runtime_s"] >= 0
    assert rows["d"]["map_points"] is None and rows["d"]["verdicts"] == []
    assert rows["a"]["translations_held"] == [False] and rows["c"]["translations_held"] == [True]
    assert rows["a"]["translations_weak"] == ["x,z"] and rows["b"]["translations_weak"] == [""]

    fleet = pq.read_table(out / FLEET_FILE).to_pylist()
    assert [Path(r["out_dir"]).name for r in fleet] == ["b", "a", "c"]  # time order, not input order
    assert fleet[0]["change_deg"] is None and fleet[0]["drift"] is False
    assert fleet[1]["change_deg"] == pytest.approx(0.2, abs=1e-9)
    assert fleet[1]["change_m"] == pytest.approx(0.0, abs=1e-12) and fleet[1]["drift"] is False
    assert fleet[2]["change_deg"] == pytest.approx(0.0, abs=1e-9)
    assert fleet[2]["change_m"] == pytest.approx(0.06, abs=1e-12) and fleet[2]["drift"] is True
    assert fleet[0]["tx_m"] == pytest.approx(0.10) and fleet[1]["verdict"] == "ok"
    assert [r["translation_held"] for r in fleet] == [False, False, True]
    assert [r["translation_weak_axes"] for r in fleet] == ["", "x,z", ""]
    from fleetcal.workflows.batch import _weak_axes

    rig = {"camera_frame": "cam_back_optical", "weak_translation_axes": ["x"], "translation_axes_frame": "cam_front"}
    assert _weak_axes(rig) == "x of cam_front"  # a joint rig's axes are its reference camera's
    assert _weak_axes(dict(rig, translation_axes_frame="cam_back_optical")) == "x"
    assert _weak_axes(dict(rig, weak_translation_axes=[])) == ""
    from fleetcal.workflows.cmd_batch import fleet_table

    printed = fleet_table(fleet, 0.5, 0.05).splitlines()
    assert printed[-4].split()[1] == "c" and "0.000 held " in printed[-4]  # c's t xyz, marked
    assert printed[-5].split()[1] == "a" and "0.000 rough(x,z) " in printed[-5]
    assert " held " not in printed[-5] and "rough" not in printed[-6]
    assert printed[-2].startswith("held: the translation is the log's own")
    assert printed[-1].startswith("rough(axes): the log fixes the translation only weakly")

    tighter = fleet_summary(result.outcomes, drift_deg=0.1, drift_m=0.1)
    assert [r["drift"] for r in tighter] == [False, True, False]


def test_manifest_is_rewritten_as_each_log_finishes(fleet_logs: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    seen: list[int] = []

    def spying_process(paths: list[str], out_dir: Path, config: Config) -> ProcessSummary:
        seen.append(len(read_manifest(out)))
        return fake_process(paths, out_dir, config)

    run_batch([str(fleet_logs / "*.mcap")], out, Config(), workers=0, process_fn=spying_process)
    assert seen == [0, 1, 2, 3, 4]


def test_resume_skips_complete_logs_and_redoes_partial_and_failed_ones(fleet_logs: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    first = run_batch([str(fleet_logs / "*.mcap")], out, Config(), workers=0, process_fn=fake_process)
    before = _manifest(out)
    (out / "c" / "result.json").unlink()  # c was killed midway: partial folder
    (out / "c" / "stale.bin").write_bytes(b"junk")
    (out / "zz").mkdir()  # a folder of no log of this batch is left alone

    CALLS.clear()
    again = run_batch([str(fleet_logs / "*.mcap")], out, Config(), workers=0, resume=True, process_fn=counting_process)
    assert CALLS == ["c.mcap", "d.mcap", "e.mcap"]
    rows = _manifest(out)
    assert [rows[n]["status"] for n in "abcde"] == ["skipped", "skipped", "ok", "failed", "failed"]
    for name in "ab":  # carried over from the previous run
        for key in ("started_ns", "finished_ns", "runtime_s", "log_start_ns", "verdicts", "scores", "map_points"):
            assert rows[name][key] == before[name][key], (name, key)
    assert not (out / "c" / "stale.bin").exists() and (out / "zz").is_dir()
    assert [r["change_m"] for r in again.fleet] == pytest.approx([r["change_m"] for r in first.fleet], nan_ok=True)

    (out / MANIFEST_FILE).unlink()  # no manifest row to carry: rebuilt from result.json
    CALLS.clear()
    run_batch([str(fleet_logs / "[abc].mcap")], out, Config(), workers=0, resume=True, process_fn=counting_process)
    assert CALLS == []
    rows = _manifest(out)
    assert rows["a"]["status"] == "skipped" and rows["a"]["map_points"] == 1234 and rows["a"]["verdicts"] == ["ok"]


def test_dask_workers_give_the_same_manifest_as_in_process(fleet_logs: Path, tmp_path: Path) -> None:
    local = run_batch([str(fleet_logs / "*.mcap")], tmp_path / "a", Config(), workers=0, process_fn=fake_process)
    dask = run_batch([str(fleet_logs / "*.mcap")], tmp_path / "b", Config(), workers=1, process_fn=fake_process)
    strip = ("out_dir", "started_ns", "finished_ns", "runtime_s")
    assert [{k: v for k, v in o.row().items() if k not in strip} for o in dask.outcomes] == [
        {k: v for k, v in o.row().items() if k not in strip} for o in local.outcomes
    ]
    assert [r["change_deg"] for r in dask.fleet] == pytest.approx([r["change_deg"] for r in local.fleet], nan_ok=True)


def test_cli_usage_and_input_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["batch", str(tmp_path / "*.mcap"), "--out", str(tmp_path / "o"), "--drift-deg", "-1"]) == 2
    assert "--drift-deg must be" in capsys.readouterr().err
    assert main(["batch", str(tmp_path / "*.mcap"), "--out", str(tmp_path / "o"), "--workers", "0"]) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"error: no logs match {tmp_path / '*.mcap'}"
    with pytest.raises(SystemExit) as exit_info:
        main(["batch", str(tmp_path / "*.mcap")])
    assert exit_info.value.code == 2
    assert "--out" in capsys.readouterr().err


# ------------------------------------------------------------------- real logs, kill and resume
TINY_SIM = ["--frames", "4", "--beams", "16", "--columns", "256", "--image-size", "160x96"]
TINY_CONFIG = """
[calibration]
frames = 2
particles = 40
iterations = 20
[mapping]
max_iterations = 10
"""


def _fleetcal(*args: str) -> list[str]:
    return [sys.executable, "-m", "fleetcal.workflows.cli", *args]


@pytest.fixture(scope="module")
def real_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 tiny simulated logs (different seeds), a corrupt file and a log without a camera."""
    from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log
    from fleetcal.workflows.sinks import ros_messages as rm
    from fleetcal.workflows.sinks.log_writer import LogWriter

    logs = tmp_path_factory.mktemp("fleet")
    for seed in range(4):
        opts = SimulationOptions(frames=4, beams=16, columns=256, width=160, height=96, seed=seed, perturb_deg=1.0)
        simulate_log(logs / f"sim{seed}.mcap", opts)
    (logs / "corrupt.mcap").write_bytes(np.random.default_rng(0).bytes(4096))
    rng = np.random.default_rng(1)
    with LogWriter(logs / "nocamera.mcap", "mcap") as writer:
        for i in range(4):
            stamp = START_NS + i * 100_000_000
            points = rng.uniform(-20, 20, (2000, 3)).astype(np.float32)
            intensity = rng.uniform(0, 255, 2000).astype(np.float32)
            msg = rm.pointcloud2(stamp, "lidar", points, {"intensity": intensity})
            writer.write("/lidar/points", "sensor_msgs/msg/PointCloud2", stamp, msg)
    (logs / "tiny.toml").write_text(TINY_CONFIG, encoding="utf-8")
    return logs


def _run_batch_cli(logs: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    cmd = _fleetcal("batch", str(logs / "*.mcap"), "--out", str(out), "--workers", "2",
                    "--config", str(logs / "tiny.toml"), *extra)  # fmt: skip
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=240, check=False)


@pytest.mark.slow
def test_real_batch_kill_and_resume(real_logs: Path, tmp_path: Path) -> None:
    full = tmp_path / "full"
    done = _run_batch_cli(real_logs, full, "--json")
    assert done.returncode == 1, done.stderr
    assert done.stderr.strip().splitlines()[-1] == f"error: 2 of 6 logs failed (see {full / MANIFEST_FILE})"
    summary = json.loads(done.stdout)
    assert (summary["ok"], summary["failed"], summary["skipped"]) == (4, 2, 0)
    rows = _manifest(full)
    assert {n for n, r in rows.items() if r["status"] == "ok"} == {f"sim{s}" for s in range(4)}
    assert "corrupt.mcap" in rows["corrupt"]["error"] and "\n" not in rows["corrupt"]["error"]
    assert "camera" in rows["nocamera"]["error"].lower()
    for seed in range(4):
        row = rows[f"sim{seed}"]
        assert row["verdicts"] and row["map_points"] > 1000 and np.isfinite(row["scores"]).all()
    fleet = pq.read_table(full / FLEET_FILE).to_pylist()
    assert len(fleet) == 4 and all(r["lidar_frame"] == "lidar" for r in fleet)

    killed = tmp_path / "killed"
    proc = subprocess.Popen(
        _fleetcal("batch", str(real_logs / "*.mcap"), "--out", str(killed), "--workers", "2",
                  "--config", str(real_logs / "tiny.toml")),  # fmt: skip
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 180
        finished: list[str] = []
        while time.monotonic() < deadline and proc.poll() is None:
            if (killed / MANIFEST_FILE).is_file():
                finished = [n for n, r in _manifest(killed).items() if r["status"] == "ok"]
                if finished:
                    break
            time.sleep(0.1)
        assert proc.poll() is None, "the batch finished before it could be killed"
        assert finished
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
        deadline = time.monotonic() + 15
        while _live_processes_of_session(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not _live_processes_of_session(proc.pid), "dask workers outlived the killed batch"
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        _kill_orphans(proc.pid)
    before = _manifest(killed)
    assert len(before) < 6
    # A log can finish (result.json written last) between the manifest update and the kill: resume
    # treats its folder as complete too, so the skip set is the folders complete at the kill.
    complete_at_kill = {p.name for p in killed.iterdir() if (p / "result.json").is_file()}
    ok_before = {n for n, r in before.items() if r["status"] == "ok"}
    assert ok_before <= complete_at_kill

    resumed = _run_batch_cli(real_logs, killed, "--resume", "--json")
    assert resumed.returncode == 1, resumed.stderr
    rows = _manifest(killed)
    skipped = {n for n, r in rows.items() if r["status"] == "skipped"}
    assert skipped and skipped == complete_at_kill
    assert {n for n, r in rows.items() if r["status"] in ("ok", "skipped")} == {f"sim{s}" for s in range(4)}
    for name in sorted(ok_before):
        assert rows[name]["verdicts"] == before[name]["verdicts"]
        assert rows[name]["finished_ns"] == before[name]["finished_ns"]
    for seed in range(4):
        for table in ("calibration.parquet", "trajectory.parquet"):
            a = pq.read_table(full / f"sim{seed}" / table).drop_columns(["runtime_s"] if table[0] == "c" else [])
            b = pq.read_table(killed / f"sim{seed}" / table).drop_columns(["runtime_s"] if table[0] == "c" else [])
            assert a.num_rows >= 1 and a.to_pandas().equals(b.to_pandas()), (seed, table)  # NaN equals NaN


def _live_processes_of_session(session_id: int) -> list[int]:
    """Processes (not zombies) of the session the batch leads: its dask nannies and workers."""
    live = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z" and int(fields[3]) == session_id:
            live.append(int(entry.name))
    return live


def _kill_orphans(session_id: int) -> None:
    """SIGKILL what is left of the killed batch's session (its dask worker processes)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(session_id, signal.SIGKILL)
