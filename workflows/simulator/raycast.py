"""Uniform-grid acceleration structure over scene triangles and the public ray-casting wrapper."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline import numba_flags
from fleetcal.pipeline.errors import ProcessingError
from fleetcal.workflows.simulator.raycast_kernels import cast_rays_kernel

MAX_CELLS = 4_000_000
_CHUNK_RAYS = 32_768


def default_threads() -> int:
    """Threads for the ray kernels: one per core, or 1 when numba itself runs kernels in parallel."""
    return 1 if numba_flags.PARALLEL else max(1, os.cpu_count() or 1)


@cache
def _pool(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=threads, thread_name_prefix="fleetcal-raycast")


def run_chunked(n: int, work: Callable[[int, int], None], threads: int | None = None) -> None:
    """Call ``work(start, stop)`` over consecutive chunks of ``range(n)`` on a thread pool.

    ``work`` must call a ``nogil`` kernel writing disjoint output slices; results do not depend on the
    thread count.
    """
    threads = default_threads() if threads is None else max(1, int(threads))
    chunks = [(a, min(a + _CHUNK_RAYS, n)) for a in range(0, n, _CHUNK_RAYS)]
    if threads == 1 or len(chunks) <= 1:
        for a, b in chunks:
            work(a, b)
        return
    for future in [_pool(threads).submit(work, a, b) for a, b in chunks]:
        future.result()


@dataclass(frozen=True)
class TriangleGrid:
    """Triangles ``v0 + a e1 + b e2`` (world frame, m; ``tri_data`` rows (v0, e1, e2), (T, 9)) bucketed into
    cubic cells of ``cell_m`` metres.

    ``cell_items[cell_start[c]:cell_start[c + 1]]`` holds the triangles whose bounding box overlaps
    cell ``c = (iz * ny + iy) * nx + ix``.
    """

    tri_data: NDArray[np.float64]
    grid_min: NDArray[np.float64]
    cell_m: float
    dims: NDArray[np.int64]
    cell_start: NDArray[np.int64]
    cell_items: NDArray[np.int32]


def build_grid(triangles: NDArray[np.float64], cell_m: float = 1.0) -> TriangleGrid:
    """Grid over (T, 3, 3) triangles (vertices in rows, world frame, m); cells grow if too many."""
    tris = np.ascontiguousarray(triangles, dtype=np.float64)
    if tris.ndim != 3 or tris.shape[1:] != (3, 3) or tris.shape[0] == 0:
        raise ProcessingError(f"expected (T, 3, 3) triangles, got shape {tris.shape}")
    if not np.all(np.isfinite(tris)):
        raise ProcessingError("scene triangles contain NaN or infinite coordinates")
    lo = tris.min(axis=1)
    hi = tris.max(axis=1)
    grid_min = lo.min(axis=0) - 1e-3
    extent = hi.max(axis=0) + 1e-3 - grid_min
    cell = float(cell_m)
    while np.prod(np.ceil(extent / cell)) > MAX_CELLS:
        cell *= 1.25
    dims = np.maximum(np.ceil(extent / cell).astype(np.int64), 1)
    pad = 1e-6
    cmin = np.clip(np.floor((lo - pad - grid_min) / cell).astype(np.int64), 0, dims - 1)
    cmax = np.clip(np.floor((hi + pad - grid_min) / cell).astype(np.int64), 0, dims - 1)
    span = cmax - cmin + 1
    counts = span.prod(axis=1)
    tri_ids = np.repeat(np.arange(tris.shape[0], dtype=np.int64), counts)
    first = np.cumsum(counts) - counts
    local = np.arange(tri_ids.size, dtype=np.int64) - first[tri_ids]
    sx, sy = span[tri_ids, 0], span[tri_ids, 1]
    ix = cmin[tri_ids, 0] + local % sx
    iy = cmin[tri_ids, 1] + (local // sx) % sy
    iz = cmin[tri_ids, 2] + local // (sx * sy)
    cells = (iz * dims[1] + iy) * dims[0] + ix
    order = np.argsort(cells, kind="stable")
    n_cells = int(dims.prod())
    cell_start = np.zeros(n_cells + 1, dtype=np.int64)
    cell_start[1:] = np.cumsum(np.bincount(cells, minlength=n_cells))
    return TriangleGrid(
        tri_data=np.ascontiguousarray(np.hstack([tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]])),
        grid_min=grid_min,
        cell_m=cell,
        dims=dims,
        cell_start=cell_start,
        cell_items=tri_ids[order].astype(np.int32),
    )


def cast_rays(
    grid: TriangleGrid,
    origins: NDArray[np.floating],
    directions: NDArray[np.floating],
    t_max: float = 1e4,
    threads: int | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
    """Nearest hits of rays (N, 3) origins and directions, world frame.

    Returns (t (N,), triangle (N,)): hit point = origin + t * direction; ``t = inf`` and triangle -1
    where the ray hits nothing within ``t_max``. ``threads``: see ``run_chunked`` (None: one per core).
    """
    o = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    if o.shape != d.shape:
        raise ProcessingError(f"ray origins {o.shape} and directions {d.shape} differ in shape")
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
        raise ProcessingError("rays contain NaN or infinite values")
    if not (np.isfinite(t_max) and t_max > 0):
        raise ProcessingError(f"t_max must be a positive number, got {t_max}")
    out_t = np.empty(o.shape[0], dtype=np.float64)
    out_tri = np.empty(o.shape[0], dtype=np.int32)

    def work(a: int, b: int) -> None:
        cast_rays_kernel(
            o[a:b],
            d[a:b],
            float(t_max),
            grid.tri_data,
            grid.grid_min,
            grid.cell_m,
            grid.dims,
            grid.cell_start,
            grid.cell_items,
            out_t[a:b],
            out_tri[a:b],
        )

    run_chunked(o.shape[0], work, threads)
    return out_t, out_tri
