"""The numba kd-tree, the fused correspondence search + linearisation, the hashed voxel sums and the
incremental local map, each against a plain NumPy reference (brute-force distances, np.unique)."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.transforms import exp_se3, from_xyz_rpy
from fleetcal.stages.registration import LocalMap, RegistrationConfig, prepare_pointset
from fleetcal.stages.registration.covariance_kernels import moved_rows_kernel
from fleetcal.stages.registration.gicp_kernels import (
    ROBUST_CAUCHY,
    fitness_kernel,
    linearize_kernel,
    match_linearize_kernel,
)
from fleetcal.stages.registration.kdtree import KdTree
from fleetcal.stages.registration.kdtree_kernels import MAX_DEPTH, nearest_two
from fleetcal.stages.registration.pointset import merge_pointsets, transformed_pointset
from fleetcal.stages.registration.voxel import VoxelSums
from fleetcal.stages.registration.voxel_kernels import group_kernel
from tests.test_registration import room_scene


def brute_d2(queries: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray[np.float64]:
    """(Q, N) squared distances."""
    return np.asarray(((queries[:, None, :] - points[None, :, :]) ** 2).sum(axis=2))


def clouds() -> list[NDArray[np.float64]]:
    """Random, clustered, planar, gridded (many ties), duplicated and one-point clouds, 3-D and 5-D."""
    rng = np.random.default_rng(40)
    grid = np.stack(np.meshgrid(*[np.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.25
    plane = np.column_stack([rng.uniform(-5, 5, (700, 2)), np.zeros(700)])
    return [
        rng.normal(0, 3, (900, 3)),
        np.concatenate([rng.normal(c, 0.05, (150, 3)) for c in rng.uniform(-10, 10, (5, 3))]),
        plane,
        grid,
        np.repeat(rng.normal(0, 1, (40, 3)), 7, axis=0),
        rng.normal(0, 1, (1, 3)),
        rng.normal(0, 2, (600, 5)),
    ]


@pytest.mark.parametrize("leaf_size", [1, 4, 16])
def test_build_partitions_points_by_splits_and_cells(leaf_size: int) -> None:
    for points in clouds():
        tree = KdTree(points, leaf_size)
        tree_points, order, leaf_of, info, split, cell = tree.arrays
        assert np.array_equal(np.sort(order), np.arange(points.shape[0]))
        np.testing.assert_array_equal(tree_points, points[order])
        np.testing.assert_array_equal(tree.points, points)
        for node in range(info.shape[0]):
            dim, left, lo, hi, _ = info[node]
            inside = tree_points[lo:hi]
            assert np.all(inside >= cell[node, 0]) and np.all(inside <= cell[node, 1])
            if dim < 0:
                assert np.all(leaf_of[lo:hi] == node)
                assert hi - lo <= leaf_size or np.all(inside == inside[0])
                continue
            assert info[left, 4] == node and info[left + 1, 4] == node
            assert info[left, 2] == lo and info[left, 3] == info[left + 1, 2] and info[left + 1, 3] == hi
            assert np.all(tree_points[lo : info[left, 3], dim] <= split[node])
            assert np.all(tree_points[info[left, 3] : hi, dim] >= split[node])


def test_build_stops_splitting_at_the_stack_depth() -> None:
    points = np.zeros((400, 3))
    points[:, 0] = 2.0 ** -np.arange(400.0)  # each split at the middle separates one point
    tree = KdTree(points, 1)
    info = tree.arrays[3]
    depth = np.zeros(info.shape[0], dtype=np.int64)
    for node in range(1, info.shape[0]):
        depth[node] = depth[info[node, 4]] + 1
    assert depth.max() <= MAX_DEPTH - 1
    dist, index = tree.nearest(points[-5:])
    assert np.all(dist == 0.0) and np.all(np.abs(points[index] - points[-5:]) == 0.0)


@pytest.mark.parametrize("max_distance", [np.inf, 0.3])
def test_nearest_matches_brute_force(max_distance: float) -> None:
    rng = np.random.default_rng(41)
    for points in clouds():
        queries = points[rng.integers(0, points.shape[0], 200)] + rng.normal(0, 0.3, (200, points.shape[1]))
        dist, index = KdTree(points).nearest(queries, max_distance)
        d2 = brute_d2(queries, points)
        best = d2.min(axis=1)
        found = best < max_distance**2
        np.testing.assert_array_equal(index >= 0, found)
        np.testing.assert_allclose(dist[found] ** 2, best[found], rtol=1e-12, atol=1e-15)
        assert np.all(np.isinf(dist[~found]))
        np.testing.assert_allclose(d2[np.flatnonzero(found), index[found]], best[found], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("k", [1, 3, 20])
def test_knn_and_self_knn_match_brute_force(k: int) -> None:
    rng = np.random.default_rng(42)
    for points in clouds():
        if points.shape[0] < k:
            continue
        tree = KdTree(points, 4)
        queries = points[rng.integers(0, points.shape[0], 150)] + rng.normal(0, 0.2, (150, points.shape[1]))
        dist, index = tree.knn(queries, k, workers=2)
        want = np.sort(brute_d2(queries, points), axis=1)[:, :k]
        np.testing.assert_allclose(dist**2, want, rtol=1e-12, atol=1e-15)
        assert np.all(np.diff(dist, axis=1) >= 0)
        got = brute_d2(queries, points)[np.arange(150)[:, None], index]
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
        neighbours = tree.self_knn(k)
        all_d2 = brute_d2(points, points)
        mine = np.sort(np.take_along_axis(all_d2, neighbours, axis=1), axis=1)
        np.testing.assert_allclose(mine, np.sort(all_d2, axis=1)[:, :k], rtol=1e-12, atol=1e-15)
        assert all(len(set(row)) == k for row in neighbours)


def test_kdtree_rejects_bad_input() -> None:
    with pytest.raises(InputError, match="NaN"):
        KdTree(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(InputError, match=r"\(N >= 1"):
        KdTree(np.zeros((0, 3)))
    tree = KdTree(np.zeros((5, 3)))
    with pytest.raises(InputError, match="k must be"):
        tree.knn(np.zeros((1, 3)), 6)
    with pytest.raises(InputError, match="queries must be"):
        tree.nearest(np.zeros((2, 2)))


def test_nearest_two_from_any_start_matches_brute_force() -> None:
    rng = np.random.default_rng(43)
    for points in clouds():
        if points.shape[0] < 2:
            continue
        tree = KdTree(points, 4)
        tree_points, _, leaf_of, info, split, cell = tree.arrays
        dims = points.shape[1]
        stacks = (np.empty(MAX_DEPTH, np.int64), np.empty(MAX_DEPTH), np.empty((MAX_DEPTH, dims)), np.empty(dims))
        for _ in range(100):
            query = tree_points[rng.integers(tree.n)] + rng.normal(0, 0.4, dims)
            d2 = np.sort(brute_d2(query[None], tree_points)[0])
            max_d2 = float(rng.choice([np.inf, 0.5]))
            starts = [(-1, -1), tuple(rng.integers(-1, tree.n, 2))]
            for candidate, other in starts:
                if candidate < 0 or candidate == other:
                    candidate, other = -1, -1
                best, best_d2, runner_up, second_d2 = nearest_two(
                    tree_points, leaf_of, info, split, cell, query, max_d2, candidate, other, *stacks
                )
                want1 = d2[0] if d2[0] < max_d2 else max_d2
                want2 = d2[1] if d2[1] < max_d2 else max_d2
                assert best_d2 == pytest.approx(want1, rel=1e-12, abs=1e-15)
                assert second_d2 == pytest.approx(want2, rel=1e-12, abs=1e-15)
                assert (best >= 0) == (d2[0] < max_d2) and (runner_up >= 0) == (d2[1] < max_d2)
                assert best != runner_up or best < 0


def match_linearize_state(n: int, dims: int) -> list[NDArray[np.generic]]:
    """searched_at, nearest, second, margin, correspondences: fresh."""
    return [np.zeros((n, dims)), np.full(n, -1, np.int64), np.full(n, -1, np.int64), np.full(n, -1.0),
            np.empty(n, np.int64)]  # fmt: skip


@pytest.mark.parametrize("n_features", [0, 1])
def test_match_linearize_equals_brute_force_correspondences_over_iterations(n_features: int) -> None:
    """Over a sequence of poses moving by shrinking steps (as Gauss-Newton's), the kept-and-searched
    correspondences are the brute-force nearest ones and H, g, cost those of ``linearize_kernel``."""
    rng = np.random.default_rng(44)
    config = RegistrationConfig(voxel_size_m=0.1)
    target = prepare_pointset(room_scene(rng, 5000), None, config)
    source = prepare_pointset(room_scene(rng, 4000), None, config)
    tgt_features = rng.normal(0, 0.2, (target.n_points, n_features))
    src_features = rng.normal(0, 0.2, (source.n_points, n_features))
    tree = KdTree(np.concatenate([target.points_xyz, tgt_features], axis=1), 8)
    state = match_linearize_state(source.n_points, 3 + n_features)
    T = from_xyz_rpy(0.05, -0.03, 0.02, 1.0, -0.5, 2.0)
    max_d2 = 0.3**2
    for step in [0.0, 0.2, 0.02, 0.004, 0.0005, 0.0]:
        T = T @ exp_se3(rng.normal(0, step, 6))
        H, g, cost, used = match_linearize_kernel(
            *tree.arrays, source.points_xyz, src_features, source.covariances, target.points_xyz,
            target.covariances, T, max_d2, ROBUST_CAUCHY, 1.0, 8, *state,
        )  # fmt: skip
        moved = np.concatenate([source.points_xyz @ T[:3, :3].T + T[:3, 3], src_features], axis=1)
        d2 = brute_d2(moved, np.concatenate([target.points_xyz, tgt_features], axis=1))
        want = np.where(d2.min(axis=1) < max_d2, d2.argmin(axis=1), -1)
        corr = state[4]
        np.testing.assert_array_equal(corr, want)
        H_ref, g_ref, cost_ref, used_ref = linearize_kernel(
            source.points_xyz, source.covariances, target.points_xyz, target.covariances, want, T, ROBUST_CAUCHY,
            1.0, 8,
        )  # fmt: skip
        assert used == used_ref
        np.testing.assert_allclose(H, H_ref, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-9)
        assert cost == pytest.approx(cost_ref, rel=1e-12)


def test_fitness_kernel_matches_numpy() -> None:
    rng = np.random.default_rng(45)
    src, tgt = rng.normal(0, 1, (300, 3)), rng.normal(0, 1, (200, 3))
    corr = rng.integers(-1, 200, 300)
    T = from_xyz_rpy(0.1, 0.0, -0.2, 5, 0, 10)
    inliers, total = fitness_kernel(src, tgt, corr, T, 0.8)
    ok = corr >= 0
    d2 = (((src[ok] @ T[:3, :3].T + T[:3, 3]) - tgt[corr[ok]]) ** 2).sum(axis=1)
    assert inliers == np.count_nonzero(d2 <= 0.8)
    assert total == pytest.approx(d2[d2 <= 0.8].sum(), rel=1e-12)


def test_moved_rows_match_transformed_pointset() -> None:
    rng = np.random.default_rng(46)
    scan = prepare_pointset(room_scene(rng, 3000), None, RegistrationConfig(voxel_size_m=0.1))
    T = from_xyz_rpy(1.0, -2.0, 0.5, 10, -20, 30)
    rows = np.empty((scan.n_points, 12))
    moved_rows_kernel(scan.points_xyz, scan.covariances, T, rows[:, :3], rows[:, 3:])
    moved = transformed_pointset(scan, T)
    np.testing.assert_allclose(rows[:, :3], moved.points_xyz, atol=1e-12)
    np.testing.assert_allclose(rows[:, 3:].reshape(-1, 3, 3), moved.covariances, atol=1e-12)


def test_group_kernel_numbers_keys_like_unique() -> None:
    rng = np.random.default_rng(47)
    for keys in [rng.integers(-1, 50, 1000), rng.integers(0, 1 << 62, 300_000), np.full(10, -1), np.zeros(0, int)]:
        keys = keys.astype(np.int64)
        group = np.empty(keys.shape[0], dtype=np.int64)
        distinct, complete = group_kernel(keys, group, -1)
        assert complete
        valid = keys >= 0
        assert np.array_equal(np.sort(distinct), np.unique(keys[valid]))
        np.testing.assert_array_equal(distinct[group[valid]], keys[valid])
        assert np.all(group[~valid] == -1)
        first = [int(np.flatnonzero(keys == key)[0]) for key in distinct[:50]]
        assert first == sorted(first)  # numbered in order of first appearance
        if distinct.shape[0]:
            capped, complete = group_kernel(keys, group, distinct.shape[0] - 1)
            assert not complete and np.array_equal(capped, distinct[:-1])


def test_voxel_sums_add_remove_and_compact_equal_a_fresh_sum() -> None:
    rng = np.random.default_rng(48)
    sums = VoxelSums(2)
    window: list[tuple[NDArray[np.int64], NDArray[np.float64]]] = []
    for _ in range(60):
        keys = rng.integers(0, 3000, 500).astype(np.int64) + len(window) * 40  # the keys drift: voxels empty
        values = rng.normal(0, 1, (500, 2))
        sums.add(keys, values)
        window.append((keys, values))
        if len(window) > 5:
            sums.remove(*window.pop(0))
    every_key = np.concatenate([k for k, _ in window])
    every_value = np.concatenate([v for _, v in window])
    unique, inverse = np.unique(every_key, return_inverse=True)
    want = np.stack([np.bincount(inverse, weights=every_value[:, c]) for c in range(2)], 1)
    want /= np.bincount(inverse)[:, None]
    keys, means = sums.means()
    order = np.argsort(keys)
    np.testing.assert_array_equal(keys[order], unique)
    np.testing.assert_allclose(means[order], want, atol=1e-9)
    assert sums.n_occupied == unique.shape[0]
    assert sums._n_groups < 2 * unique.shape[0] + 3000  # emptied voxels were compacted away


def test_local_map_target_is_the_merged_window() -> None:
    rng = np.random.default_rng(49)
    config = RegistrationConfig(method="mcgicp", channels="intensity", voxel_size_m=0.2)
    world = room_scene(rng, 6000)
    local_map = LocalMap(config, 3)
    scans, poses = [], []
    for k in range(5):
        T = from_xyz_rpy(0.2 * k, 0.05 * k, 0.0, 0.0, 0.0, 3.0 * k)
        points = (world - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.005, world.shape)
        scan = prepare_pointset(points, {"intensity": world[:, 0] + rng.normal(0, 0.1, 6000)}, config)
        local_map.add(scan, T)
        scans.append(scan)
        poses.append(T)
    target = local_map.target()
    want = merge_pointsets([transformed_pointset(s, T) for s, T in zip(scans[-3:], poses[-3:], strict=True)], config)

    def rows(ps: object) -> NDArray[np.float64]:
        out = np.concatenate([ps.points_xyz, ps.channels, ps.covariances.reshape(-1, 9)], 1)  # type: ignore[attr-defined]
        return out[np.lexsort(out[:, 2::-1].T)]

    np.testing.assert_allclose(rows(target), rows(want), atol=1e-9)
    np.testing.assert_allclose(target.channel_variance, want.channel_variance, rtol=1e-9)
    assert local_map.n_keyframes == 3 and target.frame_id == "map"
    with pytest.raises(InputError, match="different channels"):
        local_map.add(prepare_pointset(world, None, RegistrationConfig(voxel_size_m=0.2)), np.eye(4))


def test_voxel_keys_match_the_numpy_packing() -> None:
    from fleetcal.stages.registration.voxel import voxel_keys

    rng = np.random.default_rng(50)
    points = rng.uniform(-300, 300, (5000, 3)).astype(np.float32)
    valid = rng.random(5000) > 0.1
    points[~valid] = np.nan
    cells = np.floor(points[valid].astype(np.float64) / 0.3).astype(np.int64) + (1 << 20)
    want = (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]
    keys = voxel_keys(points, 0.3, valid)
    np.testing.assert_array_equal(keys[valid], want)
    assert np.all(keys[~valid] == -1)
    with pytest.raises(InputError, match="span more than"):
        voxel_keys(points, 0.3)  # NaN outside a mask
    with pytest.raises(InputError, match="span more than"):
        voxel_keys(np.array([[0.0, 0.0, 2.0e6]]), 1.0)


def test_threaded_registration_agrees_with_serial() -> None:
    """Cut into slices on two threads, the search and the sums give the serial pose (to rounding)."""
    from fleetcal.stages.registration import register

    rng = np.random.default_rng(51)
    world = room_scene(rng, 30000)
    T_true = from_xyz_rpy(0.08, -0.05, 0.02, 1.0, -0.5, 3.0)
    results = []
    for workers in (1, 2):
        config = RegistrationConfig(voxel_size_m=0.05, workers=workers)
        target = prepare_pointset(world, None, config)
        source = prepare_pointset((world - T_true[:3, 3]) @ T_true[:3, :3], None, config)
        assert source.n_points >= 8192  # two slices of the source
        results.append(register(source, target, np.eye(4), config))
    serial, threaded = results
    assert serial.iterations == threaded.iterations and serial.n_correspondences == threaded.n_correspondences
    np.testing.assert_allclose(threaded.T_target_source, serial.T_target_source, atol=1e-9)
    assert threaded.fitness == serial.fitness
