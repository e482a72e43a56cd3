"""``fleetcal calibrate-cameras``: recover a known affine warp between two image topics."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.stages.calibration.affine import affine_matrices
from fleetcal.workflows.calibrate_cameras import CAMERA_CAMERA_SCHEMA, select_spread
from fleetcal.workflows.cli import main
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter

WIDTH, HEIGHT = 320, 240
CENTRE = ((WIDTH - 1) / 2.0, (HEIGHT - 1) / 2.0)
# tx, ty (px), rotation (deg), scale x, scale y, shear: moving pixels -> base pixels.
TRUE_PARAMS = np.array([3.0, -2.0, 1.0, 1.02, 1.02, 0.0])
FRAME_NS = 100_000_000


def textured_image(seed: int) -> NDArray[np.uint8]:
    """Blurred noise plus a few filled shapes: edges in every direction at several scales."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random((HEIGHT, WIDTH)).astype(np.float32), (0, 0), 4.0)
    img = np.rint(200 * (noise - noise.min()) / (noise.max() - noise.min())).astype(np.uint8)
    for _ in range(12):
        x, y = int(rng.integers(20, WIDTH - 20)), int(rng.integers(20, HEIGHT - 20))
        colour = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.circle(img, (x, y), int(rng.integers(6, 25)), colour, -1)
        else:
            w, h = int(rng.integers(8, 40)), int(rng.integers(8, 40))
            cv2.rectangle(img, (x - w, y - h), (x + w, y + h), colour, -1)
    return img


def warp_to_moving(base: NDArray[np.uint8], A_base_moving: NDArray[np.float64]) -> NDArray[np.uint8]:
    """The moving camera's image: moving(u, v) = base(A_base_moving @ (u, v, 1)), contrast inverted."""
    moving = cv2.warpAffine(
        base,
        A_base_moving,
        (WIDTH, HEIGHT),
        flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REFLECT,
    )
    return np.asarray(255 - moving, dtype=np.uint8)  # a different spectral band: inverted contrast


def write_rig_log(path: Path, n_frames: int, moving_offset_ns: int) -> None:
    """Two cameras (``/cam_a``, ``/cam_b``) with CameraInfo; ``/cam_b`` stamps shifted by ``moving_offset_ns``."""
    A = affine_matrices(TRUE_PARAMS, CENTRE)[0]
    K = np.array([[300.0, 0.0, CENTRE[0]], [0.0, 300.0, CENTRE[1]], [0.0, 0.0, 1.0]])
    camera = CameraModel(WIDTH, HEIGHT, K, np.zeros(5), "plumb_bob")
    with LogWriter(path, "mcap") as writer:
        for topic, frame in (("/cam_a", "cam_a"), ("/cam_b", "cam_b")):
            writer.write(f"{topic}/camera_info", "sensor_msgs/msg/CameraInfo", 1,
                         rm.camera_info(1, frame, camera))  # fmt: skip
        for i in range(n_frames):
            base = textured_image(i)
            stamp = 1_000_000_000 + i * FRAME_NS
            writer.write("/cam_a/image_raw", "sensor_msgs/msg/Image", stamp,
                         rm.image(stamp, "cam_a", base, "mono8"))  # fmt: skip
            stamp_b = stamp + moving_offset_ns
            writer.write("/cam_b/image_raw", "sensor_msgs/msg/Image", stamp_b,
                         rm.image(stamp_b, "cam_b", warp_to_moving(base, A), "mono8"))  # fmt: skip


def test_camera_camera_recovers_known_affine(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log_path = tmp_path / "rig.mcap"
    write_rig_log(log_path, n_frames=6, moving_offset_ns=3_000_000)
    out = tmp_path / "out"
    rc = main([
        "calibrate-cameras", str(log_path), "--camera", "/cam_a/image_raw",
        "--camera", "/cam_b/image_raw", "--frames", "3", "--json", "-q", "--out", str(out),
    ])  # fmt: skip
    assert rc == 0
    result = json.loads(capsys.readouterr().out)["camera_camera"]
    table = pq.read_table(out / "camera_camera.parquet")
    assert table.schema.equals(CAMERA_CAMERA_SCHEMA)
    assert table.num_rows == 1
    row = table.to_pylist()[0]
    assert (row["base_topic"], row["moving_topic"]) == ("/cam_a/image_raw", "/cam_b/image_raw")
    assert row["frames_used"] == result["frames_used"] == 3
    got = np.array([row[k] for k in ("tx_px", "ty_px", "rotation_deg", "scale_x", "scale_y", "shear")])
    np.testing.assert_allclose(got, [result[k] for k in ("tx_px", "ty_px", "rotation_deg", "scale_x",
                                                          "scale_y", "shear")])  # fmt: skip
    err = got - TRUE_PARAMS
    assert np.all(np.abs(err[:2]) < 0.5), f"translation error {err[:2]} px"
    assert abs(err[2]) < 0.2, f"rotation error {err[2]} deg"
    assert np.all(np.abs(err[3:5]) < 0.005), f"scale error {err[3:5]}"
    assert abs(err[5]) < 0.005, f"shear error {err[5]}"
    # The stored matrix is the map of those parameters and moves every pixel by < 0.5 px from the truth.
    A = np.array([[row["a00"], row["a01"], row["a02"]], [row["a10"], row["a11"], row["a12"]]])
    np.testing.assert_allclose(A, affine_matrices(got, CENTRE)[0], atol=1e-9)
    corners = np.array([[0.0, 0.0], [WIDTH - 1, 0.0], [0.0, HEIGHT - 1], [WIDTH - 1, HEIGHT - 1]])
    A_true = affine_matrices(TRUE_PARAMS, CENTRE)[0]
    mapped_err = corners @ (A[:, :2] - A_true[:, :2]).T + (A[:, 2] - A_true[:, 2])
    assert np.max(np.linalg.norm(mapped_err, axis=1)) < 0.5
    assert row["score"] > row["initial_score"] + 0.1
    assert row["runtime_s"] > 0
    assert (out / "config.toml").exists()


def test_camera_camera_needs_exactly_two_cameras(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log_path = tmp_path / "rig.mcap"
    write_rig_log(log_path, n_frames=1, moving_offset_ns=0)
    base = ["calibrate-cameras", str(log_path), "--out", str(tmp_path / "out")]
    assert main([*base, "--camera", "/cam_a/image_raw"]) == 2
    assert "exactly two --camera" in capsys.readouterr().err
    three = ["--camera", "/cam_a/image_raw", "--camera", "/cam_b/image_raw", "--camera", "/cam_c/image_raw"]
    assert main([*base, *three]) == 2
    with pytest.raises(SystemExit) as no_camera:
        main(base)
    assert no_camera.value.code == 2
    assert not (tmp_path / "out").exists()


def test_camera_camera_no_pairs_within_tolerance(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log_path = tmp_path / "rig.mcap"
    write_rig_log(log_path, n_frames=3, moving_offset_ns=10_000_000_000)  # /cam_b starts after /cam_a ends
    rc = main(["calibrate-cameras", str(log_path), "--camera", "/cam_a/image_raw",
               "--camera", "/cam_b/image_raw", "--out", str(tmp_path / "out")])  # fmt: skip
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: no image on /cam_a/image_raw has an image on /cam_b/image_raw within 50 ms")
    assert "\n" not in err
    assert not (tmp_path / "out" / "camera_camera.parquet").exists()


def test_select_spread_keeps_ends_and_order() -> None:
    pairs = [(i, i + 1) for i in range(10)]
    assert select_spread(pairs, 3) == [(0, 1), (4, 5), (9, 10)]
    assert select_spread(pairs, 20) == pairs


def striped_image(angle_deg: float, seed: int) -> NDArray[np.uint8]:
    """Stripes of random widths across the image at ``angle_deg``: edges in one direction only, so a pair of
    such images fixes the affine map across the stripes and leaves it free along them."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    th = np.radians(angle_deg)
    across = u * np.cos(th) + v * np.sin(th)
    edges = np.cumsum(rng.uniform(6.0, 20.0, 64)) - 200.0
    levels = rng.integers(0, 256, edges.size + 1)
    img = levels[np.searchsorted(edges, across)].astype(np.float32)
    return np.asarray(np.rint(cv2.GaussianBlur(img, (0, 0), 1.0)), dtype=np.uint8)


def test_pairs_with_edges_in_one_direction_each_fix_the_map_together() -> None:
    """Each pair's stripes leave the map free along them; three directions in one objective fix all of it."""
    from fleetcal.stages.calibration.affine import calibrate_affine_pairs
    from fleetcal.stages.image_gradients import compute_image_gradients

    A = affine_matrices(TRUE_PARAMS, CENTRE)[0]
    pairs = []
    for i, angle in enumerate((0.0, 60.0, 120.0)):
        base = striped_image(angle, i)
        b = compute_image_gradients(base, blur_sigma_px=1.0, equalize=True)
        m = compute_image_gradients(warp_to_moving(base, A), blur_sigma_px=1.0, equalize=True)
        pairs.append((b.gxy, m.gx, m.gy))
    result = calibrate_affine_pairs(pairs, search_px=8.0, search_deg=3.0, n_particles=100, max_iterations=60)
    corners = np.array([[0.0, 0.0], [WIDTH - 1, 0.0], [0.0, HEIGHT - 1], [WIDTH - 1, HEIGHT - 1]])
    mapped_err = corners @ (result.A_base_moving[:, :2] - A[:, :2]).T + (result.A_base_moving[:, 2] - A[:, 2])
    assert np.max(np.linalg.norm(mapped_err, axis=1)) < 0.5, f"corners off by {mapped_err} px"
    assert result.pair_params.shape == (3, 6)


def test_gradients_on_dask_workers_equal_the_in_process_ones(tmp_path: Path) -> None:
    from fleetcal.pipeline.config import Config
    from fleetcal.pipeline.engine import Engine
    from fleetcal.readers.open import open_log
    from fleetcal.workflows.calibrate_cameras import collect_gradient_pairs

    log_path = tmp_path / "rig.mcap"
    write_rig_log(log_path, n_frames=4, moving_offset_ns=3_000_000)
    with open_log(log_path) as reader:
        in_process, stamps = collect_gradient_pairs(reader, "/cam_a/image_raw", "/cam_b/image_raw", Config())
        with Engine(workers=2, quiet=True) as engine:
            on_workers, stamps_workers = collect_gradient_pairs(reader, "/cam_a/image_raw", "/cam_b/image_raw",
                                                                Config(), engine)
    assert stamps == stamps_workers and len(stamps) == 4
    for (base, moving), (base_w, moving_w) in zip(in_process, on_workers, strict=True):
        for a, b in ((base, base_w), (moving, moving_w)):
            np.testing.assert_array_equal(a.gx, b.gx)
            np.testing.assert_array_equal(a.gy, b.gy)
