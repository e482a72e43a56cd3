"""Numba kernel: nearest ray-triangle hits through a uniform grid (3D DDA + Moller-Trumbore).

Kernels take contiguous arrays and scalars only; ``workflows.simulator.raycast`` validates inputs, builds
the grid and splits rays over threads (the kernels release the GIL). Compilation flags come from
``pipeline.numba_flags``. Frames: every array is in the scene (world) frame, metres.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from fleetcal.pipeline.numba_flags import NJIT_FLAGS, NJIT_PARALLEL_FLAGS

_EPS = 1e-12


@njit(**NJIT_PARALLEL_FLAGS, error_model="numpy")
def cast_rays_kernel(
    origins: np.ndarray,
    directions: np.ndarray,
    t_max: float,
    tri_data: np.ndarray,
    grid_min: np.ndarray,
    cell_m: float,
    dims: np.ndarray,
    cell_start: np.ndarray,
    cell_items: np.ndarray,
    out_t: np.ndarray,
    out_tri: np.ndarray,
) -> None:
    """Nearest hit of each ray (N rays, unit or non-unit directions) within ``t_max`` (ray parameter).

    Writes ``out_t[i]`` (ray parameter of the hit, ``inf`` for no hit) and ``out_tri[i]`` (triangle
    index, -1 for no hit). Triangle j is ``v0 + a e1 + b e2`` with ``tri_data[j] = (v0, e1, e2)`` (T, 9);
    ``cell_items[cell_start[c]:cell_start[c+1]]``
    lists the triangles overlapping grid cell ``c = (iz * ny + iy) * nx + ix``. A 4-entry mailbox skips
    triangles this ray already tested in an earlier cell (large ground triangles span many cells).
    """
    n = origins.shape[0]
    nx, ny, nz = dims[0], dims[1], dims[2]
    gmax0 = grid_min[0] + nx * cell_m
    gmax1 = grid_min[1] + ny * cell_m
    gmax2 = grid_min[2] + nz * cell_m
    for i in prange(n):
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        out_t[i] = np.inf
        out_tri[i] = -1
        t0 = 0.0
        t1 = t_max
        o = (ox, oy, oz)
        d = (dx, dy, dz)
        lo = (grid_min[0], grid_min[1], grid_min[2])
        hi = (gmax0, gmax1, gmax2)
        inside = True
        for a in range(3):
            if abs(d[a]) < _EPS:
                if o[a] < lo[a] or o[a] > hi[a]:
                    inside = False
            else:
                ta = (lo[a] - o[a]) / d[a]
                tb = (hi[a] - o[a]) / d[a]
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
        if not inside or t0 > t1:
            continue
        px = ox + t0 * dx
        py = oy + t0 * dy
        pz = oz + t0 * dz
        ix = min(max(int((px - grid_min[0]) / cell_m), 0), nx - 1)
        iy = min(max(int((py - grid_min[1]) / cell_m), 0), ny - 1)
        iz = min(max(int((pz - grid_min[2]) / cell_m), 0), nz - 1)
        sx = 1 if dx > 0 else -1
        sy = 1 if dy > 0 else -1
        sz = 1 if dz > 0 else -1
        inf = np.inf
        tmx = ((grid_min[0] + (ix + (sx > 0)) * cell_m) - ox) / dx if abs(dx) > _EPS else inf
        tmy = ((grid_min[1] + (iy + (sy > 0)) * cell_m) - oy) / dy if abs(dy) > _EPS else inf
        tmz = ((grid_min[2] + (iz + (sz > 0)) * cell_m) - oz) / dz if abs(dz) > _EPS else inf
        tdx = cell_m / abs(dx) if abs(dx) > _EPS else inf
        tdy = cell_m / abs(dy) if abs(dy) > _EPS else inf
        tdz = cell_m / abs(dz) if abs(dz) > _EPS else inf
        best_t = t1
        best_tri = -1
        mb0 = -1
        mb1 = -1
        mb2 = -1
        mb3 = -1
        while True:
            c = (iz * ny + iy) * nx + ix
            for k in range(cell_start[c], cell_start[c + 1]):
                j = cell_items[k]
                if j == mb0 or j == mb1 or j == mb2 or j == mb3:  # noqa: SIM109 (scalar compares in numba)
                    continue
                mb3 = mb2
                mb2 = mb1
                mb1 = mb0
                mb0 = j
                e1x, e1y, e1z = tri_data[j, 3], tri_data[j, 4], tri_data[j, 5]
                e2x, e2y, e2z = tri_data[j, 6], tri_data[j, 7], tri_data[j, 8]
                qx = dy * e2z - dz * e2y
                qy = dz * e2x - dx * e2z
                qz = dx * e2y - dy * e2x
                det = e1x * qx + e1y * qy + e1z * qz
                if abs(det) < _EPS:
                    continue
                inv = 1.0 / det
                sx_ = ox - tri_data[j, 0]
                sy_ = oy - tri_data[j, 1]
                sz_ = oz - tri_data[j, 2]
                u = (sx_ * qx + sy_ * qy + sz_ * qz) * inv
                if u < 0.0 or u > 1.0:
                    continue
                rx = sy_ * e1z - sz_ * e1y
                ry = sz_ * e1x - sx_ * e1z
                rz = sx_ * e1y - sy_ * e1x
                v = (dx * rx + dy * ry + dz * rz) * inv
                if v < 0.0 or u + v > 1.0:
                    continue
                t = (e2x * rx + e2y * ry + e2z * rz) * inv
                if t > 1e-6 and t < best_t:
                    best_t = t
                    best_tri = j
            t_next = min(tmx, min(tmy, tmz))
            if best_tri >= 0 and best_t <= t_next:
                break
            if t_next > t1:
                break
            if tmx <= tmy and tmx <= tmz:
                ix += sx
                if ix < 0 or ix >= nx:
                    break
                tmx += tdx
            elif tmy <= tmz:
                iy += sy
                if iy < 0 or iy >= ny:
                    break
                tmy += tdy
            else:
                iz += sz
                if iz < 0 or iz >= nz:
                    break
                tmz += tdz
        if best_tri >= 0:
            out_t[i] = best_t
            out_tri[i] = best_tri


SOLID, CHECKER, STRIPES, PATCHES, BRICKS = 0, 1, 2, 3, 4


@njit(**NJIT_FLAGS, inline="always")
def _hash01(a: int, b: int, seed: int) -> float:
    """Deterministic hash of an integer cell (a, b) and a seed, in [0, 1)."""
    h = (np.uint64(a) * np.uint64(0x9E3779B1)) ^ (np.uint64(b) * np.uint64(0x85EBCA77))
    h ^= np.uint64(seed) * np.uint64(0xC2B2AE3D)
    h ^= h >> np.uint64(15)
    h *= np.uint64(0x2C1B3C6D)
    h ^= h >> np.uint64(12)
    h *= np.uint64(0x297A2D39)
    h ^= h >> np.uint64(15)
    return float(h & np.uint64(0xFFFFFF)) / 16777216.0


@njit(**NJIT_FLAGS, inline="always")
def _surface_at(
    px: float,
    py: float,
    pz: float,
    j: int,
    tex_origin: np.ndarray,
    tex_u: np.ndarray,
    tex_v: np.ndarray,
    tex_scale: np.ndarray,
    tex_kind: np.ndarray,
    tex_seed: np.ndarray,
    mat_a: np.ndarray,
    mat_b: np.ndarray,
    mat_albedo: np.ndarray,
    mat_reflectivity: np.ndarray,
) -> tuple[float, float, float, float]:
    """(albedo r, g, b, reflectivity) of point p on triangle j; see ``surface_kernel``."""
    rx = px - tex_origin[j, 0]
    ry = py - tex_origin[j, 1]
    rz = pz - tex_origin[j, 2]
    s = tex_scale[j]
    u = (rx * tex_u[j, 0] + ry * tex_u[j, 1] + rz * tex_u[j, 2]) / s
    v = (rx * tex_v[j, 0] + ry * tex_v[j, 1] + rz * tex_v[j, 2]) / s
    fu = np.int64(np.floor(u))
    fv = np.int64(np.floor(v))
    kind = tex_kind[j]
    mix = 0.0
    gain_a = 1.0
    gain_r = 1.0
    if kind == CHECKER:
        mix = float((fu + fv) % 2)
    elif kind == STRIPES:
        mix = float(fu % 2)
    elif kind == PATCHES:
        coarse = _hash01(fu, fv, tex_seed[j])
        fine = _hash01(np.int64(np.floor(u * 4)), np.int64(np.floor(v * 4)), tex_seed[j] + 1)
        mix = np.rint((0.75 * coarse + 0.25 * (1.0 if fine > 0.7 else 0.0)) * 3) / 3
    elif kind == BRICKS:
        uu = u / 2 + 0.5 * (fv % 2)
        col = np.int64(np.floor(uu))
        mix = 1.0 if ((v - fv) < 0.14 or (uu - col) < 0.05) else 0.0
        gain_a = 0.8 + 0.4 * _hash01(col, fv, tex_seed[j])
        gain_r = 0.85 + 0.3 * _hash01(col, fv, tex_seed[j] + 7)
    mix = min(max(mix, 0.0), 1.0)
    a = mat_a[j]
    b = mat_b[j]
    red = min(max((mat_albedo[a, 0] * (1 - mix) + mat_albedo[b, 0] * mix) * gain_a, 0.0), 1.0)
    green = min(max((mat_albedo[a, 1] * (1 - mix) + mat_albedo[b, 1] * mix) * gain_a, 0.0), 1.0)
    blue = min(max((mat_albedo[a, 2] * (1 - mix) + mat_albedo[b, 2] * mix) * gain_a, 0.0), 1.0)
    refl = min(max((mat_reflectivity[a] * (1 - mix) + mat_reflectivity[b] * mix) * gain_r, 0.0), 1.0)
    return red, green, blue, refl


@njit(**NJIT_PARALLEL_FLAGS, error_model="numpy")
def surface_kernel(
    points: np.ndarray,
    tri: np.ndarray,
    tex_origin: np.ndarray,
    tex_u: np.ndarray,
    tex_v: np.ndarray,
    tex_scale: np.ndarray,
    tex_kind: np.ndarray,
    tex_seed: np.ndarray,
    mat_a: np.ndarray,
    mat_b: np.ndarray,
    mat_albedo: np.ndarray,
    mat_reflectivity: np.ndarray,
    out_albedo: np.ndarray,
    out_reflectivity: np.ndarray,
) -> None:
    """Albedo (N, 3) and reflectivity (N,) at points (N, 3, world frame) lying on triangles ``tri``.

    The texture of triangle j mixes materials ``mat_a[j]`` and ``mat_b[j]`` by a function of the surface
    coordinates ``(u, v) = ((p - tex_origin) . tex_u, (p - tex_origin) . tex_v) / tex_scale``: SOLID (a only),
    CHECKER, STRIPES (along u), PATCHES (hashed cells at two scales, 4 levels), BRICKS (offset rows of
    2:1 bricks with mortar lines; per-brick albedo and reflectivity gains drawn independently).
    """
    for i in prange(points.shape[0]):
        r, g, b, refl = _surface_at(
            points[i, 0],
            points[i, 1],
            points[i, 2],
            tri[i],
            tex_origin,
            tex_u,
            tex_v,
            tex_scale,
            tex_kind,
            tex_seed,
            mat_a,
            mat_b,
            mat_albedo,
            mat_reflectivity,
        )
        out_albedo[i, 0] = r
        out_albedo[i, 1] = g
        out_albedo[i, 2] = b
        out_reflectivity[i] = refl


@njit(**NJIT_PARALLEL_FLAGS, error_model="numpy")
def shade_kernel(
    origins: np.ndarray,
    directions: np.ndarray,
    ray_ok: np.ndarray,
    t_hit: np.ndarray,
    tri: np.ndarray,
    normals: np.ndarray,
    tex_origin: np.ndarray,
    tex_u: np.ndarray,
    tex_v: np.ndarray,
    tex_scale: np.ndarray,
    tex_kind: np.ndarray,
    tex_seed: np.ndarray,
    mat_a: np.ndarray,
    mat_b: np.ndarray,
    mat_albedo: np.ndarray,
    mat_reflectivity: np.ndarray,
    sun_dir: np.ndarray,
    sky_rgb: np.ndarray,
    spectral_mix: float,
    gain: float,
    gamma: float,
    out_rgb: np.ndarray,
) -> None:
    """8-bit-scale (0..255, float32) sRGB-like colour of each camera ray (N rays, ray i from ``origins[i]``:
    one camera position for a global shutter, one per image row for a rolling shutter).

    Hit: gain x ((1 - spectral_mix) albedo + spectral_mix reflectivity) x (0.45 + 0.55 max(0, n . sun)).
    Miss: a sky gradient by ray elevation. Rays with ``ray_ok`` False (outside a fisheye's circle) are
    black. Then ``255 * clip(linear, 0, 1) ** (1 / gamma)``.
    """
    for i in prange(directions.shape[0]):
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        lr = 0.0
        lg = 0.0
        lb = 0.0
        if ray_ok[i]:
            j = tri[i]
            if j < 0:
                k = 0.75 + 0.35 * min(max(dz, -1.0), 1.0)
                lr, lg, lb = sky_rgb[0] * k, sky_rgb[1] * k, sky_rgb[2] * k
            else:
                t = t_hit[i]
                r, g, b, refl = _surface_at(
                    origins[i, 0] + t * dx,
                    origins[i, 1] + t * dy,
                    origins[i, 2] + t * dz,
                    j,
                    tex_origin,
                    tex_u,
                    tex_v,
                    tex_scale,
                    tex_kind,
                    tex_seed,
                    mat_a,
                    mat_b,
                    mat_albedo,
                    mat_reflectivity,
                )
                nx, ny, nz = normals[j, 0], normals[j, 1], normals[j, 2]
                if nx * dx + ny * dy + nz * dz > 0:
                    nx, ny, nz = -nx, -ny, -nz
                shade = 0.45 + 0.55 * max(nx * sun_dir[0] + ny * sun_dir[1] + nz * sun_dir[2], 0.0)
                m = spectral_mix
                lr = ((1 - m) * r + m * refl) * shade
                lg = ((1 - m) * g + m * refl) * shade
                lb = ((1 - m) * b + m * refl) * shade
        out_rgb[i, 0] = 255.0 * min(max(lr * gain, 0.0), 1.0) ** (1.0 / gamma)
        out_rgb[i, 1] = 255.0 * min(max(lg * gain, 0.0), 1.0) ** (1.0 / gamma)
        out_rgb[i, 2] = 255.0 * min(max(lb * gain, 0.0), 1.0) ** (1.0 / gamma)
