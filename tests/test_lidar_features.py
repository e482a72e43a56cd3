"""Lidar feature stage: kernels vs NumPy references, plane ground truth, equalisation, edge cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.stages import lidar_feature_kernels
from fleetcal.stages.lidar_features import (
    GridSearchParams,
    compute_lidar_feature,
    equalize_rank,
    grid_neighbours,
    lidar_frame_feature,
    normal_ray_angles,
)


def reference_normal_angles(points: np.ndarray, k: int, sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force kNN + np.linalg.eigh of the covariance centred at the point (GOM eq. 4)."""
    n = len(points)
    normals = np.full((n, 3), np.nan)
    angles = np.full(n, np.nan)
    for i in range(n):
        d2 = np.sum((points - points[i]) ** 2, axis=1)
        d2[i] = np.inf
        nbr = np.argsort(d2, kind="stable")[:k]
        diff = points[nbr] - points[i]
        cov = diff.T @ diff / len(nbr)
        _, vecs = np.linalg.eigh(cov)
        normals[i] = vecs[:, 0]
        ray = points[i] - sensor
        angles[i] = np.arccos(min(1.0, abs(vecs[:, 0] @ ray) / np.linalg.norm(ray)))
    return normals, angles


def reference_equalize(values: np.ndarray) -> np.ndarray:
    """Empirical CDF with averaged ties by counting: (#less + (#equal - 1) / 2) / (n - 1)."""
    out = np.full(values.shape, np.nan)
    finite = values[np.isfinite(values)]
    n = finite.size
    for i, v in enumerate(values):
        if not np.isfinite(v):
            continue
        if n == 1:
            out[i] = 0.5
            continue
        less = np.sum(finite < v)
        equal = np.sum(finite == v)
        out[i] = (less + (equal - 1) / 2) / (n - 1)
    return out


def _random_symmetric(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(3, 3))
    return a @ a.T


def test_eigenvector_kernel_matches_eigh_on_random_matrices() -> None:
    rng = np.random.default_rng(0)
    out = np.empty(3)
    for _ in range(500):
        cov = _random_symmetric(rng) * 10.0 ** rng.uniform(-6, 3)
        vals, vecs = np.linalg.eigh(cov)
        ok = lidar_feature_kernels.smallest_eigenvector_sym3(
            cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2], out
        )
        if vals[1] - vals[0] < 1e-6 * (vals[2] - vals[0]):
            continue
        assert ok
        assert abs(abs(out @ vecs[:, 0]) - 1.0) < 1e-7
        assert np.linalg.norm(cov @ out - vals[0] * out) < 1e-7 * vals[2]


@pytest.mark.parametrize(
    "cov, expected",
    [
        (np.diag([3.0, 1.0, 2.0]), np.array([0.0, 1.0, 0.0])),
        (np.diag([0.0, 5.0, 4.0]), np.array([1.0, 0.0, 0.0])),
        (
            np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 3.0]]),
            np.array([1.0, -1.0, 0.0]) / np.sqrt(2),
        ),
    ],
)
def test_eigenvector_kernel_edge_matrices(cov: np.ndarray, expected: np.ndarray) -> None:
    out = np.empty(3)
    assert lidar_feature_kernels.smallest_eigenvector_sym3(
        cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2], out
    )
    assert abs(abs(out @ expected) - 1.0) < 1e-9


@pytest.mark.parametrize(
    "cov",
    [
        np.zeros((3, 3)),
        np.eye(3),
        np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]),
        np.full((3, 3), np.nan),
    ],
    ids=["zero", "isotropic", "rank1-line", "nan"],
)
def test_eigenvector_kernel_undefined_normal(cov: np.ndarray) -> None:
    out = np.zeros(3)
    ok = lidar_feature_kernels.smallest_eigenvector_sym3(
        cov[0, 0], cov[0, 1], cov[0, 2], cov[1, 1], cov[1, 2], cov[2, 2], out
    )
    assert not ok and np.isnan(out).all()


@pytest.mark.parametrize("n, k", [(3, 8), (9, 8), (300, 8), (200, 5)])
def test_normals_match_bruteforce_reference(n: int, k: int) -> None:
    rng = np.random.default_rng(n + k)
    points = rng.normal(size=(n, 3)) * [10.0, 10.0, 2.0] + [5.0, 0.0, 0.0]
    sensor = np.array([0.5, -0.2, 0.3])
    normals, angles = normal_ray_angles(points, k=k, sensor_xyz=sensor)
    ref_normals, ref_angles = reference_normal_angles(points, min(k, n - 1), sensor)
    np.testing.assert_allclose(angles, ref_angles, atol=1e-7)
    dots = np.abs(np.sum(normals * ref_normals, axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-7)


def test_kernel_skips_self_and_missing_indices() -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(20, 3))
    sensor = np.zeros(3)
    _, ref_angles = reference_normal_angles(pts, 4, sensor)
    d2 = ((pts[:, None, :] - pts[None, :, :]) ** 2).sum(-1)
    order = np.argsort(d2, axis=1, kind="stable")[:, :5]
    padded = np.concatenate([np.full((20, 1), 20), order, np.full((20, 2), -1)], axis=1)
    normals = np.empty((20, 3))
    angles = np.empty(20)
    lidar_feature_kernels.normal_ray_angles(pts, padded.astype(np.int64), 4, sensor, normals, angles)
    np.testing.assert_allclose(angles, ref_angles, atol=1e-9)


def test_plane_normals_give_true_incidence_angles() -> None:
    xs, ys = np.meshgrid(np.arange(2.0, 20.0, 0.25), np.arange(-8.0, 8.0, 0.25))
    ground = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, -1.7)], axis=1)
    zs, ys2 = np.meshgrid(np.arange(-1.5, 3.0, 0.2), np.arange(-8.0, 8.0, 0.2))
    wall = np.stack([np.full(zs.size, 25.0), ys2.ravel(), zs.ravel()], axis=1)
    points = np.concatenate([ground, wall])
    normals, angles = normal_ray_angles(points, k=8)
    r = np.linalg.norm(points, axis=1)
    truth_ground = np.arccos(1.7 / r[: len(ground)])
    truth_wall = np.arccos(25.0 / r[len(ground) :])
    interior_ground = (np.abs(ground[:, 1]) < 7.5) & (ground[:, 0] > 2.5) & (ground[:, 0] < 19.5)
    np.testing.assert_allclose(
        angles[: len(ground)][interior_ground], truth_ground[interior_ground], atol=1e-9
    )
    interior_wall = (np.abs(wall[:, 1]) < 7.5) & (wall[:, 2] > -1.3) & (wall[:, 2] < 2.8)
    np.testing.assert_allclose(angles[len(ground) :][interior_wall], truth_wall[interior_wall], atol=1e-9)
    assert np.allclose(np.abs(normals[: len(ground)][interior_ground, 2]), 1.0)


def test_collinear_points_have_no_normal() -> None:
    line = np.stack([np.linspace(1, 10, 30), np.zeros(30), np.zeros(30)], axis=1)
    normals, angles = normal_ray_angles(line)
    assert np.isnan(angles).all() and np.isnan(normals).all()
    assert np.isnan(compute_lidar_feature(line, "normals")).all()


@pytest.mark.parametrize(
    "values",
    [
        np.array([3.0, 1.0, 2.0, 2.0, 5.0, 1.0]),
        np.random.default_rng(1).integers(0, 10, 200).astype(float),
        np.random.default_rng(2).normal(size=100),
        np.array([4.0, np.nan, 1.0, np.inf, 2.0]),
        np.full(7, 3.3),
        np.array([42.0]),
        np.array([]),
        np.array([np.nan, np.nan]),
    ],
    ids=["ties", "integers", "normal", "nan-inf", "constant", "one", "empty", "all-nan"],
)
def test_equalize_rank_matches_reference(values: np.ndarray) -> None:
    out = equalize_rank(values)
    ref = reference_equalize(values)
    assert out.dtype == np.float32 and out.shape == values.shape
    np.testing.assert_allclose(out, ref, atol=1e-6)
    finite = out[np.isfinite(out)]
    assert np.all((finite >= 0) & (finite <= 1))


def test_range_and_intensity_features_preserve_order() -> None:
    rng = np.random.default_rng(4)
    points = rng.normal(size=(500, 3)) * 20
    intensity = rng.integers(0, 256, 500).astype(np.uint8)
    rng_feature = compute_lidar_feature(points, "range")
    r = np.linalg.norm(points, axis=1)
    assert np.all(np.diff(rng_feature[np.argsort(r)]) > 0)
    assert rng_feature.min() == 0.0 and rng_feature.max() == 1.0
    shifted = compute_lidar_feature(points, "range", sensor_xyz=(1.0, 2.0, 3.0))
    np.testing.assert_allclose(
        shifted, reference_equalize(np.linalg.norm(points - [1, 2, 3], axis=1)), atol=1e-6
    )
    inten = compute_lidar_feature(points, "intensity", intensity=intensity)
    np.testing.assert_allclose(inten, reference_equalize(intensity.astype(float)), atol=1e-6)


@pytest.mark.parametrize("kind", ["intensity", "range", "normals"])
def test_empty_and_single_point_clouds(kind: str) -> None:
    empty = compute_lidar_feature(np.zeros((0, 3), np.float32), kind, intensity=np.zeros(0))  # type: ignore[arg-type]
    assert empty.shape == (0,) and empty.dtype == np.float32
    one = compute_lidar_feature(np.array([[1.0, 2.0, 3.0]]), kind, intensity=np.array([7.0]))  # type: ignore[arg-type]
    assert one.shape == (1,)
    if kind == "normals":
        assert np.isnan(one[0])
    else:
        assert one[0] == 0.5


@pytest.mark.parametrize("kind", ["intensity", "range", "normals"])
def test_nan_points_are_flagged_and_do_not_disturb_the_rest(kind: str) -> None:
    rng = np.random.default_rng(6)
    points = rng.normal(size=(200, 3)) * 5
    intensity = rng.random(200)
    bad = np.zeros(200, bool)
    bad[[3, 50, 199]] = True
    dirty = points.copy()
    dirty[3] = np.nan
    dirty[50, 1] = np.inf
    dirty[199, 2] = np.nan
    with_nan = compute_lidar_feature(dirty, kind, intensity=intensity)  # type: ignore[arg-type]
    clean = compute_lidar_feature(points[~bad], kind, intensity=intensity[~bad])  # type: ignore[arg-type]
    assert np.isnan(with_nan[bad]).all()
    np.testing.assert_allclose(with_nan[~bad], clean, atol=1e-6)


def test_duplicate_points_do_not_crash() -> None:
    rng = np.random.default_rng(8)
    base = rng.normal(size=(50, 3))
    points = np.concatenate([base, base, base[:5]])
    feature = compute_lidar_feature(points, "normals")
    assert feature.shape == (105,)
    finite = feature[np.isfinite(feature)]
    assert finite.size > 50 and np.all((finite >= 0) & (finite <= 1))


@pytest.mark.parametrize(
    "points, kind, kwargs, match",
    [
        (np.zeros((5, 2)), "range", {}, "shape"),
        (np.zeros(3), "range", {}, "shape"),
        (np.array([["a", "b", "c"]]), "range", {}, "dtype"),
        (np.zeros((5, 3)), "colour", {}, "unknown lidar feature"),
        (np.zeros((5, 3)), "intensity", {}, "intensity channel"),
        (np.zeros((5, 3)), "intensity", {"intensity": np.zeros(4)}, "intensity must be"),
        (np.zeros((5, 3)), "normals", {"k": 1}, "k must be"),
        (np.zeros((5, 3)), "range", {"sensor_xyz": (0.0, np.nan, 0.0)}, "sensor_xyz"),
    ],
)
def test_bad_inputs_raise_input_error(
    points: np.ndarray, kind: str, kwargs: dict[str, object], match: str
) -> None:
    with pytest.raises(InputError, match=match):
        compute_lidar_feature(points, kind, **kwargs)  # type: ignore[arg-type]


def test_frame_stage_result_and_empty_frame() -> None:
    rng = np.random.default_rng(9)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    frame = LidarFrame(
        stamp_ns=11,
        topic="/lidar",
        frame_id="lidar",
        points_xyz=pts,
        channels={"intensity": rng.random(100).astype(np.float32)},
    )
    result = lidar_frame_feature(frame, kind="intensity")
    assert (result.stamp_ns, result.n_points, result.n_valid, result.kind) == (11, 100, 100, "intensity")
    np.testing.assert_allclose(
        result.feature, compute_lidar_feature(pts, "intensity", frame.channels["intensity"])
    )
    for bad_points in (np.zeros((0, 3), np.float32), np.full((4, 3), np.nan, np.float32)):
        with pytest.raises(InputError, match="no valid points"):
            lidar_frame_feature(LidarFrame(1, "/lidar", "lidar", bad_points))


def test_kitti_ground_normals_are_vertical(shared_data: Path) -> None:
    from fleetcal.readers.frames import iter_lidar_frames
    from fleetcal.readers.open import open_log

    with open_log(shared_data / "logs" / "kitti_2011_09_26.mcap") as reader:
        scan = next(iter_lidar_frames(reader, "/kitti/velo/pointcloud"))
    pts = scan.points_xyz
    normals, _ = normal_ray_angles(pts)
    road = (
        (pts[:, 2] > -1.9)
        & (pts[:, 2] < -1.55)
        & (pts[:, 0] > 5)
        & (pts[:, 0] < 15)
        & (np.abs(pts[:, 1]) < 3)
    )
    assert road.sum() > 3000
    assert np.mean(np.abs(normals[road, 2]) > 0.9) > 0.95
    for kind in ("intensity", "range", "normals"):
        feature = compute_lidar_feature(pts, kind, intensity=scan.channels["intensity"])  # type: ignore[arg-type]
        finite = feature[np.isfinite(feature)]
        assert finite.size > 0.95 * len(pts)
        # ties (e.g. many zero intensities) share their average rank, so the ends need not be 0 and 1
        assert finite.min() < 0.05 and finite.max() > 0.95 and abs(float(np.median(finite)) - 0.5) < 0.05


def test_single_and_multi_threaded_neighbour_queries_agree() -> None:
    points = np.random.default_rng(21).normal(size=(3000, 3)) * [20.0, 20.0, 3.0]
    one = compute_lidar_feature(points, "normals", knn_workers=1)
    many = compute_lidar_feature(points, "normals", knn_workers=-1)
    np.testing.assert_array_equal(one, many)


# ------------------------------------------------- range-image (grid) neighbour search


def ring_scan(rings: int, cols: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A spinning-lidar-like scan: ground plane + walls, ``rings`` lasers x ``cols`` azimuths."""
    az = np.linspace(-np.pi, np.pi, cols, endpoint=False) + rng.uniform(0, 1e-3, cols)
    el = np.radians(np.linspace(-24.8, 2.0, rings))
    a, e = np.meshgrid(az, el)
    walls = 4.0 + 20.0 * np.abs(np.sin(2 * a)) + rng.normal(scale=0.02, size=a.shape)
    ground = np.where(e < 0, 1.73 / np.maximum(-np.sin(e), 1e-3), np.inf)
    r = np.minimum(walls, ground)
    pts = np.stack([r * np.cos(e) * np.cos(a), r * np.cos(e) * np.sin(a), r * np.sin(e)], axis=-1)
    ring = np.broadcast_to(np.arange(rings)[:, None], a.shape)
    return pts.reshape(-1, 3), ring.reshape(-1).astype(np.uint16)


def brute_knn_dist(points: np.ndarray, k: int) -> np.ndarray:
    d2 = np.sum((points[:, None, :] - points[None, :, :]) ** 2, axis=2)
    np.fill_diagonal(d2, np.inf)
    return np.sqrt(np.sort(d2, axis=1)[:, :k])


@pytest.mark.parametrize("use_rings", [True, False])
def test_grid_neighbours_proven_exact_equal_bruteforce(use_rings: bool) -> None:
    pts, ring = ring_scan(16, 180, np.random.default_rng(30))
    found = grid_neighbours(pts, 8, rings=ring if use_rings else None, params=GridSearchParams(elevation_bin_deg=1.0))
    assert found.exact.mean() > 0.6
    got = np.linalg.norm(pts[found.neighbours] - pts[:, None, :], axis=2)
    want = brute_knn_dist(pts, 8)
    np.testing.assert_allclose(got[found.exact], want[found.exact], rtol=0, atol=1e-12)
    assert (found.neighbours != np.arange(len(pts))[:, None]).all()  # never itself


def test_grid_normals_identical_to_kdtree_with_shuffled_ring_ids() -> None:
    rng = np.random.default_rng(31)
    pts, ring = ring_scan(32, 600, rng)
    perm = rng.permutation(32)  # ring ids need not follow elevation (as on several vendors' lidars)
    ring = perm[ring]
    pts[::97] = np.nan
    _, kd = normal_ray_angles(pts, search="kdtree")
    for rings in (ring, None):
        _, grid = normal_ray_angles(pts, search="grid", rings=rings)
        np.testing.assert_array_equal(grid, kd)
    feature = compute_lidar_feature(pts, "normals", rings=ring, search="grid")
    np.testing.assert_array_equal(feature, compute_lidar_feature(pts, "normals"))


def test_grid_search_plane_incidence_angles() -> None:
    # a wall x = 10 seen from the origin: angle between normal (1, 0, 0) and the ray is acos(x / r)
    y, z = np.meshgrid(np.linspace(-5, 5, 60), np.linspace(-2, 2, 30))
    pts = np.stack([np.full(y.size, 10.0), y.ravel(), z.ravel()], axis=1)
    _, angles = normal_ray_angles(pts, search="grid")
    truth = np.arccos(10.0 / np.linalg.norm(pts, axis=1))
    np.testing.assert_allclose(angles, truth, atol=1e-9)


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_grid_search_tiny_clouds(n: int) -> None:
    pts = np.random.default_rng(32).normal(size=(n, 3)) + np.array([5.0, 0.0, 0.0])
    _, grid = normal_ray_angles(pts, search="grid")
    _, kd = normal_ray_angles(pts, search="kdtree")
    np.testing.assert_array_equal(grid, kd)
    found = grid_neighbours(pts, 2)
    assert found.neighbours.shape == (n, 2)
    with pytest.raises(InputError):
        grid_neighbours(np.full((3, 3), np.nan))
    with pytest.raises(InputError):
        normal_ray_angles(pts, search="octree")  # type: ignore[arg-type]


def test_kitti_grid_search_identical_to_kdtree(shared_data: Path) -> None:
    """Real HDL-64 scan (no ring channel: elevation bins): the grid path proves most points exact
    and the rest fall back to the kd-tree, so the angles are identical."""
    from fleetcal.readers.frames import iter_lidar_frames
    from fleetcal.readers.open import open_log

    with open_log(shared_data / "logs" / "kitti_2011_09_26.mcap") as reader:
        scan = next(iter_lidar_frames(reader, "/kitti/velo/pointcloud"))
    pts = np.asarray(scan.points_xyz, dtype=np.float64)
    found = grid_neighbours(pts, 8)
    assert found.exact.mean() > 0.85
    _, kd = normal_ray_angles(pts, search="kdtree")
    _, grid = normal_ray_angles(pts, search="grid")
    np.testing.assert_array_equal(grid, kd)
