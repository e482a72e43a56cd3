"""Camera models: pinhole with ``plumb_bob`` / ``rational_polynomial`` distortion, ``equidistant``
fisheye, and the GOM paper's cylindrical panorama (eq. 6).

Points are in the camera *optical* frame (x right, y down, z forward), metres; pixels are (u, v)
with the origin at the centre of the top-left pixel. The images of a rectified stereo camera were
taken in a frame turned by the CameraInfo's rectification rotation R; ``R_rect`` carries it, and
``project`` / ``unproject`` apply it, so that points stay in the camera's own (tf) optical frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import DecodeError

DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant", "cylindrical", "none")
_DISTORTION_ALIASES = {"": "none", "pinhole": "none", "radtan": "plumb_bob", "fisheye": "equidistant",
                       "kannala_brandt": "equidistant"}


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera.

    Attributes:
        width, height: image size in pixels.
        K: 3x3 intrinsic matrix (fx, fy, cx, cy in pixels). For ``cylindrical``, fx is pixels per
            radian of azimuth and fy the focal length in pixels along the cylinder axis.
        D: distortion coefficients; plumb_bob (k1 k2 p1 p2 k3), rational_polynomial
            (k1 k2 p1 p2 k3 k4 k5 k6), equidistant (k1 k2 k3 k4).
        distortion_model: one of ``DISTORTION_MODELS``.
        R_rect: 3x3 rotation from the camera's optical frame to the frame its images were rectified
            into (``p_rect = R_rect @ p``, the CameraInfo's R of a stereo pair, as OpenCV's
            ``undistortPoints(..., R, P)`` applies it); None: the identity.
    """

    width: int
    height: int
    K: NDArray[np.float64]
    D: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    distortion_model: str = "plumb_bob"
    R_rect: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        D = np.asarray(self.D, dtype=np.float64).ravel()
        model = _DISTORTION_ALIASES.get(self.distortion_model, self.distortion_model)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)
        object.__setattr__(self, "distortion_model", model)
        if model not in DISTORTION_MODELS:
            raise DecodeError(f"unsupported camera distortion model {self.distortion_model!r}")
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise DecodeError("camera intrinsics K are zero, negative or not finite")
        if not np.all(np.isfinite(D)):
            raise DecodeError("camera distortion coefficients are not finite")
        if self.width <= 0 or self.height <= 0:
            raise DecodeError(f"camera size {self.width}x{self.height} is not positive")
        if self.R_rect is not None:
            object.__setattr__(self, "R_rect", _rotation(self.R_rect))

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    def coefficients(self, n: int) -> NDArray[np.float64]:
        """The first n distortion coefficients, zero-padded."""
        out = np.zeros(n)
        m = min(n, self.D.size)
        out[:m] = self.D[:m]
        return out

    def with_focal_scale(self, scale: float) -> CameraModel:
        """Same camera with fx and fy multiplied by ``scale``."""
        K = self.K.copy()
        K[0, 0] *= scale
        K[1, 1] *= scale
        return CameraModel(self.width, self.height, K, self.D, self.distortion_model, self.R_rect)

    def without_rectification(self) -> CameraModel:
        """The same intrinsics for points already in the rectified frame (``R_rect`` dropped)."""
        return CameraModel(self.width, self.height, self.K, self.D, self.distortion_model)

    def project(self, points_cam: NDArray[np.floating]) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Project (N, 3) optical-frame points to pixels (turned by ``R_rect`` first, when set).

        Returns (uv (N, 2), valid (N,)); valid is False behind the camera, outside the image or where
        distortion folds over.
        """
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        if self.R_rect is not None:
            p = p @ self.R_rect.T
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        model = self.distortion_model
        with np.errstate(divide="ignore", invalid="ignore"):
            if model == "cylindrical":
                theta = np.arctan2(x, z)
                rho = np.hypot(x, z)
                u = self.fx * theta + self.cx
                v = self.fy * y / rho + self.cy
                front = rho > 1e-9
            elif model == "equidistant":
                r = np.hypot(x, y)
                th = np.arctan2(r, z)
                k = self.coefficients(4)
                th2 = th * th
                th_d = th * (1 + th2 * (k[0] + th2 * (k[1] + th2 * (k[2] + th2 * k[3]))))
                scale = np.where(r > 1e-12, th_d / np.where(r > 1e-12, r, 1.0), 1.0 / np.where(z > 0, z, 1.0))
                u = self.fx * x * scale + self.cx
                v = self.fy * y * scale + self.cy
                front = (z > 1e-9) & (th < np.radians(89.0))
            else:
                xn, yn = x / z, y / z
                front = z > 1e-9
                xd, yd = self._distort(xn, yn)
                u = self.fx * xd + self.K[0, 1] * yd + self.cx
                v = self.fy * yd + self.cy
        uv = np.stack([u, v], axis=1)
        inside = (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)
        valid = front & inside & np.isfinite(u) & np.isfinite(v)
        if model in ("plumb_bob", "rational_polynomial") and np.any(self.D):
            valid &= self._monotonic(p, valid)
        return uv, valid

    def _distort(
        self, xn: NDArray[np.float64], yn: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        if self.distortion_model == "none":
            return xn, yn
        k = self.coefficients(8)
        k1, k2, p1, p2, k3, k4, k5, k6 = k
        if self.distortion_model == "plumb_bob":
            k4 = k5 = k6 = 0.0
        r2 = xn * xn + yn * yn
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        return xd, yd

    def _monotonic(self, p: NDArray[np.float64], valid: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """False where a point lies beyond the radius at which radial distortion stops growing."""
        r_max = self._max_undistorted_radius()
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.hypot(p[:, 0], p[:, 1]) / p[:, 2]
        return ~valid | (r <= r_max)

    def _max_undistorted_radius(self) -> float:
        rs = np.linspace(0.0, 4.0, 4001)
        xd, _ = self._distort(rs, np.zeros_like(rs))
        grow = np.diff(xd) > 0
        if np.all(grow):
            return float(rs[-1])
        return float(rs[int(np.argmin(grow))])

    def unproject(self, uv: NDArray[np.floating]) -> NDArray[np.float64]:
        """Rays (N, 3) for pixels (N, 2) in the optical frame: unit depth (z = 1) for pinhole models
        without ``R_rect``, unit vectors otherwise."""
        rays = self._unproject_rectified(uv)
        if self.R_rect is None:
            return rays
        rays = rays @ self.R_rect  # R^T applied to each row
        return np.asarray(rays / np.linalg.norm(rays, axis=1, keepdims=True))

    def _unproject_rectified(self, uv: NDArray[np.floating]) -> NDArray[np.float64]:
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.distortion_model == "cylindrical":
            theta = (uv[:, 0] - self.cx) / self.fx
            y = (uv[:, 1] - self.cy) / self.fy
            rays = np.stack([np.sin(theta), y, np.cos(theta)], axis=1)
            return np.asarray(rays / np.linalg.norm(rays, axis=1, keepdims=True))
        yd = (uv[:, 1] - self.cy) / self.fy
        xd = (uv[:, 0] - self.cx - self.K[0, 1] * yd) / self.fx
        if self.distortion_model == "equidistant":
            th_d = np.hypot(xd, yd)
            k = self.coefficients(4)
            th = th_d.copy()
            for _ in range(20):
                th2 = th * th
                f = th * (1 + th2 * (k[0] + th2 * (k[1] + th2 * (k[2] + th2 * k[3])))) - th_d
                df = 1 + th2 * (3 * k[0] + th2 * (5 * k[1] + th2 * (7 * k[2] + th2 * 9 * k[3])))
                th = th - f / df
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(th_d > 1e-12, np.sin(th) / np.where(th_d > 1e-12, th_d, 1.0), 1.0)
            rays = np.stack([xd * s, yd * s, np.cos(th)], axis=1)
            return np.asarray(rays)
        xn, yn = xd.copy(), yd.copy()
        for _ in range(30):
            xx, yy = self._distort(xn, yn)
            xn = xn - (xx - xd)
            yn = yn - (yy - yd)
        return np.stack([xn, yn, np.ones_like(xn)], axis=1)


def with_model(camera: CameraModel | None, model: str) -> CameraModel | None:
    """``camera`` (as its CameraInfo describes it) with its projection replaced by ``model`` (same size, K
    and D); ``log`` or a missing camera: unchanged (``calibration.camera_model``)."""
    if camera is None or model == "log" or model == camera.distortion_model:
        return camera
    return CameraModel(camera.width, camera.height, camera.K, camera.D, model, camera.R_rect)


def _rotation(R: NDArray[np.floating], tol: float = 1e-3) -> NDArray[np.float64]:
    """R as a 3x3 float64 rotation (re-orthonormalised; CameraInfo stores it in printed decimals)."""
    m = np.asarray(R, dtype=np.float64)
    if m.size != 9 or not np.all(np.isfinite(m)):
        raise DecodeError("camera rectification rotation R must be 9 finite values")
    m = m.reshape(3, 3)
    if np.max(np.abs(m @ m.T - np.eye(3))) > tol or np.linalg.det(m) <= 0:
        raise DecodeError("camera rectification rotation R is not a rotation matrix")
    u, _, vt = np.linalg.svd(m)
    return np.asarray(u @ vt)
