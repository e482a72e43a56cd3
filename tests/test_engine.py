"""Engine: batching, in-process vs dask equality, skips, worker death, an external scheduler."""

from __future__ import annotations

import functools
import itertools
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import pytest

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.config import load_config
from fleetcal.pipeline.engine import Engine, plan_batches, run_batch
from fleetcal.pipeline.errors import InputError, ProcessingError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.pipeline.progress import Progress
from fleetcal.readers.frames import iter_lidar_frames
from fleetcal.readers.open import open_log
from fleetcal.stages.image_gradients import camera_frame_gradients
from fleetcal.stages.lidar_features import lidar_frame_feature
from fleetcal.workflows.frame_sources import LogFrames
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter

cloudpickle.register_pickle_by_value(sys.modules[__name__])

LIDAR = "/lidar/points"
CAMERA = "/cam/image_raw"
N_LIDAR = 40
N_CAMERA = 12
EMPTY_SCANS = (7, 23)
BLANK_IMAGES = (5,)
T0 = 1_700_000_000_000_000_000
VENV_BIN = Path(sys.executable).parent


def _write_log(path: Path) -> Path:
    rng = np.random.default_rng(42)
    camera = CameraModel(
        64, 48, np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), np.zeros(5), "plumb_bob"
    )
    with LogWriter(path, "mcap") as writer:
        writer.write("/cam/camera_info", "sensor_msgs/msg/CameraInfo", T0, rm.camera_info(T0, "cam", camera))
        for i in range(N_LIDAR):
            stamp = T0 + i * 100_000_000
            n = 1500 + 10 * i
            points = (rng.normal(size=(n, 3)) * [10.0, 10.0, 2.0]).astype(np.float32)
            if i == EMPTY_SCANS[0]:
                points = points[:0]
            elif i == EMPTY_SCANS[1]:
                points[:] = np.nan
            channels = {"intensity": rng.random(len(points)).astype(np.float32)}
            writer.write(
                LIDAR,
                "sensor_msgs/msg/PointCloud2",
                stamp + 5_000,
                rm.pointcloud2(stamp, "lidar", points, channels),
            )
        for i in range(N_CAMERA):
            stamp = T0 + i * 333_000_000
            image = rng.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
            if i in BLANK_IMAGES:
                image[:] = 90
            writer.write(
                CAMERA, "sensor_msgs/msg/Image", stamp + 7_000, rm.image(stamp, "cam", image, "rgb8")
            )
    return path


@pytest.fixture(scope="module")
def log_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _write_log(tmp_path_factory.mktemp("engine") / "fleet.mcap")


@pytest.fixture(scope="module")
def dask_engine() -> Iterator[Engine]:
    with Engine(workers=2, quiet=True) as engine:
        engine.client.wait_for_workers(2, timeout=60)
        yield engine


range_stage = functools.partial(lidar_frame_feature, kind="range")


def _by_stamp(results: list[Any]) -> dict[int, Any]:
    return {r.stamp_ns: r for r in results}


def test_plan_batches_cover_every_message_once(log_path: Path) -> None:
    batches = plan_batches(LogFrames(log_path), LIDAR, batch_size=6)
    assert [b.n_messages for b in batches] == [6] * 6 + [4]
    assert all(a.end_ns == b.start_ns for a, b in itertools.pairwise(batches))
    with open_log(log_path) as reader:
        times = [raw.log_time_ns for raw in reader.messages([LIDAR])]
    assert batches[0].start_ns == times[0] and batches[-1].end_ns == times[-1] + 1
    ranged = plan_batches(LogFrames(log_path), LIDAR, batch_size=4, start_ns=times[10], end_ns=times[30])
    assert sum(b.n_messages for b in ranged) == 20
    assert plan_batches(LogFrames(log_path), LIDAR, start_ns=times[-1] + 1) == []
    with pytest.raises(InputError, match="not in the log"):
        plan_batches(LogFrames(log_path), "/nope")
    with pytest.raises(InputError, match="CameraInfo"):
        plan_batches(LogFrames(log_path), "/cam/camera_info")


def test_in_process_results_equal_direct_computation_and_skips_are_counted(log_path: Path) -> None:
    with Engine.from_config(load_config(env={"FLEETCAL_ENGINE__WORKERS": "0"}).engine, quiet=True) as engine:
        assert engine.in_process and engine.client is None
        results = list(engine.map_frames(LogFrames(log_path), LIDAR, range_stage, batch_size=8))
        stats = engine.stats
    assert stats.frames_total == N_LIDAR
    assert stats.frames_done == N_LIDAR - len(EMPTY_SCANS) == len(results)
    assert stats.frames_skipped == len(EMPTY_SCANS)
    assert stats.skip_reasons == {"no valid points": len(EMPTY_SCANS)}
    assert stats.batches == 5
    with open_log(log_path) as reader:
        frames = [f for f in iter_lidar_frames(reader, LIDAR) if f.n_points]
    assert [r.stamp_ns for r in results] == [f.stamp_ns for f in frames]
    for result, frame in zip(results, frames, strict=True):
        direct = lidar_frame_feature(frame, kind="range")
        np.testing.assert_array_equal(result.feature, direct.feature)
        assert result.n_points == frame.n_points


def _camera_stage(frame: CameraFrame) -> tuple[int, float, float]:
    assert frame.camera is not None
    result = camera_frame_gradients(frame, blur_sigma_px=1.0)
    return frame.stamp_ns, frame.camera.fx, float(result.gradients.magnitude.sum())


def _picky_stage(frame: LidarFrame) -> int | None:
    index = (frame.stamp_ns - T0) // 100_000_000
    if index % 10 == 1:
        raise InputError(f"frame {index} rejected")
    if index % 10 == 2:
        return None
    return int(index)


def _broken_stage(frame: LidarFrame) -> int:
    raise ValueError("bug in a stage")


def test_camera_frames_blank_skipped_and_camera_model_attached(log_path: Path) -> None:
    with Engine(workers=0, quiet=True) as engine:
        results = list(engine.map_frames(LogFrames(log_path), CAMERA, _camera_stage, batch_size=5))
        assert engine.stats.skip_reasons == {"blank image": 1}
    assert len(results) == N_CAMERA - 1
    assert all(fx == 50.0 and magnitude > 0 for _, fx, magnitude in results)


def test_stage_input_errors_and_none_are_skipped_and_bugs_raise(log_path: Path) -> None:
    with Engine(workers=0, quiet=True) as engine:
        kept = list(engine.map_frames(LogFrames(log_path), LIDAR, _picky_stage, batch_size=16))
        assert engine.stats.skip_reasons == {
            "stage InputError": 4,
            "stage returned None": 4,
            "no valid points": len(EMPTY_SCANS),
        }
        assert sorted(kept) == sorted(set(range(N_LIDAR)) - {1, 11, 21, 31, 2, 12, 22, 32, *EMPTY_SCANS})
        assert any("rejected" in msg for msg in engine.stats.skip_examples)
        with pytest.raises(ProcessingError, match=r"_broken_stage failed on /lidar/points.*bug in a stage"):
            list(engine.map_frames(LogFrames(log_path), LIDAR, _broken_stage))


def test_dask_results_equal_in_process(log_path: Path, dask_engine: Engine) -> None:
    with Engine(workers=0, quiet=True) as local:
        expected = _by_stamp(list(local.map_frames(LogFrames(log_path), LIDAR, range_stage, batch_size=6)))
    got = list(dask_engine.map_frames(LogFrames(log_path), LIDAR, range_stage, batch_size=6))
    assert dask_engine.stats.frames_done == len(expected) == len(got)
    assert dask_engine.stats.skip_reasons == {"no valid points": len(EMPTY_SCANS)}
    pids = {pid for pid in dask_engine.client.run(os.getpid).values()}
    assert len(pids) == 2 and os.getpid() not in pids
    for stamp, result in _by_stamp(got).items():
        np.testing.assert_array_equal(result.feature, expected[stamp].feature)
    ordered = list(dask_engine.map_frames(LogFrames(log_path), LIDAR, range_stage, batch_size=3, ordered=True))
    stamps = [r.stamp_ns for r in ordered]
    assert stamps == sorted(expected)


def test_dask_window_bounds_tasks_in_flight(log_path: Path, dask_engine: Engine) -> None:
    engine = Engine(workers=2, quiet=True, max_in_flight=2)
    engine._client = dask_engine.client
    pending: list[int] = []
    held: list[int] = []
    for _ in engine.map_frames(LogFrames(log_path), LIDAR, _slow_stage, batch_size=2):
        states = list(dask_engine.client.futures.values())
        pending.append(sum(state.status == "pending" for state in states))
        held.append(len(states))
    engine._client = None
    assert engine.stats.frames_done == N_LIDAR - len(EMPTY_SCANS) and engine.stats.batches == 20
    # 2 tasks queued/running at most; +1 finished batch whose release is still on its way.
    assert 1 <= max(pending) <= 2 and max(held) <= 3, (pending, held)


def _slow_stage(frame: LidarFrame) -> int:
    time.sleep(0.04)
    return frame.stamp_ns


def test_killed_worker_tasks_are_retried_and_run_completes(log_path: Path) -> None:
    with Engine(workers=2, quiet=True, max_in_flight=4) as engine:
        engine.client.wait_for_workers(2, timeout=60)
        pids = list(engine.client.run(os.getpid).values())
        results: list[int] = []
        for i, stamp in enumerate(engine.map_frames(LogFrames(log_path), LIDAR, _slow_stage, batch_size=4)):
            results.append(stamp)
            if i == 0:
                os.kill(pids[0], signal.SIGKILL)
        assert sorted(results) == [T0 + i * 100_000_000 for i in range(N_LIDAR) if i not in EMPTY_SCANS]
        assert engine.stats.frames_skipped == len(EMPTY_SCANS)
        new_pids = set(engine.client.run(os.getpid).values())
    assert pids[0] not in new_pids


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def test_external_scheduler_and_worker_subprocesses(log_path: Path) -> None:
    dask_cli = VENV_BIN / "dask"
    if not dask_cli.exists():
        pytest.skip(f"the dask command line is not installed next to {sys.executable}")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    procs: list[subprocess.Popen[bytes]] = []
    try:
        procs.append(
            subprocess.Popen(
                [str(dask_cli), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
        procs.append(
            subprocess.Popen(
                [str(dask_cli), "worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"],
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
        deadline = time.monotonic() + 60
        engine = None
        while engine is None:
            try:
                engine = Engine(scheduler=address, quiet=True)
                engine.client.wait_for_workers(1, timeout=60)
            except Exception:
                if engine is not None:
                    engine.close()
                engine = None
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)
        with engine:
            worker_pids = set(engine.client.run(os.getpid).values())
            results = list(engine.map_frames(LogFrames(log_path), LIDAR, range_stage, batch_size=10))
            assert engine.stats.frames_done == N_LIDAR - len(EMPTY_SCANS)
        assert os.getpid() not in worker_pids
        with Engine(workers=0, quiet=True) as local:
            expected = _by_stamp(list(local.map_frames(LogFrames(log_path), LIDAR, range_stage, batch_size=10)))
        for stamp, result in _by_stamp(results).items():
            np.testing.assert_array_equal(result.feature, expected[stamp].feature)
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in reversed(procs):
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def test_run_batch_reports_worker_side_counts(log_path: Path) -> None:
    batch = plan_batches(LogFrames(log_path), LIDAR, batch_size=10)[0]
    result = run_batch(batch, range_stage)
    assert result.frames_done == 9 and result.skip_reasons == {"no valid points": 1}
    assert result.worker_pid == os.getpid() and result.worker_s > 0 and result.worker_cpu_s > 0


def test_in_process_yields_each_frame_before_staging_the_next(log_path: Path) -> None:
    """In-process, a frame's result reaches the consumer before the batch's next frame is staged, so a
    consumer on another thread overlaps with the stage (mapping registers while the next scan is prepared)."""
    staged: list[int] = []

    def stage(frame: LidarFrame) -> int:
        staged.append(frame.stamp_ns)
        return frame.stamp_ns

    with Engine(workers=0, quiet=True) as engine:
        seen_when_yielded = [len(staged) for _ in engine.map_frames(LogFrames(log_path), LIDAR, stage, batch_size=32)]
        stats = engine.stats
    assert seen_when_yielded == list(range(1, N_LIDAR - len(EMPTY_SCANS) + 1))
    assert stats.batches == 2 and stats.frames_done == N_LIDAR - len(EMPTY_SCANS)
    assert stats.skip_reasons == {"no valid points": len(EMPTY_SCANS)}


def test_progress_bar_is_quiet_for_short_work_and_reports_rate() -> None:
    class Sink:
        def __init__(self) -> None:
            self.text = ""

        def write(self, s: str) -> int:
            self.text += s
            return len(s)

        def flush(self) -> None:
            pass

    fast = Sink()
    with Progress(10, "x", stream=fast) as bar:  # type: ignore[arg-type]
        bar.update(10)
    assert fast.text == ""
    slow = Sink()
    bar = Progress(10, "lidar", stream=slow, delay_s=0.0, line_interval_s=0.0)  # type: ignore[arg-type]
    bar.update(4)
    bar.close()
    assert "lidar 4/10 frames" in slow.text and "frames/s" in slow.text
    quiet = Sink()
    with Progress(10, stream=quiet, quiet=True, delay_s=0.0) as bar:  # type: ignore[arg-type]
        bar.update(5)
    assert quiet.text == ""


def test_real_kitti_log_lidar_and_camera_in_process(shared_data: Path) -> None:
    log = shared_data / "logs" / "kitti_2011_09_26.mcap"
    with Engine(workers=0, quiet=True) as engine:
        lidar = list(engine.map_frames(LogFrames(log), "/kitti/velo/pointcloud", range_stage, ordered=True))
        assert engine.stats.frames_total == engine.stats.frames_done == 2
        cameras = list(engine.map_frames(LogFrames(log), "/kitti/camera_color_left/image_raw", _camera_stage))
    assert [r.n_points > 100_000 for r in lidar] == [True, True]
    assert len(cameras) == 2 and all(abs(fx - 721.5377) < 1e-3 for _, fx, _ in cameras)


def test_tasks_carry_no_frames_and_early_stop_cancels(log_path: Path, dask_engine: Engine) -> None:
    batch = plan_batches(LogFrames(log_path), LIDAR, batch_size=32)[0]
    assert batch.n_messages == 32
    assert len(cloudpickle.dumps((batch, range_stage))) < 4096  # 32 scans of ~1500 points would be ~750 kB
    stream = dask_engine.map_frames(LogFrames(log_path), LIDAR, _slow_stage, batch_size=2)
    first = next(stream)
    stream.close()
    assert first >= T0
    deadline = time.monotonic() + 10
    while dask_engine.client.futures and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not dask_engine.client.futures
    assert len(list(dask_engine.map_frames(LogFrames(log_path), LIDAR, range_stage, batch_size=20))) == N_LIDAR - 2


def test_local_cluster_serves_no_dashboard_on_port_8787() -> None:
    """Two fleetcal jobs side by side: with 8787 taken, the local cluster starts without dask's "port in
    use" warning, and its scheduler's HTTP server listens on another port of localhost only."""
    import warnings

    with socket.socket() as taken:
        try:
            taken.bind(("127.0.0.1", 8787))
        except OSError:
            pytest.skip("port 8787 is in use here")
        taken.listen()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with Engine(workers=1, quiet=True) as engine:
                engine.client.wait_for_workers(1, timeout=60)
                info = engine.client.scheduler_info()
    assert not [w for w in caught if "8787" in str(w.message)]
    assert info["address"].startswith("tcp://127.0.0.1:")
    assert all(port != 8787 for port in info["services"].values())
