"""Transforms and the tf tree: round trips, composition, interpolation, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.errors import TransformError
from fleetcal.pipeline.transforms import (
    TransformTree,
    apply,
    exp_se3,
    from_quat,
    from_xyz_rpy,
    invert,
    is_rigid,
    rotation_error_deg,
    rotvec_matrix,
    screw_apply,
    to_quat,
    to_rpy_deg,
    translation_error_m,
    twist_of,
)


def _random_T(rng: np.random.Generator) -> np.ndarray:
    return exp_se3(np.concatenate([rng.normal(size=3), rng.normal(size=3) * 3]))


def test_invert_and_apply_round_trip() -> None:
    rng = np.random.default_rng(0)
    T = _random_T(rng)
    pts = rng.normal(size=(50, 3))
    back = apply(invert(T), apply(T, pts))
    assert np.abs(back - pts).max() < 1e-12
    assert np.allclose(T @ invert(T), np.eye(4), atol=1e-12)


def test_quaternion_round_trip_scalar_last() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        T = _random_T(rng)
        t, q = to_quat(T)
        assert q[3] >= 0
        assert np.allclose(from_quat(t, q), T, atol=1e-12)
    # 90 deg about z, scalar-last
    T = from_quat([1, 2, 3], [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    assert np.allclose(apply(T, np.array([[1.0, 0, 0]])), [[1, 3, 3]])


def test_rotation_vectors_and_quaternions_match_scipy() -> None:
    """The NumPy conversions (Rodrigues, Shepperd) against SciPy's Rotation, from tiny angles to half
    turns about each axis."""
    rng = np.random.default_rng(7)
    scales = rng.choice([1e-12, 1e-9, 1e-6, 1e-3, 1.0, 3.0], size=(300, 1))
    rotvecs = [*(rng.normal(size=(300, 3)) * scales), *(np.pi * np.eye(3)), np.zeros(3)]
    for rotvec in rotvecs:
        R = Rotation.from_rotvec(rotvec).as_matrix()
        np.testing.assert_allclose(rotvec_matrix(rotvec), R, atol=1e-14)
        T = np.eye(4)
        T[:3, :3] = R
        want = Rotation.from_matrix(R).as_quat()
        want = -want if want[3] < 0 else want
        got = to_quat(T)[1]
        assert got[3] >= 0
        assert np.allclose(got, want, atol=1e-14) or (abs(want[3]) < 1e-12 and np.allclose(got, -want, atol=1e-14))
        np.testing.assert_allclose(from_quat([0.0, 0.0, 0.0], want)[:3, :3], R, atol=1e-14)


def test_euler_convention_is_xyz_extrinsic_degrees() -> None:
    T = from_xyz_rpy(0.1, 0.2, 0.3, 10, 20, 30)
    R_expected = (
        Rotation.from_euler("z", 30, degrees=True)
        * Rotation.from_euler("y", 20, degrees=True)
        * Rotation.from_euler("x", 10, degrees=True)
    ).as_matrix()
    assert np.allclose(T[:3, :3], R_expected)
    assert np.allclose(to_rpy_deg(T), [10, 20, 30])


def test_errors_between_transforms() -> None:
    A = from_xyz_rpy(0, 0, 0, 0, 0, 0)
    B = from_xyz_rpy(0.03, 0.04, 0, 0, 0, 1.5)
    assert rotation_error_deg(A, B) == pytest.approx(1.5)
    assert translation_error_m(A, B) == pytest.approx(0.05)


@pytest.mark.parametrize(
    ("t", "q"),
    [([0, 0, 0], [0, 0, 0, 0]), ([np.nan, 0, 0], [0, 0, 0, 1]), ([0, 0, 0], [np.nan, 0, 0, 1])],
)
def test_from_quat_rejects_bad_values(t: list[float], q: list[float]) -> None:
    with pytest.raises(TransformError):
        from_quat(t, q)


def test_is_rigid() -> None:
    assert is_rigid(from_xyz_rpy(1, 2, 3, 4, 5, 6))
    S = np.eye(4)
    S[0, 0] = 2
    assert not is_rigid(S)
    M = np.eye(4)
    M[0, 0] = -1
    assert not is_rigid(M)


def test_tree_lookup_composes_through_common_parent() -> None:
    tree = TransformTree()
    T_base_lidar = from_xyz_rpy(1.0, 0, 1.8, 0, 0, 2)
    T_base_cam = from_xyz_rpy(1.5, 0.2, 1.5, -90, 0, -90)
    tree.add("base_link", "lidar", T_base_lidar, 0, static=True)
    tree.add("/base_link", "cam_optical", T_base_cam, 0, static=True)
    T_cam_lidar = tree.lookup("cam_optical", "lidar")
    assert np.allclose(T_cam_lidar, invert(T_base_cam) @ T_base_lidar, atol=1e-12)
    assert np.allclose(tree.lookup("lidar", "cam_optical"), invert(T_cam_lidar), atol=1e-12)
    assert tree.is_static_path("cam_optical", "lidar")
    assert np.allclose(tree.lookup("lidar", "lidar"), np.eye(4))


def test_tree_interpolates_dynamic_edges() -> None:
    tree = TransformTree(tolerance_ns=10_000_000)
    tree.add("odom", "base", from_xyz_rpy(0, 0, 0, 0, 0, 0), 1_000_000_000, static=False)
    tree.add("odom", "base", from_xyz_rpy(2, 0, 0, 0, 0, 20), 2_000_000_000, static=False)
    mid = tree.lookup("odom", "base", 1_500_000_000)
    assert np.allclose(mid[:3, 3], [1, 0, 0])
    assert to_rpy_deg(mid)[2] == pytest.approx(10)
    assert np.allclose(tree.lookup("odom", "base", 2_005_000_000)[:3, 3], [2, 0, 0])
    with pytest.raises(TransformError, match="no transform within"):
        tree.lookup("odom", "base", 3_000_000_000)
    tree.add("base", "lidar", np.eye(4), 0, static=True)
    tree.add("base", "arm", np.eye(4), 1_200_000_000, static=False)
    tree.add("base", "arm", np.eye(4), 2_500_000_000, static=False)
    assert tree.recorded_span("odom", "lidar") == (1_000_000_000, 2_000_000_000)
    assert tree.recorded_span("odom", "arm") == (1_200_000_000, 2_000_000_000)  # where both edges were recorded
    assert tree.recorded_span("base", "lidar") is None  # static only


def test_tree_missing_path_and_bad_edges() -> None:
    tree = TransformTree()
    tree.add("a", "b", np.eye(4), 0, static=True)
    tree.add("c", "d", np.eye(4), 0, static=True)
    assert not tree.can_lookup("a", "d")
    with pytest.raises(TransformError, match="no tf path"):
        tree.lookup("a", "d")
    with pytest.raises(TransformError, match="itself"):
        tree.add("a", "a", np.eye(4), 0, static=True)
    bad = np.eye(4)
    bad[:3, :3] *= 2
    with pytest.raises(TransformError, match="not a rigid"):
        tree.add("a", "x", bad, 0, static=True)
    assert {(p, c) for p, c, _ in tree.edges()} == {("a", "b"), ("c", "d")}


def test_twist_of_and_screw_apply_round_trip() -> None:
    """The constant twist of a motion, applied over the same duration, is that motion; over half of it,
    twice gives the motion again; its first order is ``p + (v + w x p) dt``."""
    rng = np.random.default_rng(4)
    T = exp_se3(np.concatenate([rng.normal(size=3) * 0.4, rng.normal(size=3) * 2.0]))
    points = rng.normal(size=(50, 3)) * 20
    twist = twist_of(T, 0.1)
    np.testing.assert_allclose(screw_apply(twist, np.full(50, 0.1), points), apply(T, points), atol=1e-9)
    half = screw_apply(twist, np.full(50, 0.05), points)
    np.testing.assert_allclose(screw_apply(twist, np.full(50, 0.05), half), apply(T, points), atol=1e-9)
    dt = np.full(50, 1e-6)
    first_order = points + (twist[:3] + np.cross(twist[3:], points)) * 1e-6
    np.testing.assert_allclose(screw_apply(twist, dt, points), first_order, atol=1e-9)
    np.testing.assert_allclose(screw_apply(twist, np.zeros(50), points), points, atol=1e-12)
