"""Recipe: camera-camera calibration of one log (GOM paper 3.2.2), ``fleetcal calibrate-cameras``.

Steps: pair the two image topics by header stamp (nearest within ``io.pairing_tolerance_ns``) ->
keep ``calibration.frames`` pairs spread over the log -> gradients of each image (grey, histogram
equalisation, Gaussian blur ``default_blur_sigma_px(width)``,
Sobel) -> ``calibrate_affine_pairs``: one affine map maximising GOM summed over every pair, as the
lidar-camera objective is averaged over frames (one swarm whatever the number of pairs, the swarm on at
most ``AFFINE_SWARM_PIXELS`` pixels of all pairs, the polish on all of them) -> ``camera_camera.parquet``.

``params_std`` (JSON) is the spread of the pairs' own optima polished from the estimate. Images are used
as recorded (not undistorted); the affine map is in raw pixel coordinates, moving image -> base image.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.engine import Engine
from fleetcal.pipeline.errors import InputError, UsageError
from fleetcal.pipeline.frames import CameraFrame
from fleetcal.readers.base import LogReader
from fleetcal.readers.frames import IMAGE_TYPES, require_topic
from fleetcal.stages.calibration.affine import AffineResult, calibrate_affine_pairs
from fleetcal.stages.calibration.frame import default_blur_sigma_px
from fleetcal.stages.image_gradients import ImageGradients, compute_image_gradients
from fleetcal.stages.sinks.tables import write_rows
from fleetcal.workflows.frame_sources import LogFrames
from fleetcal.workflows.pairing import pair_stamps, raw_header_stamp_ns

log = logging.getLogger(__name__)

AFFINE_KEEP_FRACTION = 0.2
"""Fraction of the moving image's strongest gradient pixels in the objective (``calibrate_affine``)."""
AFFINE_SEARCH_PX = 20.0
"""Translation search half-width, pixels."""

CAMERA_CAMERA_SCHEMA = pa.schema(
    [
        ("base_topic", pa.string()),
        ("moving_topic", pa.string()),
        ("a00", pa.float64()),
        ("a01", pa.float64()),
        ("a02", pa.float64()),
        ("a10", pa.float64()),
        ("a11", pa.float64()),
        ("a12", pa.float64()),
        ("tx_px", pa.float64()),
        ("ty_px", pa.float64()),
        ("rotation_deg", pa.float64()),
        ("scale_x", pa.float64()),
        ("scale_y", pa.float64()),
        ("shear", pa.float64()),
        ("score", pa.float64()),
        ("initial_score", pa.float64()),
        ("frames_used", pa.int64()),
        ("runtime_s", pa.float64()),
    ]
)
"""``camera_camera.parquet``: one row per camera pair. ``a00..a12`` is the row-major (2, 3) affine
``A_base_moving`` taking moving-image pixels (u, v, 1) to base-image pixels; tx_px .. shear are its
parameters about the moving image centre (``stages.calibration.affine.affine_matrices``)."""


@dataclass
class CameraCameraCalibration:
    """Affine alignment of the moving camera's images to the base camera's.

    Attributes:
        base_topic, moving_topic: image topics.
        A_base_moving: (2, 3) moving pixels (u, v, 1) -> base pixels.
        params: (6,) tx, ty (px), rotation (deg), scale x, scale y, shear.
        score, initial_score: GOM over every pair at the estimate and at the identity map.
        frames_used: image pairs in the objective.
        runtime_s: wall time from pairing to the result, seconds.
        stamps_ns: (base stamp, moving stamp) of each pair used.
        pair_params: (pairs, 6) each pair's own optimum polished from ``params``.
    """

    base_topic: str
    moving_topic: str
    A_base_moving: NDArray[np.float64]
    params: NDArray[np.float64]
    score: float
    initial_score: float
    frames_used: int
    runtime_s: float
    stamps_ns: list[tuple[int, int]] = field(default_factory=list)
    pair_params: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 6)))

    def summary(self) -> dict[str, Any]:
        tx, ty, rot, sx, sy, shear = (float(v) for v in self.params)
        spread = np.std(self.pair_params, axis=0) if len(self.pair_params) else np.zeros(6)
        return {
            "base_topic": self.base_topic,
            "moving_topic": self.moving_topic,
            "A_base_moving": self.A_base_moving.tolist(),
            "tx_px": tx,
            "ty_px": ty,
            "rotation_deg": rot,
            "scale_x": sx,
            "scale_y": sy,
            "shear": shear,
            "params_std": spread.tolist(),
            "score": self.score,
            "initial_score": self.initial_score,
            "frames_used": self.frames_used,
            "runtime_s": self.runtime_s,
        }


def select_spread(pairs: list[tuple[int, int]], max_pairs: int) -> list[tuple[int, int]]:
    """``max_pairs`` of ``pairs`` spread evenly over the list (all of them when there are enough)."""
    if len(pairs) <= max_pairs:
        return pairs
    picks = np.unique(np.linspace(0, len(pairs) - 1, max_pairs).round().astype(np.int64))
    return [pairs[int(i)] for i in picks]


def _gradients(image: NDArray[Any]) -> ImageGradients:
    return compute_image_gradients(image, blur_sigma_px=default_blur_sigma_px(int(image.shape[1])), equalize=True)


@dataclass(frozen=True)
class _GradientStage:
    """Engine stage: the gradients of the images at ``log_times_ns`` (others: None), with their log time."""

    log_times_ns: frozenset[int]

    def __call__(self, camera: CameraFrame) -> tuple[int, ImageGradients] | None:
        if camera.log_time_ns not in self.log_times_ns:
            return None
        return camera.log_time_ns, _gradients(camera.image)


def _stamps(reader: LogReader, topics: tuple[str, str]) -> dict[str, list[tuple[int, int]]]:
    """(header stamp, log time) in ns of every message of each image topic; nothing is decoded."""
    stamps: dict[str, list[tuple[int, int]]] = {topic: [] for topic in topics}
    for raw in reader.messages(topics=list(topics)):
        stamps[raw.topic].append((raw_header_stamp_ns(raw, reader), raw.log_time_ns))
    return stamps


def collect_gradient_pairs(
    reader: LogReader, base_topic: str, moving_topic: str, config: Config, engine: Engine | None = None
) -> tuple[list[tuple[ImageGradients, ImageGradients]], list[tuple[int, int]]]:
    """Gradients of up to ``calibration.frames`` image pairs (nearest stamps) spread over the log.

    Header stamps first (nothing decoded), then only the chosen images are decoded and reduced to their
    gradients, on ``engine`` (None: in process). Returns the gradient pairs and their (base, moving) stamps in ns.

    Raises:
        InputError: a topic is missing / not an image topic, or no pair is within the tolerance.
    """
    for topic in (base_topic, moving_topic):
        require_topic(reader, topic, IMAGE_TYPES)
    stamps = _stamps(reader, (base_topic, moving_topic))
    base, moving = stamps[base_topic], stamps[moving_topic]
    tolerance = config.io.pairing_tolerance_ns
    matched = pair_stamps([s for s, _ in base], [s for s, _ in moving], tolerance)
    if not matched:
        raise InputError(
            f"no image on {base_topic} has an image on {moving_topic} within {tolerance / 1e6:g} ms "
            f"({len(base)} and {len(moving)} images)"
        )
    chosen = select_spread(matched, config.calibration.frames)
    source = LogFrames(reader.paths, config.io.allow_truncated)
    own = engine is None
    engine = Engine(workers=0, quiet=True) if engine is None else engine
    try:
        grads = {(topic, t): g for topic, times in ((base_topic, [base[b][1] for b, _ in chosen]),
                                                     (moving_topic, [moving[m][1] for _, m in chosen]))
                 for t, g in engine.map_frames(source, topic, _GradientStage(frozenset(times)), ordered=True,
                                               desc=f"{topic} gradients", log_times_ns=times)}
        for message in engine.stats.skip_examples:
            log.warning("skipping an undecodable image: %s", message)
    finally:
        if own:
            engine.close()
    out: list[tuple[ImageGradients, ImageGradients]] = []
    out_stamps: list[tuple[int, int]] = []
    for b, m in chosen:
        key_b, key_m = (base_topic, base[b][1]), (moving_topic, moving[m][1])
        if key_b in grads and key_m in grads:
            out.append((grads[key_b], grads[key_m]))
            out_stamps.append((base[b][0], moving[m][0]))
    if not out:
        raise InputError(f"none of the {len(chosen)} paired images on {base_topic} / {moving_topic} could be decoded")
    return out, out_stamps


def calibrate_cameras(reader: LogReader, base_topic: str, moving_topic: str, config: Config,
                      engine: Engine | None = None) -> CameraCameraCalibration:
    """Affine map from ``moving_topic``'s image pixels to ``base_topic``'s (one objective over the image pairs);
    the images' gradients are computed on ``engine`` (None: in process)."""
    start = time.perf_counter()
    pairs, stamps = collect_gradient_pairs(reader, base_topic, moving_topic, config, engine)
    c = config.calibration
    result: AffineResult = calibrate_affine_pairs(
        [(np.asarray(base.gxy, dtype=np.float32), moving.gx, moving.gy) for base, moving in pairs],
        search_px=AFFINE_SEARCH_PX,
        search_deg=c.search_deg, keep_fraction=AFFINE_KEEP_FRACTION, n_particles=c.particles,
        max_iterations=c.iterations,
    )  # fmt: skip
    log.info("%d pairs: params %s score %.4f (identity %.4f)", len(pairs), result.params, result.score,
             result.initial_score)  # fmt: skip
    return CameraCameraCalibration(
        base_topic, moving_topic, result.A_base_moving, result.params, result.score, result.initial_score,
        len(pairs), time.perf_counter() - start, stamps, result.pair_params,
    )  # fmt: skip


def camera_camera_row(cal: CameraCameraCalibration) -> dict[str, Any]:
    A = cal.A_base_moving
    tx, ty, rot, sx, sy, shear = (float(v) for v in cal.params)
    return {
        "base_topic": cal.base_topic, "moving_topic": cal.moving_topic,
        "a00": A[0, 0], "a01": A[0, 1], "a02": A[0, 2], "a10": A[1, 0], "a11": A[1, 1], "a12": A[1, 2],
        "tx_px": tx, "ty_px": ty, "rotation_deg": rot, "scale_x": sx, "scale_y": sy, "shear": shear,
        "score": cal.score, "initial_score": cal.initial_score, "frames_used": cal.frames_used,
        "runtime_s": cal.runtime_s,
    }  # fmt: skip


def write_camera_camera(cal: CameraCameraCalibration, out_dir: Path) -> Path:
    """``camera_camera.parquet`` (atomic)."""
    return write_rows([camera_camera_row(cal)], CAMERA_CAMERA_SCHEMA, out_dir / "camera_camera.parquet")


def run_cli(args: argparse.Namespace, config: Config) -> int:
    """``fleetcal calibrate-cameras``: the first ``--camera`` is the base, the second moves."""
    from fleetcal.workflows.calibrate import calibration_engine
    from fleetcal.workflows.cli import emit_json
    from fleetcal.workflows.common import open_logs, prepare_out_dir, table, write_config

    cameras = list(args.camera or [])
    if len(cameras) != 2:
        raise UsageError(f"calibrate-cameras needs exactly two --camera topics, got {len(cameras)}")
    if cameras[0] == cameras[1]:
        raise UsageError(f"calibrate-cameras needs two different cameras, got {cameras[0]} twice")
    out_dir = prepare_out_dir(args.out)
    with open_logs(args.logs, config, quiet=args.quiet) as reader, calibration_engine(config, args.quiet, ()) as engine:
        cal = calibrate_cameras(reader, cameras[0], cameras[1], config, engine)
    write_config(config, out_dir)
    path = write_camera_camera(cal, out_dir)
    summary = cal.summary()
    if args.json:
        emit_json({"out": str(out_dir), "camera_camera": summary})
        return 0
    row = [cal.moving_topic, cal.base_topic, f"{summary['tx_px']:.2f}", f"{summary['ty_px']:.2f}",
           f"{summary['rotation_deg']:.3f}", f"{summary['scale_x']:.4f}", f"{summary['scale_y']:.4f}",
           f"{summary['shear']:.4f}", f"{cal.initial_score:.4f}", f"{cal.score:.4f}", str(cal.frames_used),
           f"{cal.runtime_s:.1f}"]  # fmt: skip
    print(table([row], ["moving", "base", "tx px", "ty px", "rot deg", "scale x", "scale y", "shear",
                        "initial", "score", "frames", "time s"]))  # fmt: skip
    print(f"wrote {path}", file=sys.stderr)
    return 0
