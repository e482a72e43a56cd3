"""Procedural, seeded scenes of textured triangles with lidar reflectivity and visible albedo.

Every triangle carries two materials (A, B) and a texture function that mixes them by position on the
surface, so reflectivity/albedo edges exist at several scales (tiles, bricks, markings, posters,
patches). Reflectivity (lidar, near infrared) and albedo (visible RGB) are correlated but not equal,
and some materials invert between the two (foliage, mortar, asphalt repairs, some paints), like the
418 nm vs 950 nm example of the GOM paper.

World frame: x east, y north, z up, metres, ground at z = 0.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, ProcessingError
from fleetcal.workflows.simulator.raycast_kernels import BRICKS, CHECKER, PATCHES, SOLID, STRIPES, surface_kernel

SceneName = Literal["street", "corridor", "open"]
SCENES: tuple[str, ...] = ("street", "corridor", "open")

# name: (albedo r g b in [0, 1], lidar reflectivity in [0, 1])
MATERIALS: dict[str, tuple[tuple[float, float, float], float]] = {
    "asphalt": ((0.13, 0.13, 0.14), 0.10),
    "asphalt_light": ((0.24, 0.23, 0.22), 0.07),
    "asphalt_dark": ((0.06, 0.06, 0.07), 0.18),
    "paint_white": ((0.88, 0.88, 0.85), 0.80),
    "paint_yellow": ((0.85, 0.68, 0.12), 0.55),
    "concrete": ((0.58, 0.56, 0.52), 0.36),
    "concrete_dark": ((0.36, 0.34, 0.33), 0.42),
    "kerb": ((0.72, 0.72, 0.70), 0.48),
    "plaster": ((0.80, 0.76, 0.66), 0.58),
    "plaster_blue": ((0.35, 0.45, 0.62), 0.62),
    "brick": ((0.56, 0.24, 0.17), 0.42),
    "mortar": ((0.78, 0.75, 0.68), 0.28),
    "glass": ((0.07, 0.09, 0.12), 0.04),
    "frame_white": ((0.90, 0.90, 0.90), 0.62),
    "wood": ((0.36, 0.21, 0.10), 0.46),
    "metal": ((0.50, 0.50, 0.53), 0.34),
    "sign_white": ((0.92, 0.92, 0.92), 0.95),
    "sign_red": ((0.75, 0.08, 0.08), 0.85),
    "sign_blue": ((0.10, 0.22, 0.70), 0.78),
    "bark": ((0.25, 0.18, 0.12), 0.30),
    "foliage": ((0.08, 0.20, 0.06), 0.62),
    "foliage_dark": ((0.04, 0.11, 0.03), 0.48),
    "grass": ((0.16, 0.36, 0.10), 0.56),
    "gravel": ((0.46, 0.44, 0.40), 0.24),
    "dirt": ((0.36, 0.27, 0.19), 0.38),
    "car_red": ((0.62, 0.05, 0.05), 0.34),
    "car_white": ((0.86, 0.86, 0.86), 0.60),
    "car_black": ((0.04, 0.04, 0.04), 0.30),
    "car_blue": ((0.05, 0.10, 0.45), 0.28),
    "car_silver": ((0.60, 0.60, 0.62), 0.50),
    "tyre": ((0.03, 0.03, 0.03), 0.05),
    "wall": ((0.76, 0.75, 0.72), 0.50),
    "floor": ((0.46, 0.42, 0.37), 0.30),
    "floor_dark": ((0.30, 0.28, 0.26), 0.36),
    "ceiling": ((0.86, 0.86, 0.84), 0.60),
    "poster_yellow": ((0.92, 0.80, 0.18), 0.30),
    "poster_navy": ((0.08, 0.10, 0.40), 0.62),
    "poster_red": ((0.80, 0.12, 0.10), 0.70),
    "poster_black": ((0.05, 0.05, 0.05), 0.40),
    "poster_white": ((0.93, 0.93, 0.90), 0.20),
    "poster_retro": ((0.95, 0.95, 0.92), 0.95),
    "poster_matte": ((0.03, 0.03, 0.04), 0.04),
    "poster_ir_dark": ((0.85, 0.80, 0.70), 0.08),
    "poster_ir_bright": ((0.10, 0.14, 0.10), 0.85),
    "tile_white": ((0.80, 0.78, 0.72), 0.72),
    "tile_black": ((0.08, 0.08, 0.09), 0.07),
    "ceiling_lamp": ((0.98, 0.98, 0.95), 0.08),
}
MATERIAL_NAMES: tuple[str, ...] = tuple(MATERIALS)
_MAT_INDEX = {name: i for i, name in enumerate(MATERIAL_NAMES)}
MATERIAL_ALBEDO = np.array([MATERIALS[m][0] for m in MATERIAL_NAMES], dtype=np.float64)
MATERIAL_REFLECTIVITY = np.array([MATERIALS[m][1] for m in MATERIAL_NAMES], dtype=np.float64)


@dataclass(frozen=True)
class RouteSpec:
    """A counter-clockwise rounded-rectangle loop (world frame): half sizes and corner radius, m."""

    half_x_m: float
    half_y_m: float
    corner_radius_m: float


@dataclass
class Scene:
    """Triangles (T, 3, 3) with per-triangle texture parameters; see ``surface_properties``.

    Attributes:
        name, seed: what built it.
        triangles: (T, 3, 3) vertices, world frame, m.
        normals: (T, 3) unit normals.
        mat_a, mat_b: (T,) material indices into ``MATERIAL_NAMES``.
        tex_kind: (T,) SOLID | CHECKER | STRIPES | PATCHES | BRICKS.
        tex_scale_m: (T,) texture period, m.
        tex_origin, tex_u, tex_v: (T, 3) texture origin and unit axes in the surface plane.
        tex_seed: (T,) per-surface hash seed.
        route: the loop the vehicle drives.
        lidar_height_m: lidar mounting height above the ground for this scene.
    """

    name: str
    seed: int
    triangles: NDArray[np.float64]
    normals: NDArray[np.float64]
    mat_a: NDArray[np.int64]
    mat_b: NDArray[np.int64]
    tex_kind: NDArray[np.int64]
    tex_scale_m: NDArray[np.float64]
    tex_origin: NDArray[np.float64]
    tex_u: NDArray[np.float64]
    tex_v: NDArray[np.float64]
    tex_seed: NDArray[np.int64]
    route: RouteSpec
    lidar_height_m: float = 1.9

    @property
    def n_triangles(self) -> int:
        return int(self.triangles.shape[0])


@dataclass
class SceneBuilder:
    """Accumulates textured quads and boxes (world frame, m); ``build`` freezes them into a ``Scene``."""

    rng: np.random.Generator
    tris: list[NDArray[np.float64]] = field(default_factory=list)
    attrs: list[tuple[int, int, int, float, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], int]] = (
        field(default_factory=list)
    )

    def quad(
        self,
        corner: NDArray[np.float64] | list[float],
        edge_u: NDArray[np.float64] | list[float],
        edge_v: NDArray[np.float64] | list[float],
        mat_a: str,
        mat_b: str | None = None,
        kind: int = SOLID,
        scale_m: float = 1.0,
    ) -> None:
        """Parallelogram ``corner + a edge_u + b edge_v`` (a, b in [0, 1]); texture axes along the edges."""
        c = np.asarray(corner, dtype=np.float64)
        eu = np.asarray(edge_u, dtype=np.float64)
        ev = np.asarray(edge_v, dtype=np.float64)
        u = eu / np.linalg.norm(eu)
        v = ev - u * (ev @ u)
        v = v / np.linalg.norm(v)
        seed = int(self.rng.integers(0, 2**31 - 1))
        entry = (_MAT_INDEX[mat_a], _MAT_INDEX[mat_b or mat_a], kind, scale_m, c, u, v, seed)
        self.tris.append(np.stack([c, c + eu, c + eu + ev]))
        self.tris.append(np.stack([c, c + eu + ev, c + ev]))
        self.attrs.extend([entry, entry])

    def box(
        self,
        center: list[float] | NDArray[np.float64],
        size: list[float] | NDArray[np.float64],
        yaw_rad: float,
        mat_a: str,
        mat_b: str | None = None,
        kind: int = SOLID,
        scale_m: float = 1.0,
        top: str | None = None,
        bottom: bool = False,
    ) -> None:
        """Box with centre (x, y, z), size (length along yaw, width, height); optional top material."""
        cx, cy, cz = center
        lx, ly, lz = size
        c, s = np.cos(yaw_rad), np.sin(yaw_rad)
        ax = np.array([c, s, 0.0]) * lx
        ay = np.array([-s, c, 0.0]) * ly
        az = np.array([0.0, 0.0, lz])
        o = np.array([cx, cy, cz]) - (ax + ay + az) / 2
        self.quad(o, ax, az, mat_a, mat_b, kind, scale_m)
        self.quad(o + ax, ay, az, mat_a, mat_b, kind, scale_m)
        self.quad(o + ax + ay, -ax, az, mat_a, mat_b, kind, scale_m)
        self.quad(o + ay, -ay, az, mat_a, mat_b, kind, scale_m)
        self.quad(
            o + az,
            ax,
            ay,
            top or mat_a,
            mat_b if top is None else None,
            kind if top is None else SOLID,
            scale_m,
        )
        if bottom:
            self.quad(o, ay, ax, mat_a)

    def facet(self, vertices: list[NDArray[np.float64]], mat: str) -> None:
        """Convex planar polygon (vertices in order, world frame, m) of one solid material, as a fan."""
        v = [np.asarray(p, dtype=np.float64) for p in vertices]
        u = (v[1] - v[0]) / np.linalg.norm(v[1] - v[0])
        n = np.cross(v[1] - v[0], v[2] - v[0])
        w = np.cross(n, u)
        w = w / np.linalg.norm(w)
        seed = int(self.rng.integers(0, 2**31 - 1))
        entry = (_MAT_INDEX[mat], _MAT_INDEX[mat], SOLID, 1.0, v[0], u, w, seed)
        for a, b in itertools.pairwise(v[1:]):
            self.tris.append(np.stack([v[0], a, b]))
            self.attrs.append(entry)

    def terrace(self, center: NDArray[np.float64] | list[float], top_size: tuple[float, float], height_m: float,
                run_m: float, yaw_rad: float, mat: str, side_mat: str | None = None) -> None:
        """Raised platform on the ground: flat top ``top_size`` (length along yaw, width, m) at
        ``height_m``, four sides sloping down over ``run_m`` to z = 0. Its creases are edges of surface
        orientation (sun shading in the image, normals in the lidar) with continuous range."""
        c, s = np.cos(yaw_rad), np.sin(yaw_rad)
        ax, ay = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
        ctr = np.array([center[0], center[1], 0.0])
        corners = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        top = [ctr + i * ax * top_size[0] / 2 + j * ay * top_size[1] / 2 + [0, 0, height_m] for i, j in corners]
        foot = [ctr + i * ax * (top_size[0] / 2 + run_m) + j * ay * (top_size[1] / 2 + run_m) for i, j in corners]
        self.facet(top, mat)
        for k in range(4):
            m = (k + 1) % 4
            self.facet([foot[k], foot[m], top[m], top[k]], side_mat or mat)

    def build(self, name: str, seed: int, route: RouteSpec, lidar_height_m: float) -> Scene:
        tris = np.ascontiguousarray(np.stack(self.tris))
        cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        normals: NDArray[np.float64] = np.asarray(cross / np.linalg.norm(cross, axis=1, keepdims=True), np.float64)
        a = self.attrs
        return Scene(
            name=name,
            seed=seed,
            triangles=tris,
            normals=normals,
            mat_a=np.array([x[0] for x in a], dtype=np.int64),
            mat_b=np.array([x[1] for x in a], dtype=np.int64),
            tex_kind=np.array([x[2] for x in a], dtype=np.int64),
            tex_scale_m=np.array([x[3] for x in a], dtype=np.float64),
            tex_origin=np.stack([x[4] for x in a]),
            tex_u=np.stack([x[5] for x in a]),
            tex_v=np.stack([x[6] for x in a]),
            tex_seed=np.array([x[7] for x in a], dtype=np.int64),
            route=route,
            lidar_height_m=lidar_height_m,
        )


def build_scene(name: str, seed: int = 0) -> Scene:
    """Build scene ``street``, ``corridor`` or ``open`` deterministically from ``seed``."""
    if name not in SCENES:
        raise ConfigError(f"unknown scene {name!r} (choose from {', '.join(SCENES)})")
    rng = np.random.default_rng(np.random.SeedSequence([seed, SCENES.index(name), 0x5CE7E]))
    if name == "street":
        return _street(rng, seed)
    if name == "corridor":
        return _corridor(rng, seed)
    return _open(rng, seed)


def surface_properties(
    scene: Scene, tri: NDArray[np.integer], points_world: NDArray[np.floating]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Albedo (N, 3) RGB in [0, 1] and lidar reflectivity (N,) in [0, 1] at points (N, 3, world frame, m)
    lying on triangles ``tri`` (N,) of ``scene``."""
    tri_idx = np.ascontiguousarray(tri, dtype=np.int64).ravel()
    points = np.ascontiguousarray(points_world, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] != tri_idx.size:
        raise ProcessingError(f"{points.shape[0]} points but {tri_idx.size} triangle indices")
    if tri_idx.size and (tri_idx.min() < 0 or tri_idx.max() >= scene.n_triangles):
        raise ProcessingError("triangle index out of range")
    if not np.all(np.isfinite(points)):
        raise ProcessingError("surface points contain NaN or infinite values")
    albedo = np.empty((tri_idx.size, 3))
    refl = np.empty(tri_idx.size)
    if tri_idx.size:
        surface_kernel(
            points,
            tri_idx,
            scene.tex_origin,
            scene.tex_u,
            scene.tex_v,
            scene.tex_scale_m,
            scene.tex_kind,
            scene.tex_seed,
            scene.mat_a,
            scene.mat_b,
            MATERIAL_ALBEDO,
            MATERIAL_REFLECTIVITY,
            albedo,
            refl,
        )
    return albedo, refl


def _ring_sides(half_x: float, half_y: float) -> list[tuple[NDArray[np.float64], NDArray[np.float64], float]]:
    """The four sides of a rectangle as (start point, unit direction, length), counter-clockwise."""
    corners = [(-half_x, -half_y), (half_x, -half_y), (half_x, half_y), (-half_x, half_y)]
    sides = []
    for k in range(4):
        p0 = np.array([*corners[k], 0.0])
        p1 = np.array([*corners[(k + 1) % 4], 0.0])
        d = p1 - p0
        length = float(np.linalg.norm(d))
        sides.append((p0, d / length, length))
    return sides


def _facade(
    b: SceneBuilder,
    p0: NDArray[np.float64],
    along: NDArray[np.float64],
    out: NDArray[np.float64],
    length: float,
    height: float,
    material: str,
) -> None:
    """Windows, frames and a door on the facade plane through ``p0`` (outward normal ``out``)."""
    rng = b.rng
    up = np.array([0.0, 0.0, 1.0])
    floors = int(height // 3.2)
    spacing = float(rng.uniform(2.6, 3.8))
    n_win = int((length - 1.0) // spacing)
    w, h = float(rng.uniform(0.9, 1.5)), float(rng.uniform(1.2, 1.7))
    door_slot = int(rng.integers(0, max(n_win, 1)))
    for f in range(floors):
        for k in range(n_win):
            x0 = 0.5 + spacing * (k + 0.5) - w / 2
            z0 = 3.2 * f + 0.9
            if f == 0 and k == door_slot:
                base = p0 + along * (x0 - 0.1) + out * 0.04
                b.quad(base, along * (w + 0.2), up * 2.3, "wood", "metal", STRIPES, 0.3)
                continue
            base = p0 + along * (x0 - 0.12) + up * (z0 - 0.12) + out * 0.05
            b.quad(base, along * (w + 0.24), up * (h + 0.24), "frame_white")
            b.quad(
                base + along * 0.12 + up * 0.12 + out * 0.03,
                along * w,
                up * h,
                "glass",
                "frame_white",
                STRIPES,
                w / 2 - 0.02 if rng.random() < 0.5 else 10.0,
            )


def _building(
    b: SceneBuilder, p0: NDArray[np.float64], along: NDArray[np.float64], length: float, depth: float
) -> None:
    """A building whose road-facing facade starts at ``p0`` and runs ``length`` along ``along``."""
    rng = b.rng
    out = np.array([along[1], -along[0], 0.0])
    height = float(rng.uniform(7.0, 17.0))
    style = int(rng.integers(0, 3))
    mat, mat_b, kind, scale = [
        ("plaster", "plaster_blue", PATCHES, 6.0),
        ("brick", "mortar", BRICKS, 0.25),
        ("concrete", "concrete_dark", CHECKER, 1.6),
    ][style]
    center = p0 + along * length / 2 - out * depth / 2
    yaw = float(np.arctan2(along[1], along[0]))
    b.box(
        [center[0], center[1], height / 2],
        [length, depth, height],
        yaw,
        mat,
        mat_b,
        kind,
        scale,
        top="concrete",
    )
    _facade(b, p0, along, out, length, height, mat)


def _street(rng: np.random.Generator, seed: int) -> Scene:
    """A one-way loop around a city block: road, markings, kerbs, pavements, facades, poles, trees, cars."""
    b = SceneBuilder(rng)
    A, B, road_half, walk = 48.0, 32.0, 4.5, 4.0
    route = RouteSpec(A + 1.75, B + 1.75, 10.0)
    _street_ground(b, A, B, road_half, walk)
    for p0, d, length in _ring_sides(A, B):
        side = _Side(p0, d, np.array([-d[1], d[0], 0.0]), length, road_half + 0.5)
        _road_markings(b, side, road_half)
        _parked_cars(b, side, road_half)
        _pavement_furniture(b, side, road_half)
        _facades(b, side, road_half + walk)
    return b.build("street", seed, route, lidar_height_m=1.9)


@dataclass(frozen=True)
class _Side:
    """One side of the street's loop: its start (3,), direction (3,) and left (3,) unit vectors, length (m) and
    where its straight part starts (m from the corner)."""

    p0: NDArray[np.float64]
    d: NDArray[np.float64]
    left: NDArray[np.float64]
    length: float
    straight0: float


def _street_ground(b: SceneBuilder, A: float, B: float, road_half: float, walk: float) -> None:
    """The asphalt, the block's kerbed concrete island and the four pavements."""
    kerb_h = 0.12
    margin = 30.0
    b.quad(
        [-A - margin, -B - margin, 0.0],
        [2 * (A + margin), 0, 0],
        [0, 2 * (B + margin), 0],
        "asphalt",
        "asphalt_light",
        PATCHES,
        3.0,
    )
    ix, iy = A - road_half, B - road_half
    b.box([0, 0, kerb_h / 2], [2 * ix, 2 * iy, kerb_h], 0.0, "kerb", top="concrete")
    b.quad([-ix, -iy, kerb_h + 0.002], [2 * ix, 0, 0], [0, 2 * iy, 0], "concrete", "concrete_dark", CHECKER, 0.6)
    ox, oy = A + road_half, B + road_half
    for cx, cy, sx, sy in [
        (0, -(oy + walk / 2), 2 * (ox + walk), walk),
        (0, oy + walk / 2, 2 * (ox + walk), walk),
        (-(ox + walk / 2), 0, walk, 2 * oy),
        (ox + walk / 2, 0, walk, 2 * oy),
    ]:
        b.box([cx, cy, kerb_h / 2], [sx, sy, kerb_h], 0.0, "kerb", top="concrete")
        b.quad(
            [cx - sx / 2, cy - sy / 2, kerb_h + 0.002],
            [sx, 0, 0],
            [0, sy, 0],
            "concrete",
            "concrete_dark",
            CHECKER,
            0.6,
        )


def _road_markings(b: SceneBuilder, side: _Side, road_half: float) -> None:
    """A dashed centre line, edge lines, zebra crossings at both ends and three asphalt patches."""
    p0, d, left, length, straight0 = side.p0, side.d, side.left, side.length, side.straight0
    s = straight0
    while s + 3.0 < length - straight0:
        c = p0 + d * s - left * 0.075 + np.array([0, 0, 0.006])
        b.quad(c, d * 3.0, left * 0.15, "paint_yellow")
        s += 9.0
    for off in (road_half - 0.35, -(road_half - 0.35)):
        c = p0 + d * straight0 + left * off - left * 0.06 + np.array([0, 0, 0.006])
        b.quad(c, d * (length - 2 * straight0), left * 0.12, "paint_white")
    for end in (straight0 + 0.6, length - straight0 - 4.6):
        for k in range(9):
            c = p0 + d * end + left * (-road_half + 0.3 + k * 0.95) + np.array([0, 0, 0.006])
            b.quad(c, d * 4.0, left * 0.5, "paint_white")
    for _ in range(3):
        s0 = float(b.rng.uniform(straight0 + 6, length - straight0 - 10))
        off = float(b.rng.uniform(-road_half + 0.5, road_half - 3.0))
        c = p0 + d * s0 + left * off + np.array([0, 0, 0.003])
        b.quad(
            c,
            d * float(b.rng.uniform(2, 5)),
            left * float(b.rng.uniform(1.2, 2.5)),
            "asphalt_dark",
            "asphalt_light",
            PATCHES,
            0.8,
        )


def _parked_cars(b: SceneBuilder, side: _Side, road_half: float) -> None:
    """Cars parked along the inner kerb (left of the driving direction)."""
    s = side.straight0 + 8.0
    while s < side.length - side.straight0 - 12.0:
        if b.rng.random() < 0.55:
            _car(b, side.p0 + side.d * (s + 2.1) + side.left * (road_half - 1.2),
                 float(np.arctan2(side.d[1], side.d[0])))
        s += float(b.rng.uniform(5.5, 8.0))


def _pavement_furniture(b: SceneBuilder, side: _Side, road_half: float) -> None:
    """Trees and poles (some with a sign facing the road) on both pavements."""
    p0, d, left, length, straight0 = side.p0, side.d, side.left, side.length, side.straight0
    for sign in (1.0, -1.0):
        s = straight0 + float(b.rng.uniform(2, 6))
        while s < length - straight0 - 2:
            base = p0 + d * s + left * sign * (road_half + 0.8)
            if b.rng.random() < 0.5:
                _tree(b, base)
            else:
                b.box([base[0], base[1], 2.6], [0.14, 0.14, 5.2], 0.0, "metal")
                if b.rng.random() < 0.6:
                    face = -left * sign
                    sign_c = base + face * 0.09 - d * 0.35 + np.array([0, 0, 2.2])
                    mats = [("sign_red", "sign_white"), ("sign_blue", "sign_white")][int(b.rng.integers(0, 2))]
                    b.quad(
                        sign_c,
                        d * 0.7,
                        np.array([0, 0, 0.7]),
                        mats[0],
                        mats[1],
                        [STRIPES, CHECKER][int(b.rng.integers(0, 2))],
                        0.175,
                    )
            s += float(b.rng.uniform(9.0, 16.0))


def _facades(b: SceneBuilder, side: _Side, inset: float) -> None:
    """Buildings of the inner block (left of the driving direction, 8 m) and the outer row (right, 10 m)."""
    p0, d, left, length = side.p0, side.d, side.left, side.length
    s = inset + 0.5
    while s < length - inset - 4.0:
        blen = float(min(b.rng.uniform(10.0, 22.0), length - inset - 0.5 - s))
        _building(b, p0 + d * s + left * inset, d, blen, 8.0)
        s += blen + float(b.rng.uniform(0.0, 3.0))
    s = -inset + 0.5
    while s < length + inset - 4.0:
        blen = float(min(b.rng.uniform(10.0, 22.0), length + inset - 0.5 - s))
        _building(b, p0 + d * (s + blen) - left * inset, -d, blen, 10.0)
        s += blen + float(b.rng.uniform(0.0, 3.0))


def _car(b: SceneBuilder, center: NDArray[np.float64], yaw: float) -> None:
    rng = b.rng
    paint = ["car_red", "car_white", "car_black", "car_blue", "car_silver"][int(rng.integers(0, 5))]
    c, s = np.cos(yaw), np.sin(yaw)
    fwd, left = np.array([c, s, 0.0]), np.array([-s, c, 0.0])
    b.box([center[0], center[1], 0.7], [4.2, 1.8, 0.8], yaw, paint)
    cab = center - fwd * 0.3
    b.box([cab[0], cab[1], 1.4], [2.2, 1.6, 0.6], yaw, "glass", top=paint)
    for fx in (-1.35, 1.35):
        for ly in (-0.8, 0.8):
            w = center + fwd * fx + left * ly
            b.box([w[0], w[1], 0.3], [0.65, 0.25, 0.6], yaw, "tyre")


def _tree(b: SceneBuilder, base: NDArray[np.float64]) -> None:
    rng = b.rng
    trunk_h = float(rng.uniform(2.0, 3.0))
    b.box([base[0], base[1], trunk_h / 2], [0.3, 0.3, trunk_h], float(rng.uniform(0, np.pi)), "bark")
    size = float(rng.uniform(2.0, 3.2))
    b.box(
        [base[0], base[1], trunk_h + size / 2],
        [size, size, size],
        float(rng.uniform(0, np.pi)),
        "foliage",
        "foliage_dark",
        PATCHES,
        0.5,
        bottom=True,
    )


def _corridor(rng: np.random.Generator, seed: int) -> Scene:
    """A loop of 3 m wide, 3 m high corridors with 71 m long straights (paper Fig. 3's poster wall).

    Geometry is degenerate along each straight (two flat walls, floor, ceiling); texture is not: the walls
    are covered edge to edge with posters of varied sizes (0.2-1.6 m wide, stacked in one to three rows)
    whose lidar reflectivity and visible albedo both jump strongly at every poster edge (some inverted
    between the two), the floor has black/white tiles in irregular patches and cross lines at random
    spacing, and the ceiling carries lamp panels. The vehicle starts in the middle of the bottom straight
    heading +x; the corridor's ends are 35.5 m ahead and behind, so with ``max_range_m`` <= 25 m they
    stay out of range for the first ~70 scans at the default 1.5 m/s (nothing pins the along-wall motion
    but texture); at full range a few near-horizontal beams still see them.
    """
    b = SceneBuilder(rng)
    A, B, half_w, height = 34.0, 12.0, 1.5, 3.0
    route = RouteSpec(A, B, 1.5)
    ext = 2.0
    b.quad(
        [-A - ext, -B - ext, 0.0],
        [2 * (A + ext), 0, 0],
        [0, 2 * (B + ext), 0],
        "tile_white",
        "tile_black",
        PATCHES,
        0.4,
    )
    b.quad([-A - ext, -B - ext, height], [0, 2 * (B + ext), 0], [2 * (A + ext), 0, 0], "ceiling")
    for p0, d, length in _ring_sides(A, B):
        _corridor_floor_and_lamps(b, p0, d, length, half_w, height)
    for sign in (1.0, -1.0):
        for p0, d, length in _ring_sides(A - sign * half_w, B - sign * half_w):
            _poster_wall(b, p0, d, length, np.array([-d[1], d[0], 0.0]) * (-sign), height)
    return b.build("corridor", seed, route, lidar_height_m=1.0)


_POSTER_MATERIALS = [
    ("poster_retro", "poster_matte"),
    ("poster_yellow", "poster_navy"),
    ("poster_white", "poster_black"),
    ("poster_red", "poster_matte"),
    ("poster_ir_dark", "poster_ir_bright"),
    ("poster_navy", "poster_retro"),
    ("poster_ir_bright", "poster_white"),
    ("poster_ir_dark", "poster_retro"),
]
"""(material, second material) pairs of the corridor's posters: reflectivity and albedo jump at their edges."""
_UP = np.array([0.0, 0.0, 1.0])


def _corridor_floor_and_lamps(b: SceneBuilder, p0: NDArray[np.float64], d: NDArray[np.float64], length: float,
                              half_w: float, height: float) -> None:
    """One straight's floor cross lines (white and yellow paint, random spacing and width) and ceiling lamps."""
    rng, up = b.rng, _UP
    left = np.array([-d[1], d[0], 0.0])
    s = float(rng.uniform(0.2, 1.0))
    while s < length - 0.5:
        w = float(rng.uniform(0.05, 0.3))
        paint = "paint_white" if rng.random() < 0.6 else "paint_yellow"
        b.quad(p0 + d * s - left * half_w + up * 0.002, d * w, left * 2 * half_w, paint)
        s += w + float(rng.uniform(0.6, 3.5))
    s = float(rng.uniform(0.5, 2.0))
    while s < length - 1.5:
        w = float(rng.uniform(0.6, 1.2))
        b.quad(p0 + d * (s + w) - left * 0.3 + up * (height - 0.002), -d * w, left * 0.6, "ceiling_lamp")
        s += w + float(rng.uniform(1.5, 4.0))


def _poster_wall(b: SceneBuilder, p0: NDArray[np.float64], d: NDArray[np.float64], length: float,
                 inward_to_corridor: NDArray[np.float64], height: float) -> None:
    """One wall of a straight, covered edge to edge with posters stacked in one to three rows."""
    rng, up = b.rng, _UP
    b.quad(p0 + np.array([0, 0, 0.0]), d * length, up * height, "wall")
    s = float(rng.uniform(0.0, 0.2))
    while s < length - 0.2:
        w = float(min(rng.uniform(0.2, 1.6), length - s))
        rows = int(rng.integers(1, 4))
        edges = np.concatenate([[0.05], np.sort(rng.uniform(0.4, 2.6, size=rows - 1)), [2.95]])
        for z0, z1 in itertools.pairwise(edges):
            if z1 - z0 < 0.15:
                continue
            ma, mb = _POSTER_MATERIALS[int(rng.integers(0, len(_POSTER_MATERIALS)))]
            kind = [CHECKER, STRIPES, PATCHES, SOLID, STRIPES][int(rng.integers(0, 5))]
            c = p0 + d * s + up * float(z0 + 0.02) + inward_to_corridor * 0.002
            b.quad(c, d * w, up * float(z1 - z0 - 0.04), ma, mb, kind, float(rng.uniform(0.05, 0.4)))
        s += w + float(rng.uniform(0.02, 0.25))


def _open(rng: np.random.Generator, seed: int) -> Scene:
    """A large flat yard: few depth edges, strong reflectivity/albedo texture on the ground."""
    b = SceneBuilder(rng)
    route = RouteSpec(30.0, 20.0, 8.0)
    half = 120.0
    b.quad([-half, -half, 0.0], [2 * half, 0, 0], [0, 2 * half, 0], "asphalt", "asphalt_light", PATCHES, 4.0)
    ground = [("grass", "dirt"), ("gravel", "asphalt_dark"), ("concrete", "concrete_dark"), ("dirt", "grass")]
    for _ in range(40):
        c = rng.uniform(-60, 60, size=2)
        sx, sy = rng.uniform(3, 14, size=2)
        ma, mb = ground[int(rng.integers(0, len(ground)))]
        b.quad([c[0], c[1], 0.003], [sx, 0, 0], [0, sy, 0], ma, mb, PATCHES, float(rng.uniform(0.5, 2.5)))
    for row in range(-3, 4):
        y0 = row * 12.0 + 6.0
        for k in range(-12, 13):
            x0 = k * 2.8
            if rng.random() < 0.85:
                b.quad([x0, y0 - 2.5, 0.006], [0.15, 0, 0], [0, 5.0, 0], "paint_white")
        b.quad([-34.0, y0 - 0.08, 0.006], [68.0, 0, 0], [0, 0.16, 0], "paint_yellow")
    for _ in range(12):
        c = rng.uniform(-45, 45, size=2)
        ang = float(rng.uniform(0, np.pi))
        d = np.array([np.cos(ang), np.sin(ang), 0.0])
        n = np.array([-d[1], d[0], 0.0])
        b.quad([c[0], c[1], 0.008], d * 3.0, n * 0.9, "paint_white", "paint_yellow", STRIPES, 0.3)
    for _ in range(4):
        ang = float(rng.uniform(0, 2 * np.pi))
        r = float(rng.uniform(55, 80))
        b.box(
            [r * np.cos(ang), r * np.sin(ang), 1.3],
            [6.0, 2.4, 2.6],
            float(rng.uniform(0, np.pi)),
            "car_blue",
            "metal",
            STRIPES,
            0.4,
        )
    b.box([0.0, 0.0, 3.0], [0.2, 0.2, 6.0], 0.0, "metal")
    _earthworks(b, rng, route)
    return b.build("open", seed, route, lidar_height_m=1.9)


def _earthworks(b: SceneBuilder, rng: np.random.Generator, route: RouteSpec, count: int = 24) -> None:
    """Grass terraces and concrete platforms along the route (their feet 3-15 m from it): creases of
    surface orientation with continuous range, so the open yard has shape that only normals (and
    sun shading in the image) see."""
    placed = 0
    while placed < count:
        c = rng.uniform(-58, 58, size=2)
        length, width = float(rng.uniform(6, 18)), float(rng.uniform(4, 10))
        run = float(rng.uniform(1.5, 4.0))
        reach = 0.5 * np.hypot(length, width) + run + 3.0
        # distance from the centre to the route (|signed distance| to its rounded rectangle)
        q = np.abs(c) - [route.half_x_m - route.corner_radius_m, route.half_y_m - route.corner_radius_m]
        d = abs(float(np.hypot(*np.maximum(q, 0.0))) + min(float(q.max()), 0.0) - route.corner_radius_m)
        if not reach <= d <= reach + 12.0:
            continue
        top, side = [("grass", "concrete"), ("gravel", "concrete_dark"), ("grass", "dirt")][int(rng.integers(0, 3))]
        b.terrace(c, (length, width), float(rng.uniform(0.5, 1.4)), run, float(rng.uniform(0, np.pi)), top, side)
        placed += 1
