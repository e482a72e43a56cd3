"""Camera models: pinhole with ``plumb_bob`` / ``rational_polynomial`` distortion, ``equidistant``
fisheye, and the GOM paper's cylindrical panorama (eq. 6).

Points are in the camera *optical* frame (x right, y down, z forward), metres; pixels are (u, v)
with the origin at the centre of the top-left pixel. The images of a rectified stereo camera were
taken in a frame turned by the CameraInfo's rectification rotation R; ``R_rect`` carries it, and
``project`` / ``unproject`` apply it, so that points stay in the camera's own (tf) optical frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.polynomial import Polynomial
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

        Returns (uv (N, 2), valid (N,)); valid is False behind the camera, outside the image or outside
        the lens model's valid region (``max_undistorted_radius``, ``max_view_angle_rad``), where the
        distortion folds over. Points outside that region are culled before distorting: their uv are
        NaN, and no point, however far off axis, overflows or warns.
        """
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        if self.R_rect is not None:
            p = p @ self.R_rect.T
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        model = self.distortion_model
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            if model == "cylindrical":
                theta = np.arctan2(x, z)
                rho = np.hypot(x, z)
                u = self.fx * theta + self.cx
                v = self.fy * y / rho + self.cy
                inside_region = rho > 1e-9
            elif model == "equidistant":
                r = np.hypot(x, y)
                th = np.arctan2(r, z)
                inside_region = (z > 1e-9) & (th < self.max_view_angle_rad)
                th = np.where(inside_region, th, 0.0)
                th_d = self._equidistant_radius(th)
                scale = np.where(r > 1e-12, th_d / np.where(r > 1e-12, r, 1.0), 1.0 / np.where(z > 1e-9, z, 1.0))
                u = np.where(inside_region, self.fx * x * scale + self.cx, np.nan)
                v = np.where(inside_region, self.fy * y * scale + self.cy, np.nan)
            else:
                front = z > 1e-9
                xn = np.where(front, x / np.where(front, z, 1.0), np.inf)
                yn = np.where(front, y / np.where(front, z, 1.0), np.inf)
                inside_region = front & (xn * xn + yn * yn <= self.max_undistorted_radius**2)
                xd, yd = self._distort(np.where(inside_region, xn, 0.0), np.where(inside_region, yn, 0.0))
                u = np.where(inside_region, self.fx * xd + self.K[0, 1] * yd + self.cx, np.nan)
                v = np.where(inside_region, self.fy * yd + self.cy, np.nan)
        uv = np.stack([u, v], axis=1)
        with np.errstate(invalid="ignore"):
            inside = (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)
        valid = inside_region & inside & np.isfinite(u) & np.isfinite(v)
        return uv, valid

    def _distort(
        self, xn: NDArray[np.float64], yn: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Distorted normalised coordinates of undistorted ones (``plumb_bob`` / ``rational_polynomial``)."""
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

    @cached_property
    def _radial_polynomials(self) -> tuple[Polynomial, Polynomial, Polynomial]:
        """(num, den, slope) in s = r^2 of a ``plumb_bob`` / ``rational_polynomial`` radial map
        ``r -> r num(s) / den(s)``, whose derivative in r is ``slope(s) / den(s)^2``."""
        k1, k2, _, _, k3, k4, k5, k6 = self.coefficients(8)
        if self.distortion_model != "rational_polynomial":
            k4 = k5 = k6 = 0.0
        num = Polynomial([1.0, k1, k2, k3])
        den = Polynomial([1.0, k4, k5, k6])
        slope = num * den + Polynomial([0.0, 2.0]) * (num.deriv() * den - num * den.deriv())
        return num, den, slope

    @cached_property
    def max_undistorted_radius(self) -> float:
        """Largest undistorted radius ``r = hypot(x, y) / z`` (tan of the angle off the optical axis) up to
        which the ``plumb_bob`` / ``rational_polynomial`` radial map ``r -> r * radial(r^2)`` still grows:
        the first positive root of its derivative (or of the rational denominator), from the
        coefficients. Beyond it the lens model folds back (a strong wide-angle barrel distortion does
        so inside the field of view) and is no model of the lens. ``inf`` where it never stops growing and
        for the other models."""
        if self.distortion_model not in ("plumb_bob", "rational_polynomial") or not np.any(self.D):
            return float("inf")
        _, den, slope = self._radial_polynomials
        return float(np.sqrt(_first_positive_root([slope, den])))

    def _max_undistorted_radius(self) -> float:
        """``max_undistorted_radius`` (the name the metric kernels' packing reads)."""
        return self.max_undistorted_radius

    @cached_property
    def max_view_angle_rad(self) -> float:
        """Largest angle off the optical axis (radians) an ``equidistant`` point may have: 89 deg, or less
        where ``theta -> theta_d`` stops growing first (the first positive root of its derivative). pi
        for the other models (they limit the radius instead: ``max_undistorted_radius``)."""
        if self.distortion_model != "equidistant":
            return float(np.pi)
        k1, k2, k3, k4 = self.coefficients(4)
        slope = Polynomial([1.0, 3 * k1, 5 * k2, 7 * k3, 9 * k4])  # d theta_d / d theta in t = theta^2
        return float(min(np.radians(89.0), np.sqrt(_first_positive_root([slope]))))

    def _equidistant_radius(self, th: NDArray[np.float64]) -> NDArray[np.float64]:
        """theta_d of angles ``th`` (radians) off the optical axis."""
        k = self.coefficients(4)
        th2 = th * th
        return np.asarray(th * (1 + th2 * (k[0] + th2 * (k[1] + th2 * (k[2] + th2 * k[3])))))

    def _radial_map(self, r: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Distorted radius of undistorted radii ``r`` and its derivative in r (``plumb_bob`` /
        ``rational_polynomial``, no tangential part)."""
        num, den, slope = self._radial_polynomials
        s = r * r
        d = den(s)
        return r * num(s) / d, slope(s) / (d * d)

    @cached_property
    def _radial_table(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(distorted, undistorted) radii on 4097 points of the valid region (both increasing), to invert
        the radial map by interpolation; the region is capped at r = 20 (87 deg) where it is unbounded."""
        r_max = min(self.max_undistorted_radius, 20.0)
        r = np.linspace(0.0, r_max, 4097)
        return self._radial_map(r)[0], r

    def unproject(self, uv: NDArray[np.floating]) -> NDArray[np.float64]:
        """Rays (N, 3) for pixels (N, 2) in the optical frame: unit depth (z = 1) for pinhole models
        without ``R_rect``, unit vectors otherwise. A pixel beyond the image of the lens model's valid
        region (a wide-angle image's corners, where the model folds over) gets the ray at the region's
        edge in its direction; ``project`` of that ray lands short of the pixel."""
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
            return self._unproject_equidistant(xd, yd)
        if self.distortion_model == "none":
            return np.stack([xd, yd, np.ones_like(xd)], axis=1)
        xn, yn = self._undistort_radial(xd, yd)
        p1, p2 = self.coefficients(4)[2:4]
        if p1 != 0.0 or p2 != 0.0:
            for _ in range(8):  # tangential terms (small): fixed point on the radially distorted target
                r2 = xn * xn + yn * yn
                tx = 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
                ty = p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
                xn, yn = self._undistort_radial(xd - tx, yd - ty)
        return np.stack([xn, yn, np.ones_like(xn)], axis=1)

    def _undistort_radial(self, xd: NDArray[np.float64], yd: NDArray[np.float64]) -> tuple[
            NDArray[np.float64], NDArray[np.float64]]:
        """Undistorted normalised coordinates of radially distorted ones: the radius by interpolating the
        monotonic table of the valid region and two Newton steps, clamped to the region."""
        f_tab, r_tab = self._radial_table
        rd = np.hypot(xd, yd)
        r = np.interp(rd, f_tab, r_tab)
        inside = rd < f_tab[-1]
        for _ in range(3):  # Newton steps from the table's estimate, kept inside the region
            f, df = self._radial_map(r)
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.clip(np.where(inside & (df > 1e-12), r - (f - rd) / df, r), 0.0, r_tab[-1])
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(rd > 1e-15, r / np.where(rd > 1e-15, rd, 1.0), 1.0)
        return xd * scale, yd * scale

    def _unproject_equidistant(self, xd: NDArray[np.float64], yd: NDArray[np.float64]) -> NDArray[np.float64]:
        th_max = self.max_view_angle_rad
        th_d_max = float(self._equidistant_radius(np.array([th_max]))[0])
        th_d = np.hypot(xd, yd)
        th = np.minimum(th_d, th_max)
        k = self.coefficients(4)
        for _ in range(20):
            th2 = th * th
            f = self._equidistant_radius(th) - np.minimum(th_d, th_d_max)
            df = 1 + th2 * (3 * k[0] + th2 * (5 * k[1] + th2 * (7 * k[2] + th2 * 9 * k[3])))
            th = np.clip(th - f / np.maximum(df, 1e-9), 0.0, th_max)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(th_d > 1e-12, np.sin(th) / np.where(th_d > 1e-12, th_d, 1.0), 1.0)
        return np.stack([xd * s, yd * s, np.cos(th)], axis=1)


def _first_positive_root(polys: list[Polynomial]) -> float:
    """The smallest real positive root of any of ``polys`` (inf where none has one)."""
    roots = [z.real for poly in polys for z in poly.trim().roots()
             if abs(z.imag) <= 1e-9 * max(1.0, abs(z)) and z.real > 0]
    return float(min(roots, default=np.inf))


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
