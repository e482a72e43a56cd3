"""The calibration's per-frame work (decoding, lidar feature, image gradients) on the engine: the same
frames with dask workers as in process, and as the chosen pairs decoded and built one by one; only the
chosen messages are decoded; ``calibrate --workers 2`` gives the in-process answer."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.engine import Engine
from fleetcal.readers.frames import load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration.frame import CalibrationFrame, build_frame
from fleetcal.workflows import calibrate as calibrate_workflow
from fleetcal.workflows.calibrate import ScansSeen, collect_frames
from fleetcal.workflows.cli import main
from fleetcal.workflows.pairing import iter_pairs
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

LIDAR, CAMERA = "/lidar/points", "/camera_0/image_raw"


@pytest.fixture(scope="module")
def small_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log = tmp_path_factory.mktemp("calib_engine") / "small.mcap"
    simulate_log(log, SimulationOptions(frames=6, beams=16, columns=256, width=160, height=96, seed=2,
                                        deskew=False), quiet=True)
    return log


def _config() -> Config:
    config = Config()
    config.calibration.frames = 3
    config.calibration.feature = "intensity+range"
    return config


def _collect(log: Path, engine: Engine | None) -> list[CalibrationFrame]:
    with open_log(log) as reader:
        return collect_frames(reader, LIDAR, CAMERA, _config(), load_tf_tree(reader), engine).frames


def _assert_same(a: list[CalibrationFrame], b: list[CalibrationFrame], motion: bool = True) -> None:
    assert [f.stamp_ns for f in a] == [f.stamp_ns for f in b]
    for fa, fb in zip(a, b, strict=True):
        np.testing.assert_array_equal(fa.points_xyz, fb.points_xyz)
        np.testing.assert_array_equal(fa.feature, fb.feature)
        np.testing.assert_array_equal(fa.gradients.gxy, fb.gradients.gxy)
        np.testing.assert_array_equal(np.asarray(fa.intensity), np.asarray(fb.intensity))
        np.testing.assert_array_equal(fa.camera.K, fb.camera.K)
        if motion:
            np.testing.assert_array_equal(fa.point_time_offsets_s, fb.point_time_offsets_s)  # type: ignore[arg-type]
            np.testing.assert_array_equal(fa.twist_lidar, fb.twist_lidar)  # type: ignore[arg-type]


def test_engine_frames_are_the_in_process_frames_and_only_the_chosen_are_decoded(small_log: Path) -> None:
    in_process = _collect(small_log, None)
    assert len(in_process) == 3
    assert in_process[0].feature.shape[1] == 2
    assert all(f.twist_lidar is not None for f in in_process)  # per-point times of the skewed sweeps
    with Engine(workers=2, quiet=True) as engine:
        on_workers = _collect(small_log, engine)
        assert engine.stats.frames_total == 3  # the image topic's run: the 3 chosen images of 6
    _assert_same(in_process, on_workers)


def test_engine_frames_are_the_pairs_built_one_by_one(small_log: Path) -> None:
    """Reference: ``iter_pairs`` decodes the same 3 pairs spread over the log and ``build_frame`` builds
    each in process."""
    config = _config()
    with open_log(small_log) as reader:
        pairs = list(iter_pairs(reader, LIDAR, CAMERA, config.io.pairing_tolerance_ns, max_pairs=3))
    reference = [replace(build_frame(lidar, camera, config.calibration.feature), intensity=None)  # GOM: no grey
                 for lidar, camera in pairs]
    _assert_same(reference, _collect(small_log, None), motion=False)


def test_frames_hold_the_equalised_grey_only_for_nmi(small_log: Path) -> None:
    """The equalised grey is the NMI metric's image term: a GOM calibration's frames do not hold it, an NMI
    one's hold the whole image's."""
    assert all(f.intensity is None for f in _collect(small_log, None))
    config = _config()
    config.calibration.metric = "nmi"
    with open_log(small_log) as reader:
        frames = collect_frames(reader, LIDAR, CAMERA, config, load_tf_tree(reader)).frames
    assert len(frames) == 3
    assert all(f.intensity is not None and f.intensity.shape == (96, 160) and f.intensity.dtype == np.uint8
               for f in frames)


def test_cameras_of_one_run_share_each_scan(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two cameras pairing with the same scans: the second camera's frames reuse the first's decoded scans
    (the lidar stage runs once per scan) and hold the same float64 points array, and equal the frames it
    collects on its own."""
    log = tmp_path / "two_cameras.mcap"
    simulate_log(log, SimulationOptions(frames=4, beams=16, columns=256, width=160, height=96, seed=3, cameras=2,
                                        deskew=False), quiet=True)
    featured: list[int] = []
    stage = calibrate_workflow.lidar_feature_stage

    def counted(lidar: object, feature: str = "range") -> object:
        featured.append(lidar.stamp_ns)  # type: ignore[attr-defined]
        return stage(lidar, feature)  # type: ignore[arg-type]

    monkeypatch.setattr(calibrate_workflow, "lidar_feature_stage", counted)
    seen = ScansSeen()
    with open_log(log) as reader:
        tree = load_tf_tree(reader)
        first, second = (collect_frames(reader, LIDAR, f"/camera_{k}/image_raw", _config(), tree, None, seen).frames
                         for k in range(2))
        assert len(featured) == len(set(featured)) == 3
        alone = collect_frames(reader, LIDAR, "/camera_1/image_raw", _config(), tree).frames
    assert [f.label for f in second] == ["/camera_1/image_raw"] * 3
    assert all(a.points_xyz is b.points_xyz and a.points_xyz.dtype == np.float64
               for a, b in zip(first, second, strict=True))
    _assert_same(alone, second)


def test_calibrate_on_two_workers_gives_the_in_process_answer(
    small_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    for name, value in {"PARTICLES": "30", "ITERATIONS": "15", "REPEATS": "1", "FRAMES": "3"}.items():
        monkeypatch.setenv(f"FLEETCAL_CALIBRATION__{name}", value)
    answers = []
    for workers in ("0", "2"):
        argv = ["calibrate", str(small_log), "--workers", workers, "--no-report", "--json", "-q",
                "--out", str(tmp_path / workers)]
        assert main(argv) == 0
        answers.append(json.loads(capsys.readouterr().out)["pairs"][0])
    np.testing.assert_array_equal(answers[0]["T_camera_lidar"], answers[1]["T_camera_lidar"])
    assert answers[0]["score"] == answers[1]["score"]
