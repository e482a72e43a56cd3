"""Recipe: camera-camera calibration of one log (GOM paper 3.2.2), ``fleetcal calibrate-cameras``.

Steps: pair the two image topics by header stamp (nearest within ``io.pairing_tolerance_ns``) ->
keep ``calibration.frames`` pairs spread over the log -> gradients of each image (grey, histogram
equalisation, Gaussian blur ``default_blur_sigma_px(width)``,
Sobel) -> ``calibrate_affine`` on each pair -> the median of the per-pair parameters ->
``camera_camera.parquet``.

``calibrate_affine`` takes one image pair, so the metric is not averaged over pairs: each pair is
solved on its own and the result is the element-wise median of the six parameters (tx, ty, rotation,
scale x, scale y, shear), robust to a pair that locked onto a wrong optimum. ``score`` and
``initial_score`` are the medians of the per-pair scores. Images are used as recorded (not
undistorted); the affine map is in raw pixel coordinates, moving image -> base image.
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
from fleetcal.pipeline.errors import DecodeError, InputError, UsageError
from fleetcal.readers.base import LogReader
from fleetcal.readers.frames import IMAGE_TYPES, decode_camera_image, require_topic
from fleetcal.stages.calibration.affine import AffineResult, affine_matrices, calibrate_affine
from fleetcal.stages.calibration.frame import default_blur_sigma_px
from fleetcal.stages.image_gradients import ImageGradients, compute_image_gradients
from fleetcal.stages.sinks.tables import write_rows
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
        A_base_moving: (2, 3) moving pixels (u, v, 1) -> base pixels, from the median parameters.
        params: (6,) median tx, ty (px), rotation (deg), scale x, scale y, shear.
        score, initial_score: median per-pair GOM at the estimate and at the identity map.
        frames_used: image pairs solved.
        runtime_s: wall time from pairing to the result, seconds.
        stamps_ns: (base stamp, moving stamp) of each pair used.
        per_pair: the ``AffineResult`` of each pair.
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
    per_pair: list[AffineResult] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        tx, ty, rot, sx, sy, shear = (float(v) for v in self.params)
        spread = np.std([r.params for r in self.per_pair], axis=0) if self.per_pair else np.zeros(6)
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


def collect_gradient_pairs(
    reader: LogReader, base_topic: str, moving_topic: str, config: Config
) -> tuple[list[tuple[ImageGradients, ImageGradients]], list[tuple[int, int]]]:
    """Gradients of up to ``calibration.frames`` image pairs (nearest stamps) spread over the log.

    Two passes: header stamps only (nothing decoded), then only the chosen images are decoded; each
    image is reduced to its gradients at once. Returns the gradient pairs and their (base, moving)
    stamps in ns.

    Raises:
        InputError: a topic is missing / not an image topic, or no pair is within the tolerance.
    """
    types = {t: require_topic(reader, t, IMAGE_TYPES) for t in (base_topic, moving_topic)}
    stamps: dict[str, list[int]] = {base_topic: [], moving_topic: []}
    for raw in reader.messages(topics=[base_topic, moving_topic]):
        stamps[raw.topic].append(raw_header_stamp_ns(raw, reader))
    tolerance = config.io.pairing_tolerance_ns
    matched = pair_stamps(stamps[base_topic], stamps[moving_topic], tolerance)
    if not matched:
        raise InputError(
            f"no image on {base_topic} has an image on {moving_topic} within {tolerance / 1e6:g} ms "
            f"({len(stamps[base_topic])} and {len(stamps[moving_topic])} images)"
        )
    chosen = select_spread(matched, config.calibration.frames)
    wanted = {base_topic: {b for b, _ in chosen}, moving_topic: {m for _, m in chosen}}
    grads: dict[tuple[str, int], ImageGradients] = {}
    seen = {base_topic: -1, moving_topic: -1}
    for raw in reader.messages(topics=[base_topic, moving_topic]):
        seen[raw.topic] += 1
        index = seen[raw.topic]
        if index not in wanted[raw.topic]:
            continue
        try:
            frame = decode_camera_image(types[raw.topic], reader.deserialize(raw), raw.topic, raw.log_time_ns)
        except DecodeError as err:
            log.warning("skipping an undecodable image on %s at log time %d: %s", raw.topic, raw.log_time_ns, err)
            continue
        grads[(raw.topic, index)] = _gradients(frame.image)
    out: list[tuple[ImageGradients, ImageGradients]] = []
    out_stamps: list[tuple[int, int]] = []
    for b, m in chosen:
        if (base_topic, b) in grads and (moving_topic, m) in grads:
            out.append((grads[(base_topic, b)], grads[(moving_topic, m)]))
            out_stamps.append((stamps[base_topic][b], stamps[moving_topic][m]))
    if not out:
        raise InputError(f"none of the {len(chosen)} paired images on {base_topic} / {moving_topic} could be decoded")
    return out, out_stamps


def calibrate_cameras(reader: LogReader, base_topic: str, moving_topic: str, config: Config) -> CameraCameraCalibration:
    """Affine map from ``moving_topic``'s image pixels to ``base_topic``'s (median over image pairs)."""
    start = time.perf_counter()
    pairs, stamps = collect_gradient_pairs(reader, base_topic, moving_topic, config)
    c = config.calibration
    results: list[AffineResult] = []
    for i, (base, moving) in enumerate(pairs):
        results.append(calibrate_affine(
            base.gx, base.gy, moving.gx, moving.gy, search_px=AFFINE_SEARCH_PX, search_deg=c.search_deg,
            keep_fraction=AFFINE_KEEP_FRACTION, n_particles=c.particles, max_iterations=c.iterations,
            seed=i,
        ))  # fmt: skip
        log.info("pair %d: params %s score %.4f (identity %.4f)", i, results[-1].params, results[-1].score,
                 results[-1].initial_score)  # fmt: skip
    params = np.median(np.stack([r.params for r in results]), axis=0)
    height, width = pairs[0][1].shape
    A = affine_matrices(params, ((width - 1) / 2.0, (height - 1) / 2.0))[0]
    return CameraCameraCalibration(
        base_topic, moving_topic, A, params,
        float(np.median([r.score for r in results])), float(np.median([r.initial_score for r in results])),
        len(results), time.perf_counter() - start, stamps, results,
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
    from fleetcal.workflows.cli import emit_json
    from fleetcal.workflows.common import open_logs, prepare_out_dir, table, write_config

    cameras = list(args.camera or [])
    if len(cameras) != 2:
        raise UsageError(f"calibrate-cameras needs exactly two --camera topics, got {len(cameras)}")
    if cameras[0] == cameras[1]:
        raise UsageError(f"calibrate-cameras needs two different cameras, got {cameras[0]} twice")
    out_dir = prepare_out_dir(args.out)
    with open_logs(args.logs, config, quiet=args.quiet) as reader:
        cal = calibrate_cameras(reader, cameras[0], cameras[1], config)
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
