"""Colour for lidar points from calibrated cameras: project each point into the paired images and sample.

Frames: points are in the lidar frame; each view carries ``T_camera_lidar`` (p_camera = T @ p_lidar,
camera = optical frame, x right, y down, z forward). A point takes its colour from the view in which it
projects closest to the principal point (least distortion and vignetting) among the views that see it
unoccluded; points that no view sees get ``seen = False``.

Occlusion: lidar and camera sit apart, so a lidar point hidden from the camera by a nearer surface would
otherwise take that surface's colour. A coarse z-buffer (cells of ``occlusion_cell_px`` pixels holding
the nearest lidar depth) rejects points farther than ``(1 + occlusion_rel_tol) * nearest +
occlusion_abs_tol_m`` in their cell.

Unseen points in MC-GICP (``color`` / ``combined`` channels): ``fill_unseen`` gives them the mean colour
of the seen points of the scan. A region with no camera coverage then has a constant colour, so its
MC-GICP descriptor weights (eq. 7) are uniform there and its covariances fall back to the geometric
ones; in the (3 + n)-D correspondence search it is one point of colour space, so it adds no colour
gradient (it can only be matched to differently coloured seen points at a colour cost).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import apply, is_rigid

CameraView = tuple[NDArray[np.generic], CameraModel, NDArray[np.float64]]
"""(image (H, W, 3) RGB or (H, W) grey, camera model, T_camera_lidar (4, 4))."""


def _sample_bilinear(image: NDArray[np.generic], uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 3) colours at sub-pixel positions ``uv`` (pixel centres at integers), bilinear, edge-clamped."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim == 2:
        img = img[:, :, None]
    coords = np.stack([uv[:, 1], uv[:, 0]])  # (row, col)
    out = np.stack(
        [map_coordinates(img[:, :, c], coords, order=1, mode="nearest") for c in range(img.shape[2])], axis=1
    )
    return np.repeat(out, 3, axis=1) if out.shape[1] == 1 else out


def unoccluded(
    uv: NDArray[np.float64],
    depth: NDArray[np.float64],
    shape: tuple[int, int],
    cell_px: int,
    rel_tol: float,
    abs_tol_m: float,
) -> NDArray[np.bool_]:
    """Coarse z-buffer: True where the point is within the tolerance of the nearest depth in its cell.

    ``uv`` (M, 2) pixel positions of points that project into an image of ``shape`` (H, W), ``depth``
    (M,) their camera z, metres; kept when ``depth <= (1 + rel_tol) * nearest + abs_tol_m``.
    """
    rows = (np.clip(np.rint(uv[:, 1]), 0, shape[0] - 1) // cell_px).astype(np.int64)
    cols = (np.clip(np.rint(uv[:, 0]), 0, shape[1] - 1) // cell_px).astype(np.int64)
    n_cols = (shape[1] + cell_px - 1) // cell_px
    cell = rows * n_cols + cols
    nearest = np.full(int(cell.max(initial=0)) + 1, np.inf)
    np.minimum.at(nearest, cell, depth)
    return np.asarray(depth <= nearest[cell] * (1.0 + rel_tol) + abs_tol_m)


def colorize(
    points_xyz: NDArray[np.floating],
    images: Sequence[CameraView],
    *,
    occlusion: bool = True,
    occlusion_cell_px: int = 4,
    occlusion_rel_tol: float = 0.1,
    occlusion_abs_tol_m: float = 0.1,
    points_per_view: Sequence[NDArray[np.floating] | None] | None = None,
) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
    """Colour (N, 3) lidar-frame points (metres) from calibrated camera images.

    Args:
        points_xyz: (N, 3) points in the lidar frame, m; non-finite points are never seen.
        images: views ``(image, CameraModel, T_camera_lidar)``; image (H, W, 3) RGB or (H, W) grey, uint8
            (values are sampled as they are and rounded into 0..255).
        occlusion: reject points hidden behind nearer lidar points in a coarse z-buffer.
        points_per_view: optional, per view, the same N points in the lidar frame at that image's stamp
            (a moving rig: ``workflows.ego_motion.points_at``); None (or a None entry): ``points_xyz``.

    Returns:
        (rgb (N, 3) uint8, seen (N,) bool); rgb is 0 where not seen.

    Raises:
        InputError: malformed points, image or extrinsics, or an image whose size differs from its model.
    """
    pts = np.asarray(points_xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points_xyz must be (N, 3), got {pts.shape}")
    n = pts.shape[0]
    finite = np.all(np.isfinite(pts), axis=1)
    best_score = np.full(n, np.inf)
    rgb = np.zeros((n, 3))
    if points_per_view is not None and len(points_per_view) != len(images):
        raise InputError(f"points_per_view has {len(points_per_view)} entries for {len(images)} views")
    for index, (image, model, T_camera_lidar) in enumerate(images):
        view_pts = pts
        if points_per_view is not None and points_per_view[index] is not None:
            view_pts = np.asarray(points_per_view[index], dtype=np.float64)
            if view_pts.shape != pts.shape:
                raise InputError(f"view {index}: points_per_view is {view_pts.shape}, expected {pts.shape}")
        img = np.asarray(image)
        if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
            raise InputError(f"view {index}: image must be (H, W) or (H, W, 3), got {img.shape}")
        if img.shape[:2] != (model.height, model.width):
            raise InputError(
                f"view {index}: image is {img.shape[1]}x{img.shape[0]} but its camera model is "
                f"{model.width}x{model.height}"
            )
        T = np.asarray(T_camera_lidar, dtype=np.float64)
        if not is_rigid(T):
            raise InputError(f"view {index}: T_camera_lidar is not a finite 4x4 rigid transform")
        idx = np.flatnonzero(finite & np.all(np.isfinite(view_pts), axis=1))
        p_cam = apply(T, view_pts[idx])
        uv, valid = model.project(p_cam)
        idx, uv, p_cam = idx[valid], uv[valid], p_cam[valid]
        if idx.size == 0:
            continue
        if occlusion:
            keep = unoccluded(
                uv, p_cam[:, 2], img.shape[:2], occlusion_cell_px, occlusion_rel_tol, occlusion_abs_tol_m
            )
            idx, uv = idx[keep], uv[keep]
        score = np.hypot((uv[:, 0] - model.cx) / model.fx, (uv[:, 1] - model.cy) / model.fy)
        better = score < best_score[idx]
        idx, uv = idx[better], uv[better]
        best_score[idx] = score[better]
        rgb[idx] = _sample_bilinear(img, uv)
    seen = np.isfinite(best_score)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), seen


def fill_unseen(rgb: NDArray[np.uint8], seen: NDArray[np.bool_]) -> NDArray[np.uint8]:
    """Copy of ``rgb`` with unseen points set to the mean colour of the seen ones (grey 128 if none).

    This is how MC-GICP ``color`` / ``combined`` treats points no camera saw (see the module docstring).
    """
    out = np.array(rgb, dtype=np.uint8, copy=True)
    mask = np.asarray(seen, dtype=bool)
    if out.shape != (mask.shape[0], 3):
        raise InputError(f"rgb must be ({mask.shape[0]}, 3), got {out.shape}")
    mean = out[mask].mean(axis=0) if np.any(mask) else np.full(3, 128.0)
    out[~mask] = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    return out


def colorize_frame(frame: LidarFrame, images: Sequence[CameraView], **kwargs: object) -> LidarFrame:
    """The frame with ``r``, ``g``, ``b`` (uint8, unseen filled by ``fill_unseen``) and ``seen`` (uint8 0/1)
    channels from ``colorize``; the other fields are shared with ``frame``."""
    rgb, seen = colorize(frame.points_xyz, images, **kwargs)  # type: ignore[arg-type]
    rgb = fill_unseen(rgb, seen)
    channels = dict(frame.channels)
    channels.update({"r": rgb[:, 0], "g": rgb[:, 1], "b": rgb[:, 2], "seen": seen.astype(np.uint8)})
    return LidarFrame(
        stamp_ns=frame.stamp_ns,
        topic=frame.topic,
        frame_id=frame.frame_id,
        points_xyz=frame.points_xyz,
        channels=channels,
        organized_shape=frame.organized_shape,
        organized_index=frame.organized_index,
        dropped_points=frame.dropped_points,
        log_time_ns=frame.log_time_ns,
    )
