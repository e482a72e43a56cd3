"""Rigid transforms (4x4 float64, ``p_a = T_a_b @ p_b``) and the tf tree.

Quaternions are scalar-last ``(qx, qy, qz, qw)`` as in ROS. Euler angles are xyz-extrinsic
(roll about x, then pitch about y, then yaw about z, all about fixed axes), in degrees.

Quaternions and rotation vectors convert in NumPy; SciPy's ``Rotation`` (Euler angles, screw motions,
slerp) is imported by the functions that use it, as importing ``scipy.spatial`` takes a quarter of a
second that ``fleetcal map`` does not otherwise spend.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import TransformError

Mat4 = NDArray[np.float64]


def make_T(rotation: NDArray[np.float64], translation: NDArray[np.float64] | list[float]) -> Mat4:
    """4x4 transform from a 3x3 rotation matrix and a translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def invert(T: Mat4) -> Mat4:
    """Inverse of a rigid transform (``T_b_a`` from ``T_a_b``)."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def apply(T: Mat4, points_xyz: NDArray[np.floating]) -> NDArray[np.float64]:
    """Apply ``T_a_b`` to (N, 3) points in frame b; returns (N, 3) points in frame a."""
    pts = np.asarray(points_xyz, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


def from_quat(translation: NDArray[np.float64] | list[float], quat_xyzw: NDArray[np.float64] | list[float]) -> Mat4:
    """Transform from translation (m) and quaternion (qx, qy, qz, qw); rejects non-finite or zero norm."""
    q = np.asarray(quat_xyzw, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t))):
        raise TransformError("transform has NaN or infinite values")
    norm = float(np.linalg.norm(q))
    if norm < 1e-6:
        raise TransformError("transform has a zero-length quaternion")
    x, y, z, w = q / norm
    R = np.array([
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ])  # fmt: skip
    return make_T(R, t)


def to_quat(T: Mat4) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(translation (3,), quaternion (4,) scalar-last with qw >= 0) of a transform.

    Shepperd's method: the component with the largest magnitude comes from the diagonal, the others
    from sums and differences of the off-diagonal terms divided by it."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    largest = int(np.argmax([trace, R[0, 0], R[1, 1], R[2, 2]]))
    if largest == 0:
        w = 0.5 * np.sqrt(max(1.0 + trace, 0.0))
        q = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 4.0 * w * w]) / (4.0 * w)
    elif largest == 1:
        x = 0.5 * np.sqrt(max(1.0 + R[0, 0] - R[1, 1] - R[2, 2], 0.0))
        q = np.array([4.0 * x * x, R[0, 1] + R[1, 0], R[0, 2] + R[2, 0], R[2, 1] - R[1, 2]]) / (4.0 * x)
    elif largest == 2:
        y = 0.5 * np.sqrt(max(1.0 - R[0, 0] + R[1, 1] - R[2, 2], 0.0))
        q = np.array([R[0, 1] + R[1, 0], 4.0 * y * y, R[1, 2] + R[2, 1], R[0, 2] - R[2, 0]]) / (4.0 * y)
    else:
        z = 0.5 * np.sqrt(max(1.0 - R[0, 0] - R[1, 1] + R[2, 2], 0.0))
        q = np.array([R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], 4.0 * z * z, R[1, 0] - R[0, 1]]) / (4.0 * z)
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return np.asarray(T, dtype=np.float64)[:3, 3].copy(), q


def from_xyz_rpy(x: float, y: float, z: float, roll_deg: float, pitch_deg: float, yaw_deg: float) -> Mat4:
    """Transform from metres and xyz-extrinsic Euler angles in degrees."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [roll_deg, pitch_deg, yaw_deg], degrees=True).as_matrix()
    return make_T(R, [x, y, z])


def to_rpy_deg(T: Mat4) -> NDArray[np.float64]:
    """xyz-extrinsic Euler angles (roll, pitch, yaw) in degrees."""
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_matrix(T[:3, :3]).as_euler("xyz", degrees=True))


def exp_se3(xi: NDArray[np.float64]) -> Mat4:
    """Transform from a 6-vector (rotation vector rad (3), translation m (3)), rotation and translation decoupled."""
    xi = np.asarray(xi, dtype=np.float64)
    return make_T(rotvec_matrix(xi[:3]), xi[3:6])


def rotvec_matrix(rotvec: NDArray[np.float64]) -> NDArray[np.float64]:
    """(3, 3) rotation matrix of a rotation vector (axis times angle, rad): Rodrigues' formula
    R = I + sin(t)/t K + (1 - cos t)/t^2 K^2, K the cross-product matrix, the second coefficient as
    (sin(t/2) / (t/2))^2 / 2 (no cancellation at small angles)."""
    w = np.asarray(rotvec, dtype=np.float64)
    theta = float(np.sqrt(w @ w))
    K = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * (K @ K)
    half = 0.5 * theta
    return np.eye(3) + (np.sin(theta) / theta) * K + 0.5 * (np.sin(half) / half) ** 2 * (K @ K)


def _screw_terms(theta: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(1 - cos t) / t^2`` and ``(t - sin t) / t^3`` of angles t (rad), by their series near 0."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    b = np.where(small, 1.0 / 6.0 - theta**2 / 120.0, (t - np.sin(t)) / t**3)
    return a, b


def screw_apply(twist: NDArray[np.floating], dt_s: NDArray[np.floating],
                points_xyz: NDArray[np.floating]) -> NDArray[np.float64]:
    """``exp(twist * dt_i) @ p_i`` for each point: the SE(3) exponential of a constant body twist
    (vx, vy, vz m/s, wx, wy, wz rad/s) over its own duration dt_i (s), applied to points (N, 3), metres."""
    tw = np.asarray(twist, dtype=np.float64).ravel()
    dt = np.asarray(dt_s, dtype=np.float64).ravel()
    v, w = tw[:3], tw[3:]
    from scipy.spatial.transform import Rotation

    pts = Rotation.from_rotvec(w[None, :] * dt[:, None]).apply(np.asarray(points_xyz, dtype=np.float64))
    a, b = _screw_terms(np.linalg.norm(w) * np.abs(dt))
    wv = np.cross(w, v)
    wwv = np.cross(w, wv)
    shift = v[None, :] * dt[:, None] + (a * dt**2)[:, None] * wv[None, :] + (b * dt**3)[:, None] * wwv[None, :]
    return np.asarray(pts + shift)


def twist_of(T_start_end: Mat4, duration_s: float) -> NDArray[np.float64]:
    """The constant body twist (vx, vy, vz m/s, wx, wy, wz rad/s) whose motion over ``duration_s``
    is ``T_start_end`` (SE(3) logarithm / duration; inverse of ``screw_apply``)."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T_start_end, dtype=np.float64)
    phi = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    a, b = _screw_terms(np.array([np.linalg.norm(phi)]))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    V = np.eye(3) + a[0] * K + b[0] * (K @ K)
    rho = np.linalg.solve(V, T[:3, 3])
    return np.concatenate([rho, phi]) / duration_s


def rotation_error_deg(T_a: Mat4, T_b: Mat4) -> float:
    """Angle (degrees) of the relative rotation between two transforms."""
    R = T_a[:3, :3].T @ T_b[:3, :3]
    cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)))


def translation_error_m(T_a: Mat4, T_b: Mat4) -> float:
    """Distance (m) between the translations of two transforms."""
    return float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def is_rigid(T: NDArray[np.float64], tol: float = 1e-6) -> bool:
    """True when T is a finite 4x4 rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(R.T @ R, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
        and np.allclose(T[3], [0, 0, 0, 1], atol=tol)
    )


@dataclass
class _Edge:
    """Transforms of one parent->child edge: static, or a time series of ``T_parent_child``."""

    static: Mat4 | None = None
    stamps_ns: list[int] = field(default_factory=list)
    transforms: list[Mat4] = field(default_factory=list)

    def at(self, stamp_ns: int | None, tolerance_ns: int) -> Mat4:
        if self.static is not None:
            return self.static
        if not self.stamps_ns:
            raise TransformError("edge has no transforms")
        if stamp_ns is None or len(self.stamps_ns) == 1:
            if stamp_ns is not None and abs(stamp_ns - self.stamps_ns[0]) > tolerance_ns:
                raise TransformError(f"no transform within {tolerance_ns / 1e6:.0f} ms of {stamp_ns}")
            return self.transforms[-1 if stamp_ns is None else 0]
        i = bisect.bisect_left(self.stamps_ns, stamp_ns)
        if i == 0 or i == len(self.stamps_ns):
            j = 0 if i == 0 else len(self.stamps_ns) - 1
            if abs(stamp_ns - self.stamps_ns[j]) > tolerance_ns:
                raise TransformError(f"no transform within {tolerance_ns / 1e6:.0f} ms of {stamp_ns}")
            return self.transforms[j]
        t0, t1 = self.stamps_ns[i - 1], self.stamps_ns[i]
        T0, T1 = self.transforms[i - 1], self.transforms[i]
        s = (stamp_ns - t0) / (t1 - t0) if t1 != t0 else 0.0
        from scipy.spatial.transform import Rotation, Slerp

        rots = Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]]))
        R = Slerp([0.0, 1.0], rots)([s]).as_matrix()[0]
        return make_T(R, (1 - s) * T0[:3, 3] + s * T1[:3, 3])


class TransformTree:
    """A tf tree from ``/tf`` and ``/tf_static``: ``lookup(target, source, stamp_ns)`` gives ``T_target_source``.

    Dynamic edges are interpolated (slerp + linear) between their stamps; outside the recorded span a
    lookup succeeds only within ``tolerance_ns`` of the nearest stamp.
    """

    def __init__(self, tolerance_ns: int = 100_000_000) -> None:
        self._edges: dict[tuple[str, str], _Edge] = {}
        self._children: dict[str, set[str]] = {}
        self._parents: dict[str, set[str]] = {}
        self.tolerance_ns = tolerance_ns

    def add(self, parent: str, child: str, T_parent_child: Mat4, stamp_ns: int, static: bool) -> None:
        """Add one edge sample. Raises TransformError for a non-rigid transform or a self-loop."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if parent == child:
            raise TransformError(f"transform from frame {parent!r} to itself")
        if not is_rigid(T_parent_child, tol=1e-4):
            raise TransformError(f"transform {parent} -> {child} is not a rigid transform")
        edge = self._edges.setdefault((parent, child), _Edge())
        self._children.setdefault(parent, set()).add(child)
        self._parents.setdefault(child, set()).add(parent)
        if static:
            edge.static = T_parent_child
            return
        i = bisect.bisect_left(edge.stamps_ns, stamp_ns)
        if i < len(edge.stamps_ns) and edge.stamps_ns[i] == stamp_ns:
            edge.transforms[i] = T_parent_child
            return
        edge.stamps_ns.insert(i, stamp_ns)
        edge.transforms.insert(i, T_parent_child)

    @property
    def frames(self) -> set[str]:
        return set(self._children) | set(self._parents)

    def edges(self) -> list[tuple[str, str, bool]]:
        """(parent, child, static) for every edge."""
        return [(p, c, e.static is not None) for (p, c), e in sorted(self._edges.items())]

    def is_static_path(self, target: str, source: str) -> bool:
        path = self._path(target.lstrip("/"), source.lstrip("/"))
        return all(self._edges[key].static is not None for key, _ in path)

    def _path(self, target: str, source: str) -> list[tuple[tuple[str, str], bool]]:
        """Edges from source to target as (edge key, forward) where forward means child->parent."""
        if target == source:
            return []
        prev: dict[str, tuple[str, tuple[tuple[str, str], bool]] | None] = {source: None}
        queue = deque([source])
        while queue:
            node = queue.popleft()
            if node == target:
                break
            for parent in self._parents.get(node, ()):
                if parent not in prev:
                    prev[parent] = (node, ((parent, node), True))
                    queue.append(parent)
            for child in self._children.get(node, ()):
                if child not in prev:
                    prev[child] = (node, ((node, child), False))
                    queue.append(child)
        if target not in prev:
            raise TransformError(f"no tf path from {source!r} to {target!r}")
        steps: list[tuple[tuple[str, str], bool]] = []
        node = target
        while prev[node] is not None:
            back = prev[node]
            assert back is not None
            steps.append(back[1])
            node = back[0]
        return steps[::-1]

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> Mat4:
        """``T_target_source`` at ``stamp_ns`` (None: latest / static)."""
        target, source = target.lstrip("/"), source.lstrip("/")
        T = np.eye(4)
        for key, forward in self._path(target, source):
            T_parent_child = self._edges[key].at(stamp_ns, self.tolerance_ns)
            step = T_parent_child if forward else invert(T_parent_child)
            T = step @ T
        return T

    def recorded_span(self, target: str, source: str) -> tuple[int, int] | None:
        """(first, last) stamps, ns, between which every moving edge from ``source`` to ``target`` was recorded
        (lookups there interpolate); None where the path has no moving edge or the spans do not overlap."""
        spans = [(e.stamps_ns[0], e.stamps_ns[-1]) for e in
                 (self._edges[key] for key, _ in self._path(target.lstrip("/"), source.lstrip("/")))
                 if e.static is None and e.stamps_ns]
        if not spans:
            return None
        first, last = max(a for a, _ in spans), min(b for _, b in spans)
        return (first, last) if first <= last else None

    def can_lookup(self, target: str, source: str) -> bool:
        try:
            self._path(target.lstrip("/"), source.lstrip("/"))
        except TransformError:
            return False
        return True


def root_of(tree: TransformTree, frame: str) -> str:
    """The top-most ancestor of ``frame`` (following the first parent at each step)."""
    node = frame.lstrip("/")
    seen = {node}
    while True:
        parents = sorted(tree._parents.get(node, ()))
        if not parents or parents[0] in seen:
            return node
        node = parents[0]
        seen.add(node)
