"""Report PNGs: lidar points over camera images, score landscapes, the map seen from above."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.stages.sinks.atomic import atomic_path


def _write_png(image_bgr: NDArray[np.uint8], path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", image_bgr)
    if not ok:
        raise OSError(f"cannot encode {path.name}")
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(buf.tobytes())
    return path


def _to_bgr(image: NDArray[Any]) -> NDArray[np.uint8]:
    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img / max(int(img.max()), 1) * 255).astype(np.uint8)
    if img.ndim == 2:
        return np.asarray(cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_GRAY2BGR))
    return np.asarray(cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_RGB2BGR))


def overlay_image(
    image: NDArray[Any], camera: CameraModel, points_cam: NDArray[np.floating], max_points: int = 60_000
) -> NDArray[np.uint8]:
    """BGR image with optical-frame points drawn, coloured by their distance from the camera (near red, far
    blue; the distance, not z, so that a panorama's points behind the optical axis are coloured too)."""
    canvas = _to_bgr(image)
    uv, valid = camera.project(points_cam)
    uv, depth = uv[valid], np.linalg.norm(np.asarray(points_cam)[valid], axis=1)
    if uv.shape[0] > max_points:
        pick = np.random.default_rng(0).choice(uv.shape[0], max_points, replace=False)
        uv, depth = uv[pick], depth[pick]
    if uv.shape[0]:
        d = np.clip(np.log(np.maximum(depth, 0.5)) / np.log(80.0), 0, 1)
        colours = cv2.applyColorMap((d * 255).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_JET).reshape(-1, 3)
        px = np.round(uv).astype(np.int64)
        radius = max(1, round(canvas.shape[1] / 1000))
        for (u, v), c in zip(px, colours, strict=True):
            cv2.circle(canvas, (int(u), int(v)), radius, (int(c[0]), int(c[1]), int(c[2])), -1)
    return canvas


def write_overlay(image: NDArray[Any], camera: CameraModel, points_cam: NDArray[np.floating], path: Path) -> Path:
    return _write_png(overlay_image(image, camera, points_cam), path)


def jpeg_overlay(
    image: NDArray[Any], camera: CameraModel, points_cam: NDArray[np.floating], quality: int = 85
) -> bytes:
    """The overlay as JPEG bytes (for ``/fleetcal/overlay/<camera>`` CompressedImage messages)."""
    ok, buf = cv2.imencode(".jpg", overlay_image(image, camera, points_cam), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise OSError("cannot encode overlay JPEG")
    return bytes(buf.tobytes())


def _heatmap(values: NDArray[np.floating], cell: int = 12) -> NDArray[np.uint8]:
    v = np.asarray(values, dtype=np.float64)
    lo, hi = np.nanmin(v), np.nanmax(v)
    norm = np.zeros_like(v) if hi <= lo else (v - lo) / (hi - lo)
    img = cv2.applyColorMap((np.nan_to_num(norm) * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    img = cv2.resize(img, (v.shape[1] * cell, v.shape[0] * cell), interpolation=cv2.INTER_NEAREST)
    cy, cx = v.shape[0] // 2, v.shape[1] // 2
    cv2.drawMarker(img, (cx * cell + cell // 2, cy * cell + cell // 2), (0, 0, 255), cv2.MARKER_CROSS, cell, 2)
    return np.asarray(img)


def write_landscape(grids: Mapping[str, NDArray[np.floating]], path: Path) -> Path:
    """Side-by-side heatmaps of score grids (e.g. ``roll/pitch``, ``x/y``), optimum at the centre cross."""
    tiles = []
    for name, grid in grids.items():
        tile = _heatmap(grid)
        banner = np.full((24, tile.shape[1], 3), 255, np.uint8)
        cv2.putText(banner, name, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(np.vstack([banner, tile]))
    height = max(t.shape[0] for t in tiles)
    tiles = [np.vstack([t, np.full((height - t.shape[0], t.shape[1], 3), 255, np.uint8)]) for t in tiles]
    spacer = np.full((height, 8, 3), 255, np.uint8)
    row = tiles[0]
    for t in tiles[1:]:
        row = np.hstack([row, spacer, t])
    return _write_png(row, path)


def map_top_image(
    points_xyz: NDArray[np.floating],
    intensity: NDArray[np.floating] | None = None,
    trajectory_xyz: NDArray[np.floating] | None = None,
    size_px: int = 1000,
) -> NDArray[np.uint8]:
    """Bird's-eye view of a map (x right, y up), coloured by intensity or height, trajectory in red."""
    pts = np.asarray(points_xyz, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        return np.zeros((size_px, size_px, 3), np.uint8)
    xy = pts[:, :2]
    lo, hi = np.percentile(xy, 1.0, axis=0), np.percentile(xy, 99.0, axis=0)
    if trajectory_xyz is not None and len(trajectory_xyz):
        tr = np.asarray(trajectory_xyz)[:, :2]
        lo, hi = np.minimum(lo, tr.min(axis=0)), np.maximum(hi, tr.max(axis=0))
    extent = np.maximum(hi - lo, 1e-6)
    scale = (size_px - 20) / float(np.max(extent))
    width = int(np.clip(extent[0] * scale + 20, 200, size_px))
    height = int(np.clip(extent[1] * scale + 20, 200, size_px))
    canvas = np.zeros((height, width, 3), np.uint8)

    def to_px(p: NDArray[np.float64]) -> NDArray[np.int64]:
        u = (p[:, 0] - lo[0]) * scale + 10
        v = height - 10 - (p[:, 1] - lo[1]) * scale
        return np.stack([u, v], axis=1).round().astype(np.int64)

    px = to_px(xy)
    inside = (px[:, 0] >= 0) & (px[:, 0] < width) & (px[:, 1] >= 0) & (px[:, 1] < height)
    values = pts[:, 2] if intensity is None else np.asarray(intensity, dtype=np.float64)
    vlo, vhi = np.percentile(values, 2), np.percentile(values, 98)
    shade = np.clip((values - vlo) / max(vhi - vlo, 1e-9), 0, 1)
    colours = cv2.applyColorMap((shade * 255).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)
    canvas[px[inside, 1], px[inside, 0]] = colours[inside]
    if trajectory_xyz is not None and len(trajectory_xyz) > 1:
        tpx = to_px(np.asarray(trajectory_xyz, dtype=np.float64)[:, :2])
        cv2.polylines(canvas, [tpx.reshape(-1, 1, 2).astype(np.int32)], False, (0, 0, 255), 2)
    return canvas


def write_map_top(
    points_xyz: NDArray[np.floating],
    path: Path,
    intensity: NDArray[np.floating] | None = None,
    trajectory_xyz: NDArray[np.floating] | None = None,
) -> Path:
    return _write_png(map_top_image(points_xyz, intensity, trajectory_xyz), path)
