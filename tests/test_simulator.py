"""Simulator pieces against slow NumPy references and closed-form ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.errors import ConfigError, ProcessingError
from fleetcal.pipeline.transforms import (
    apply,
    from_xyz_rpy,
    invert,
    make_T,
    rotation_error_deg,
    translation_error_m,
)
from fleetcal.workflows.simulator.camera import (
    SKY_RGB,
    SUN_DIR_WORLD,
    SimCamera,
    fisheye_camera,
    pinhole_camera,
    render,
    render_depth,
    row_times_s,
)
from fleetcal.workflows.simulator.lidar import ROSETTE_HALF_ANGLE_DEG, LidarModel, beam_elevations_deg, simulate_scan
from fleetcal.workflows.simulator.motion import LoopMotion
from fleetcal.workflows.simulator.raycast import build_grid, cast_rays
from fleetcal.workflows.simulator.raycast_kernels import shade_kernel
from fleetcal.workflows.simulator.scene import (
    BRICKS,
    CHECKER,
    MATERIAL_ALBEDO,
    MATERIAL_REFLECTIVITY,
    MATERIALS,
    PATCHES,
    SCENES,
    SOLID,
    STRIPES,
    RouteSpec,
    Scene,
    SceneBuilder,
    build_scene,
    surface_properties,
)
from fleetcal.workflows.simulator.truth import build_rig, perturb
from fleetcal.workflows.simulator.write import SimulationOptions, camera_pose


# ---------------------------------------------------------------- slow NumPy references
def _bruteforce_hits(tris: np.ndarray, origins: np.ndarray, dirs: np.ndarray, t_max: float):
    """Nearest Moller-Trumbore hit of every ray against every triangle (no acceleration)."""
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    best_t = np.full(len(origins), np.inf)
    best_tri = np.full(len(origins), -1)
    for i, (o, d) in enumerate(zip(origins, dirs, strict=True)):
        q = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, q)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            inv = 1.0 / det
            s = o - v0
            u = np.einsum("ij,ij->i", s, q) * inv
            r = np.cross(s, e1)
            v = (r @ d) * inv
            t = np.einsum("ij,ij->i", e2, r) * inv
            ok = (np.abs(det) >= 1e-12) & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t > 1e-6) & (t < t_max)
        if np.any(ok):
            j = np.flatnonzero(ok)[np.argmin(t[ok])]
            best_t[i], best_tri[i] = t[j], j
    return best_t, best_tri


def _hash01_ref(a: np.ndarray, b: np.ndarray, seed: np.ndarray) -> np.ndarray:
    h = (a.astype(np.uint64) * np.uint64(0x9E3779B1)) ^ (b.astype(np.uint64) * np.uint64(0x85EBCA77))
    h ^= seed.astype(np.uint64) * np.uint64(0xC2B2AE3D)
    h ^= h >> np.uint64(15)
    h *= np.uint64(0x2C1B3C6D)
    h ^= h >> np.uint64(12)
    h *= np.uint64(0x297A2D39)
    h ^= h >> np.uint64(15)
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(0x1000000)


def _surface_ref(scene: Scene, tri: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised NumPy version of the texture functions (see ``surface_kernel``)."""
    rel = p - scene.tex_origin[tri]
    s = scene.tex_scale_m[tri]
    u = np.einsum("ij,ij->i", rel, scene.tex_u[tri]) / s
    v = np.einsum("ij,ij->i", rel, scene.tex_v[tri]) / s
    kind, seed = scene.tex_kind[tri], scene.tex_seed[tri]
    fu, fv = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    mix = np.zeros(tri.size)
    gain_a, gain_r = np.ones(tri.size), np.ones(tri.size)
    m = kind == CHECKER
    mix[m] = (fu[m] + fv[m]) % 2
    m = kind == STRIPES
    mix[m] = fu[m] % 2
    m = kind == PATCHES
    coarse = _hash01_ref(fu[m], fv[m], seed[m])
    fine = _hash01_ref(np.floor(u[m] * 4).astype(np.int64), np.floor(v[m] * 4).astype(np.int64), seed[m] + 1)
    mix[m] = np.rint((0.75 * coarse + 0.25 * (fine > 0.7)) * 3) / 3
    m = kind == BRICKS
    row = fv[m]
    uu = u[m] / 2 + 0.5 * (row % 2)
    col = np.floor(uu).astype(np.int64)
    mix[m] = ((v[m] - row) < 0.14) | ((uu - col) < 0.05)
    gain_a[m] = 0.8 + 0.4 * _hash01_ref(col, row, seed[m])
    gain_r[m] = 0.85 + 0.3 * _hash01_ref(col, row, seed[m] + 7)
    a, b = scene.mat_a[tri], scene.mat_b[tri]
    albedo = (MATERIAL_ALBEDO[a] * (1 - mix)[:, None] + MATERIAL_ALBEDO[b] * mix[:, None]) * gain_a[:, None]
    refl = (MATERIAL_REFLECTIVITY[a] * (1 - mix) + MATERIAL_REFLECTIVITY[b] * mix) * gain_r
    return np.clip(albedo, 0, 1), np.clip(refl, 0, 1)


def _ground_scene(material: str = "concrete", size_m: float = 400.0) -> Scene:
    b = SceneBuilder(np.random.default_rng(0))
    h = size_m / 2
    b.quad([-h, -h, 0.0], [size_m, 0, 0], [0, size_m, 0], material)
    return b.build("ground", 0, RouteSpec(20.0, 20.0, 5.0), lidar_height_m=2.0)


@pytest.fixture(scope="module")
def street() -> Scene:
    return build_scene("street", seed=4)


# ---------------------------------------------------------------- ray casting
def test_cast_rays_matches_bruteforce(street: Scene) -> None:
    rng = np.random.default_rng(1)
    n = 400
    origins = np.column_stack([rng.uniform(-60, 60, n), rng.uniform(-45, 45, n), rng.uniform(0.3, 12, n)])
    dirs = rng.standard_normal((n, 3))
    dirs[:50, 2] = np.abs(dirs[:50, 2]) + 2.0  # steep upward rays: mostly misses
    dirs[50:100, 2] = 0.0  # exactly horizontal
    dirs[100:110] = [0.0, 0.0, -1.0]  # straight down onto the ground
    grid = build_grid(street.triangles, cell_m=1.0)
    t, tri = cast_rays(grid, origins, dirs, t_max=150.0)
    t_ref, tri_ref = _bruteforce_hits(street.triangles, origins, dirs, 150.0)
    assert np.array_equal(np.isfinite(t), np.isfinite(t_ref))
    hit = np.isfinite(t_ref)
    assert 100 < hit.sum() < n  # both hits and misses are exercised
    np.testing.assert_allclose(t[hit], t_ref[hit], rtol=0, atol=1e-9)
    # ties (a shared quad diagonal, coplanar overlays) may pick another triangle at the same distance
    assert np.mean(tri[hit] == tri_ref[hit]) > 0.98
    assert np.all(tri[~hit] == -1)


def test_cast_rays_same_result_for_any_thread_count_and_cell_size(street: Scene) -> None:
    rng = np.random.default_rng(2)
    origins = np.tile([0.0, -33.75, 1.9], (70_000, 1))
    dirs = rng.standard_normal((70_000, 3))
    t1, k1 = cast_rays(build_grid(street.triangles, 1.0), origins, dirs, threads=1)
    t2, k2 = cast_rays(build_grid(street.triangles, 1.0), origins, dirs, threads=3)
    t3, _ = cast_rays(build_grid(street.triangles, 2.5), origins, dirs, threads=2)
    assert np.array_equal(t1, t2) and np.array_equal(k1, k2)
    np.testing.assert_allclose(t3, t1, atol=1e-9)


def test_cast_rays_edge_inputs(street: Scene) -> None:
    grid = build_grid(street.triangles)
    t, tri = cast_rays(grid, np.zeros((0, 3)), np.zeros((0, 3)))
    assert t.shape == (0,) and tri.shape == (0,)
    with pytest.raises(ProcessingError, match="NaN"):
        cast_rays(grid, np.array([[0.0, 0.0, np.nan]]), np.array([[1.0, 0.0, 0.0]]))
    with pytest.raises(ProcessingError, match="shape"):
        cast_rays(grid, np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ProcessingError, match="triangles"):
        build_grid(np.zeros((0, 3, 3)))
    # a ray starting outside the grid, pointing at it, hits the ground at the exact distance
    t, tri = cast_rays(grid, np.array([[0.0, -300.0, 10.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert not np.isfinite(t[0]) and tri[0] == -1
    t, tri = cast_rays(grid, np.array([[0.0, -33.0, 50.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert t[0] == pytest.approx(50.0, abs=1e-9) and tri[0] >= 0


# ---------------------------------------------------------------- scene and textures
@pytest.mark.parametrize("name", SCENES)
def test_surface_kernel_matches_numpy_reference(name: str) -> None:
    scene = build_scene(name, seed=3)
    rng = np.random.default_rng(5)
    tri = rng.integers(0, scene.n_triangles, 20_000)
    a, b = rng.random(tri.size), rng.random(tri.size)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    T = scene.triangles[tri]
    points = T[:, 0] + a[:, None] * (T[:, 1] - T[:, 0]) + b[:, None] * (T[:, 2] - T[:, 0])
    albedo, refl = surface_properties(scene, tri, points)
    albedo_ref, refl_ref = _surface_ref(scene, tri, points)
    np.testing.assert_allclose(albedo, albedo_ref, atol=1e-12)
    np.testing.assert_allclose(refl, refl_ref, atol=1e-12)
    kinds = set(scene.tex_kind[tri].tolist())
    assert {SOLID, PATCHES} <= kinds
    with pytest.raises(ProcessingError, match="out of range"):
        surface_properties(scene, np.array([scene.n_triangles]), points[:1])


def test_shade_kernel_matches_numpy_reference(street: Scene) -> None:
    grid = build_grid(street.triangles)
    rig = build_rig(1, street.lidar_height_m, 0.0, 0.0, seed=0)
    T = LoopMotion(street.route, 8.0).T_world_base(2.0) @ rig.T_base_cameras[0]
    cam = SimCamera(fisheye_camera(160, 90))
    rays, ray_ok = cam.rays()
    dirs = np.ascontiguousarray(rays @ T[:3, :3].T)
    origins = np.repeat(T[None, :3, 3], dirs.shape[0], axis=0)
    origins[dirs.shape[0] // 2 :] += (0.4, -0.2, 0.1)  # the lower half from another position (rolling shutter)
    t_hit, tri = cast_rays(grid, origins, dirs, t_max=500.0)
    mix, gain, gamma = 0.3, 1.4, 2.2
    out = np.empty((dirs.shape[0], 3), dtype=np.float32)
    shade_kernel(
        origins,
        dirs,
        ray_ok,
        t_hit,
        tri,
        street.normals,
        street.tex_origin,
        street.tex_u,
        street.tex_v,
        street.tex_scale_m,
        street.tex_kind,
        street.tex_seed,
        street.mat_a,
        street.mat_b,
        MATERIAL_ALBEDO,
        MATERIAL_REFLECTIVITY,
        SUN_DIR_WORLD,
        SKY_RGB,
        mix,
        gain,
        gamma,
        out,
    )
    hit = (tri >= 0) & ray_ok
    sky = (tri < 0) & ray_ok
    assert hit.sum() > 1000 and sky.sum() > 100 and (~ray_ok).sum() > 100
    linear = np.zeros((dirs.shape[0], 3))
    albedo, refl = _surface_ref(street, tri[hit], origins[hit] + dirs[hit] * t_hit[hit, None])
    n = street.normals[tri[hit]]
    n = np.where((np.einsum("ij,ij->i", n, dirs[hit]) > 0)[:, None], -n, n)
    shade = 0.45 + 0.55 * np.clip(n @ SUN_DIR_WORLD, 0, None)
    linear[hit] = ((1 - mix) * albedo + mix * refl[:, None]) * shade[:, None]
    linear[sky] = SKY_RGB * (0.75 + 0.35 * np.clip(dirs[sky, 2], -1, 1))[:, None]
    expected = 255.0 * np.clip(linear * gain, 0, 1) ** (1 / gamma)
    np.testing.assert_allclose(out, expected, atol=1e-3)
    assert np.all(out[~ray_ok] == 0)  # outside the fisheye circle


def test_scenes_are_seeded_and_textured() -> None:
    a, b, c = build_scene("street", 7), build_scene("street", 7), build_scene("street", 8)
    assert np.array_equal(a.triangles, b.triangles) and np.array_equal(a.tex_seed, b.tex_seed)
    assert a.triangles.shape != c.triangles.shape or not np.array_equal(a.triangles, c.triangles)
    assert a.n_triangles > 2000  # road, markings, kerbs, facades with windows, poles, trees, cars
    assert {CHECKER, STRIPES, PATCHES, BRICKS} <= set(a.tex_kind.tolist())
    corridor = build_scene("corridor", 7)
    wall_normals = np.abs(corridor.normals[:, 2]) < 0.1
    assert wall_normals.sum() > 50  # posters on the walls
    with pytest.raises(ConfigError, match="unknown scene"):
        build_scene("moon")


def test_reflectivity_and_albedo_correlated_not_equal_some_inverted() -> None:
    grey = np.array([np.mean(v[0]) for v in MATERIALS.values()])
    refl = np.array([v[1] for v in MATERIALS.values()])
    r = np.corrcoef(grey, refl)[0, 1]
    assert 0.3 < r < 0.95
    inverted = [
        (m1, m2)
        for m1, (a1, r1) in MATERIALS.items()
        for m2, (a2, r2) in MATERIALS.items()
        if np.mean(a1) > np.mean(a2) + 0.1 and r1 < r2 - 0.1
    ]
    assert ("foliage", "asphalt") not in inverted  # foliage: darker visible AND brighter lidar
    assert ("asphalt", "foliage") in inverted or ("mortar", "brick") in inverted
    assert ("mortar", "brick") in inverted and ("asphalt_light", "asphalt_dark") in inverted


# ---------------------------------------------------------------- lidar
def test_beam_layouts() -> None:
    el64 = beam_elevations_deg(64)
    assert el64.size == 64 and el64[0] == pytest.approx(-24.8) and el64[-1] == pytest.approx(2.0)
    assert np.all(np.diff(el64) > 0)
    np.testing.assert_allclose(np.diff(beam_elevations_deg(16)), 2.0)
    assert beam_elevations_deg(32)[0] == pytest.approx(-30.67)
    assert beam_elevations_deg(128).size == 128
    with pytest.raises(ConfigError, match="beam"):
        beam_elevations_deg(0)
    with pytest.raises(ConfigError, match="columns"):
        LidarModel(columns=10)


def test_lidar_on_flat_ground_ranges_intensity_dropouts() -> None:
    scene = _ground_scene("concrete")
    grid = build_grid(scene.triangles)
    model = LidarModel(beams=16, columns=2048, range_noise_m=0.015, dropout=0.01, seed=3)
    T_world_lidar = make_T(np.eye(3), [0.0, 0.0, 2.0])
    scan = simulate_scan(scene, grid, model, T_world_lidar, np.random.default_rng(0))
    el = np.radians(model.elevations_deg)
    assert not scan.valid[el >= 0].any()  # upward beams see nothing
    assert not scan.valid[2.0 / np.sin(-np.minimum(el, -1e-9)) > 100.5].any()  # beyond max range
    down = el < np.radians(-5.0)  # in range, signal well above the weak-return threshold
    assert scan.points_xyz.shape == (16, 2048, 3) and scan.points_xyz.dtype == np.float32
    valid = scan.valid[down]
    drop_rate = 1 - valid.mean()
    assert 0.005 < drop_rate < 0.02
    expected_range = (2.0 / np.sin(-el[down]))[:, None] * np.ones((1, 2048))
    rng_m = np.linalg.norm(scan.points_xyz[down].astype(np.float64), axis=-1)
    residual = (rng_m - expected_range)[valid]
    assert abs(residual.mean()) < 0.002 and 0.012 < residual.std() < 0.018
    # ring r is the r-th lowest beam; its points lie at that elevation
    pts = scan.points_xyz[scan.valid].astype(np.float64)
    elev = np.degrees(np.arcsin(pts[:, 2] / np.linalg.norm(pts, axis=1)))
    np.testing.assert_allclose(elev, model.elevations_deg[scan.ring[scan.valid]], atol=0.05)
    # intensity = 255 * reflectivity * cos(incidence) * beam gain (+ 1.5 DN noise)
    expected_i = 255 * MATERIALS["concrete"][1] * np.sin(-el[down])[:, None] * model.beam_gains[down][:, None]
    ratio = np.nanmedian(scan.intensity[down] / expected_i, axis=1)
    np.testing.assert_allclose(ratio, 1.0, atol=0.03)
    assert np.std(model.beam_gains) > 0.03  # gains really differ per beam
    np.testing.assert_array_equal(scan.time_s, 0.0)  # de-skewed: every point is where it was at the stamp


def test_skewed_scan_reports_each_column_in_its_own_frame() -> None:
    scene = _ground_scene()
    grid = build_grid(scene.triangles)
    model = LidarModel(beams=16, columns=256, range_noise_m=0.0, dropout=0.0)
    poses = np.stack([make_T(np.eye(3), [x, 0.0, 2.0]) for x in np.linspace(0, 1.0, 256)])
    skewed = simulate_scan(scene, grid, model, poses, np.random.default_rng(0))
    still = simulate_scan(scene, grid, model, poses[0], np.random.default_rng(0))
    # over flat ground a pure translation changes nothing in the sensor frame
    np.testing.assert_allclose(skewed.points_xyz[skewed.valid], still.points_xyz[still.valid], atol=1e-4)
    np.testing.assert_allclose(skewed.time_s[0], np.arange(256) / 256 * 0.1, atol=1e-7)  # firing times
    with pytest.raises(ConfigError, match="T_world_lidar"):
        simulate_scan(scene, grid, model, poses[:3], np.random.default_rng(0))


def _fov_cells(directions: np.ndarray, cell_deg: float = 0.3, within_deg: float = 30.0) -> set[tuple[int, int]]:
    """Cells (``cell_deg`` square in the lidar's y/x, z/x angles) hit by rays within ``within_deg`` of +x."""
    d = directions.reshape(-1, 3)
    d = d[np.degrees(np.arccos(np.clip(d[:, 0], -1, 1))) < within_deg]
    yaw = np.floor(np.degrees(np.arctan2(d[:, 1], d[:, 0])) / cell_deg).astype(int)
    pitch = np.floor(np.degrees(np.arctan2(d[:, 2], d[:, 0])) / cell_deg).astype(int)
    return set(zip(yaw.tolist(), pitch.tolist(), strict=True))


def test_rosette_lidar_fills_its_circular_field_of_view_without_repeating() -> None:
    """6 lines x 4000 samples (a Livox Avia's 24k points per 0.1 s scan): every ray within the 35.2 deg
    half-angle, from the centre to the rim; the next scan's rays lie elsewhere, so ten scans hit about 3x
    the 0.3 deg cells that one does (measured 3.1x), as a non-repetitive pattern does."""
    model = LidarModel(beams=6, columns=4000, pattern="rosette")
    first = model.directions(0.0)
    assert first.shape == (6, 4000, 3)
    np.testing.assert_allclose(np.linalg.norm(first, axis=-1), 1.0, atol=1e-12)
    off_axis_deg = np.degrees(np.arccos(np.clip(first[..., 0], -1.0, 1.0)))
    assert off_axis_deg.max() == pytest.approx(ROSETTE_HALF_ANGLE_DEG, abs=0.05)
    assert off_axis_deg.min() < 0.5
    np.testing.assert_array_equal(model.directions(0.0), first)  # the pattern follows the clock only
    assert np.abs(model.directions(0.1) - first).max() > 0.5
    one = _fov_cells(first)
    ten = set(one).union(*(_fov_cells(model.directions(0.1 * k)) for k in range(1, 10)))
    assert len(ten) > 2.5 * len(one)
    with pytest.raises(ConfigError, match="lines"):
        LidarModel(beams=64, pattern="rosette")
    with pytest.raises(ConfigError, match="pattern"):
        LidarModel(pattern="flash")  # type: ignore[arg-type]


def test_simulation_options_take_the_lidar_patterns_layout_unless_given() -> None:
    """Beams and columns left out follow the pattern (64 x 1024 spinning, 6 x 4000 rosette), in the Python
    API as on the CLI; given ones are kept and checked against the pattern."""
    rosette = SimulationOptions(lidar="rosette")
    rosette.validate()
    assert (rosette.beams, rosette.columns) == (6, 4000)
    spinning = SimulationOptions(columns=512)
    assert (spinning.beams, spinning.columns) == (64, 512)
    assert SimulationOptions(lidar="rosette", beams=16).beams == 16
    with pytest.raises(ConfigError, match="lines"):
        SimulationOptions(lidar="rosette", beams=64).validate()


def test_simulation_options_clock_offset_and_readout() -> None:
    """Milliseconds in, seconds out; 0 and 0 by default; nonsense values are refused."""
    default = SimulationOptions()
    assert (default.time_offset_s, default.readout_s) == (0.0, 0.0)
    opts = SimulationOptions(time_offset_ms=-30.0, readout_ms=20.0)
    opts.validate()
    assert (opts.time_offset_s, opts.readout_s) == (-0.03, 0.02)
    for kwargs, message in [
        ({"time_offset_ms": float("nan")}, "time-offset-ms"),
        ({"time_offset_ms": 1500.0}, "time-offset-ms"),
        ({"readout_ms": -1.0}, "readout-ms"),
        ({"readout_ms": float("inf")}, "readout-ms"),
    ]:
        with pytest.raises(ConfigError, match=message):
            SimulationOptions(**kwargs).validate()  # type: ignore[arg-type]


def test_rosette_scan_returns_lie_on_their_rays_over_ground() -> None:
    """A rosette pitched 45 deg down from 2 m over flat ground: each return lies on its own ray at the
    range where that ray meets the ground (noise 1.5 cm), and its line is its row."""
    scene = _ground_scene("concrete")
    grid = build_grid(scene.triangles)
    model = LidarModel(beams=4, columns=1000, pattern="rosette", dropout=0.0, seed=2)
    pitch_down = Rotation.from_euler("y", 45.0, degrees=True).as_matrix()
    T_world_lidar = make_T(pitch_down, [0.0, 0.0, 2.0])
    scan = simulate_scan(scene, grid, model, T_world_lidar, np.random.default_rng(0), scan_start_s=3.0)
    dirs = model.directions(3.0)
    down = -(dirs @ pitch_down.T)[..., 2]  # sine of each ray's angle below the horizon
    assert scan.valid[down > 0.05].mean() > 0.97 and not scan.valid[down <= 0].any()
    ranges = np.linalg.norm(scan.points_xyz.astype(np.float64), axis=-1)
    np.testing.assert_allclose((scan.points_xyz / ranges[..., None])[scan.valid], dirs[scan.valid], atol=1e-5)
    residual = (ranges - 2.0 / np.where(down > 0, down, np.nan))[scan.valid & (down > 0.05)]
    assert abs(residual.mean()) < 0.005 and residual.std() < 0.03
    np.testing.assert_array_equal(scan.ring, np.arange(4)[:, None] * np.ones((1, 1000), dtype=np.uint16))


# ---------------------------------------------------------------- cameras and truth geometry
@pytest.mark.parametrize("make", [pinhole_camera, fisheye_camera])
def test_camera_rays_reproject_to_their_pixels(make) -> None:
    cam = SimCamera(make(320, 200))
    rays, ok = cam.rays()
    uv, valid = cam.model.project(rays * 7.0)
    v, u = np.mgrid[0:200, 0:320]
    pix = np.column_stack([u.ravel(), v.ravel()])
    assert ok.mean() > 0.6 and np.all(valid[ok])
    np.testing.assert_allclose(uv[ok], pix[ok], atol=1e-3)


def test_lidar_range_matches_camera_depth_at_true_extrinsic(street: Scene) -> None:
    """Geometric ground truth: noise-free lidar points moved by the true T_camera_lidar have the depth the
    camera renders at their pixel (sub-millimetre); 1 deg or 5 cm about/along any axis breaks that."""
    grid = build_grid(street.triangles)
    motion = LoopMotion(street.route, 8.0)
    rig = build_rig(1, street.lidar_height_m, 2.0, 0.1, seed=4)
    T_world_base = motion.T_world_base(3.0)
    lidar = LidarModel(beams=64, columns=1024, range_noise_m=0.0, seed=4)
    scan = simulate_scan(street, grid, lidar, T_world_base @ rig.T_base_lidar, np.random.default_rng(0))
    cam = SimCamera(pinhole_camera(640, 360))
    depth = render_depth(grid, cam, T_world_base @ rig.T_base_cameras[0])
    points = scan.points_xyz[scan.valid].astype(np.float64)

    def residuals(T_camera_lidar: np.ndarray) -> np.ndarray:
        p = apply(T_camera_lidar, points)
        uv, ok = cam.model.project(p)
        d = map_coordinates(depth, [uv[ok, 1], uv[ok, 0]], order=1, mode="nearest")
        return np.asarray(d - p[ok, 2])

    T_true = rig.T_camera_lidar[0]
    r = residuals(T_true)
    assert r.size > 5000
    assert np.nanmedian(np.abs(r)) < 0.001
    agree_truth = np.nanmean(np.abs(r) < 0.01)
    assert agree_truth > 0.9
    for axis in range(6):
        for sign in (1.0, -1.0):
            delta = np.zeros(6)
            delta[axis] = sign * (0.05 if axis < 3 else 1.0)
            agree = np.nanmean(np.abs(residuals(from_xyz_rpy(*delta) @ T_true)) < 0.01)
            assert agree < agree_truth - 0.1, (axis, sign, agree, agree_truth)
    assert np.nanmean(np.abs(residuals(rig.T_camera_lidar_in_log[0])) < 0.01) < 0.5


def test_render_is_seeded_and_sees_texture(street: Scene) -> None:
    grid = build_grid(street.triangles)
    cam = SimCamera(pinhole_camera(320, 180))
    rig = build_rig(1, street.lidar_height_m, 0.0, 0.0, seed=0)
    T = LoopMotion(street.route, 8.0).T_world_base(1.0) @ rig.T_base_cameras[0]
    a = render(street, grid, cam, T, np.random.default_rng(3))
    b = render(street, grid, cam, T, np.random.default_rng(3))
    c = render(street, grid, cam, T, np.random.default_rng(4))
    assert a.shape == (180, 320, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.abs(a.astype(int) - c.astype(int)).mean() < 3  # only the sensor noise differs
    assert a[:40].mean() > 100 and a.std() > 25  # bright sky on top, textured scene
    nir = render(street, grid, SimCamera(cam.model, spectral_mix=1.0), T, np.random.default_rng(3))
    assert np.abs(nir[..., 0].astype(int) - nir[..., 2].astype(int))[100:].mean() < 3  # grey where it hits
    with pytest.raises(ConfigError, match="spectral_mix"):
        SimCamera(cam.model, spectral_mix=1.5)
    # one pose per row, all the same: the global-shutter image, bit for bit
    same_rows = np.repeat(T[None], 180, axis=0)
    np.testing.assert_array_equal(render(street, grid, cam, same_rows, np.random.default_rng(3)), a)
    np.testing.assert_array_equal(render_depth(grid, cam, same_rows), render_depth(grid, cam, T))
    with pytest.raises(ProcessingError, match="one per image row"):
        render(street, grid, cam, same_rows[:-1], np.random.default_rng(3))


def test_rolling_shutter_row_is_the_global_shutter_render_at_that_rows_time(street: Scene) -> None:
    """Rolling shutter (50 ms readout at 10 m/s in a corner of the street block): row r of the image equals
    row r of a global-shutter image taken at row r's time, colour (no blur, no noise) and depth alike; the
    first row is the stamp's, most later rows differ from it."""
    grid = build_grid(street.triangles)
    cam = SimCamera(pinhole_camera(160, 120), blur_sigma_px=0.0, noise_dn=0.0)
    rig = build_rig(1, street.lidar_height_m, 0.0, 0.0, seed=0)
    motion = LoopMotion(street.route, 10.0)
    T_base_camera = rig.T_base_cameras[0]
    first_s, readout_s = 2.3, 0.05
    times = row_times_s(first_s, readout_s, 120)
    assert times[0] == first_s and times[-1] == pytest.approx(first_s + readout_s, abs=1e-12)
    np.testing.assert_allclose(np.diff(times), readout_s / 119, rtol=1e-9)
    per_row = np.stack([motion.T_world_base(t) @ T_base_camera for t in times])
    poses = camera_pose(motion, T_base_camera, first_s, readout_s, 120)
    assert poses.shape == (120, 4, 4)
    np.testing.assert_allclose(poses, per_row, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(camera_pose(motion, T_base_camera, first_s, 0.0, 120), per_row[0])
    rolling = render(street, grid, cam, per_row, np.random.default_rng(0))
    depth = render_depth(grid, cam, per_row)
    for r in (0, 37, 80, 119):
        glob = render(street, grid, cam, per_row[r], np.random.default_rng(0))
        np.testing.assert_array_equal(rolling[r], glob[r])
        np.testing.assert_array_equal(depth[r], render_depth(grid, cam, per_row[r])[r])
    at_stamp = render(street, grid, cam, per_row[0], np.random.default_rng(0))
    changed = np.any(rolling != at_stamp, axis=(1, 2))
    assert not changed[0] and changed.mean() > 0.7
    with pytest.raises(ConfigError, match="readout"):
        row_times_s(first_s, -0.01, 120)


# ---------------------------------------------------------------- motion and rig
def test_loop_motion_constant_speed_tangent_heading_and_closed_loop() -> None:
    motion = LoopMotion(RouteSpec(49.75, 33.75, 10.0), 8.0)
    period = motion.loop_length_m / 8.0
    t = np.linspace(0, period, 4001)
    x, y, yaw = motion.planar(t)
    step = np.hypot(np.diff(x), np.diff(y))
    np.testing.assert_allclose(step, 8.0 * (t[1] - t[0]), rtol=1e-3)
    heading = np.arctan2(np.diff(y), np.diff(x))
    assert np.max(np.abs(np.angle(np.exp(1j * (heading - yaw[:-1]))))) < 0.01
    assert (x[-1], y[-1]) == pytest.approx((x[0], y[0]), abs=1e-9)
    assert np.ptp(np.unwrap(yaw)) == pytest.approx(2 * np.pi, abs=1e-2)  # four left turns
    with pytest.raises(ConfigError):
        LoopMotion(RouteSpec(10.0, 10.0, 20.0), 1.0)


def test_perturb_has_exact_magnitudes_and_rig_is_consistent() -> None:
    rng = np.random.default_rng(0)
    T = from_xyz_rpy(0.1, -0.3, 0.2, 10, -80, 95)
    for deg, m in [(2.0, 0.1), (0.5, 0.0), (10.0, 0.3)]:
        P = perturb(T, deg, m, rng)
        assert rotation_error_deg(T, P) == pytest.approx(deg, abs=1e-9)
        assert translation_error_m(T, P) == pytest.approx(m, abs=1e-12)
    rig = build_rig(4, 1.9, 2.0, 0.1, seed=9)
    for i in range(4):
        assert rotation_error_deg(rig.T_camera_lidar[i], rig.T_camera_lidar_in_log[i]) == pytest.approx(2.0)
        # optical z of camera i points along its yaw (forward, left, right, back) and slightly down
        z_base = rig.T_base_cameras[i][:3, 2]
        yaw = np.degrees(np.arctan2(z_base[1], z_base[0]))
        assert abs((yaw - [0, 90, -90, 180][i] + 180) % 360 - 180) < 1.5
        assert -0.1 < z_base[2] < 0.0
    np.testing.assert_allclose(invert(rig.T_base_cameras[0]) @ rig.T_base_lidar, rig.T_camera_lidar[0])
    with pytest.raises(ConfigError):
        build_rig(0, 1.9, 0, 0, 0)


def test_a_drifted_lidar_mount_leaves_the_cameras_tf_to_one_another_exact() -> None:
    """``drift="lidar"``: every camera's logged extrinsic is off by the same lidar drift (2 deg, 12 cm) and the
    transforms between the cameras that the log implies are the true ones; ``drift="cameras"`` (default)
    drifts each camera apart."""
    lidar = build_rig(6, 1.9, 2.0, 0.12, seed=3, drift="lidar")
    cameras = build_rig(6, 1.9, 2.0, 0.12, seed=3)
    for rig, apart in ((lidar, False), (cameras, True)):
        true0, log0 = rig.T_camera_lidar[0], rig.T_camera_lidar_in_log[0]
        for i in range(6):
            assert rotation_error_deg(rig.T_camera_lidar[i], rig.T_camera_lidar_in_log[i]) == pytest.approx(2.0)
            assert translation_error_m(rig.T_camera_lidar[i], rig.T_camera_lidar_in_log[i]) == pytest.approx(0.12)
            true_i0 = rig.T_camera_lidar[i] @ invert(true0)
            logged_i0 = rig.T_camera_lidar_in_log[i] @ invert(log0)
            assert (rotation_error_deg(true_i0, logged_i0) > 0.5) == (apart and i > 0)
            if not apart:
                np.testing.assert_allclose(logged_i0, true_i0, atol=1e-12)
    np.testing.assert_array_equal(cameras.T_camera_lidar_in_log,
                                  build_rig(6, 1.9, 2.0, 0.12, seed=3, drift="cameras").T_camera_lidar_in_log)
    with pytest.raises(ConfigError):
        build_rig(2, 1.9, 2.0, 0.1, seed=0, drift="camera")


def test_wide_angle_pixels_beyond_the_lens_models_region_see_nothing() -> None:
    """The wide-angle lens's model folds 50 deg off axis, inside the image's corners: those pixels have no
    ray (black), every pixel within the region's image has one, and its ray projects back onto it."""
    from fleetcal.workflows.simulator.camera import wide_angle_camera

    model = wide_angle_camera(160, 90)
    rays, ok = SimCamera(model).rays()
    v, u = np.mgrid[0:90, 0:160]
    d = np.hypot(u.ravel() - model.cx, v.ravel() - model.cy) / model.fx
    f_edge = float(model._radial_map(np.array([model.max_undistorted_radius]))[0][0])
    assert not np.any(ok[d > 1.01 * f_edge]) and np.any(d > 1.01 * f_edge)
    assert np.all(ok[d < 0.99 * f_edge])
    uv, valid = model.project(rays[ok])
    assert np.all(valid)
    np.testing.assert_allclose(uv, np.stack([u.ravel(), v.ravel()], axis=1)[ok], atol=0.01)
