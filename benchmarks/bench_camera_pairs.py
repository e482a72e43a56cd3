"""``fleetcal calibrate-cameras`` against the number of image pairs: one objective summed over the pairs (what the
command does) beside one swarm per pair and the median of their parameters, in the same run.

The rig is ``tests/test_calibrate_cameras.py``'s: two 320x240 cameras, the moving one's image the base image
warped by a known affine with its contrast inverted, written with 40 frames; ``--noise`` adds Gaussian noise of
that many grey levels to the moving images. Each row: pairs, method, wall seconds (the search, the images'
gradients already computed), and the error as the largest move of an image corner between the estimated and the
true map, pixels.

    .venv/bin/python benchmarks/bench_camera_pairs.py [--pairs 3 10 40] [--noise 0 60] [--per-pair-up-to 10]

The default takes about 5 minutes on 2 cores (most of it the per-pair method at 10 pairs).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tests.test_calibrate_cameras as rig
from fleetcal.pipeline.config import Config, load_config
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration.affine import affine_matrices, calibrate_affine_pairs
from fleetcal.workflows.calibrate_cameras import (
    AFFINE_KEEP_FRACTION,
    AFFINE_SEARCH_PX,
    collect_gradient_pairs,
)

FRAMES = 40
"""Frames of the written rig log."""
PLAIN_WARP = rig.warp_to_moving


def noisy_warp(sigma: float) -> Any:
    """``rig.warp_to_moving`` with Gaussian noise of ``sigma`` grey levels (seeded by the image)."""
    def warped(base: NDArray[np.uint8], A: NDArray[np.float64]) -> NDArray[np.uint8]:
        moving = PLAIN_WARP(base, A).astype(np.float32)
        rng = np.random.default_rng(int(base.sum()) % 1000)
        return np.asarray(np.clip(moving + rng.normal(0.0, sigma, moving.shape), 0, 255), dtype=np.uint8)

    return warped


def corner_error_px(params: NDArray[np.float64]) -> float:
    """Largest distance between where the estimated and the true map send the image's corners, pixels."""
    A = affine_matrices(params, rig.CENTRE)[0]
    A_true = affine_matrices(rig.TRUE_PARAMS, rig.CENTRE)[0]
    corners = np.array([[0.0, 0.0], [rig.WIDTH - 1, 0.0], [0.0, rig.HEIGHT - 1], [rig.WIDTH - 1, rig.HEIGHT - 1]])
    moved = corners @ (A[:, :2] - A_true[:, :2]).T + (A[:, 2] - A_true[:, 2])
    return float(np.max(np.linalg.norm(moved, axis=1)))


def solve(pairs: list[Any], config: Config, per_pair: bool) -> NDArray[np.float64]:
    """The map's parameters: one objective over ``pairs``, or the median of one solve per pair."""
    c = config.calibration
    settings: dict[str, Any] = {"search_px": AFFINE_SEARCH_PX, "search_deg": c.search_deg,
                                "keep_fraction": AFFINE_KEEP_FRACTION, "n_particles": c.particles,
                                "max_iterations": c.iterations}
    gradients = [(b.gxy, m.gx, m.gy) for b, m in pairs]
    if not per_pair:
        return calibrate_affine_pairs(gradients, **settings).params
    return np.asarray(np.median([calibrate_affine_pairs([g], seed=i, **settings).params
                                 for i, g in enumerate(gradients)], axis=0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, nargs="+", default=[3, 10, 40])
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 60.0])
    parser.add_argument("--per-pair-up-to", type=int, default=10,
                        help="run the per-pair method only up to this many pairs (it costs a swarm per pair)")
    args = parser.parse_args()
    config = load_config(env={})
    print(f"{'noise':>5} {'pairs':>5} {'method':<14} {'seconds':>8} {'corner error px':>16}")
    with tempfile.TemporaryDirectory() as tmp:
        for sigma in args.noise:
            rig.warp_to_moving = noisy_warp(sigma) if sigma > 0 else PLAIN_WARP
            log = Path(tmp) / f"rig_{sigma:g}.mcap"
            rig.write_rig_log(log, FRAMES, 3_000_000)
            for n in args.pairs:
                config.calibration.frames = n
                with open_log(log) as reader:
                    pairs, _ = collect_gradient_pairs(reader, "/cam_a/image_raw", "/cam_b/image_raw", config)
                for per_pair in (False, True):
                    if per_pair and n > args.per_pair_up_to:
                        continue
                    start = time.perf_counter()
                    params = solve(pairs, config, per_pair)
                    label = "per-pair median" if per_pair else "one objective"
                    print(f"{sigma:5g} {len(pairs):5d} {label:<14} {time.perf_counter() - start:8.1f} "
                          f"{corner_error_px(params):16.3f}", flush=True)


if __name__ == "__main__":
    main()
