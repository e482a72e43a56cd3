"""numba kernels for the calibration metrics: camera projection, Keys bicubic interpolation, and the
batched GOM / NMI / Levinson scores.

Kernels take contiguous arrays and scalars only; the public wrappers in ``metrics.py`` validate
inputs. A pose batch is ``poses`` (P, 3, 4) float64: rows of ``[R | t]`` of ``T_camera_lidar`` (lidar
points into the camera optical frame, metres) and ``focal_scale`` (P,) multiplying fx and fy.

Camera parameters are packed in ``cam`` (float64, 16): ``model, fx, fy, cx, cy, skew, k1, k2, p1, p2,
k3, k4, k5, k6, r_max, unused``; for ``equidistant`` the four fisheye coefficients sit in k1..k4
slots 6..9. Model codes are ``MODEL_CODES``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from fleetcal.pipeline.numba_flags import NJIT_FLAGS

MODEL_NONE = 0
MODEL_PLUMB_BOB = 1
MODEL_RATIONAL = 2
MODEL_EQUIDISTANT = 3
MODEL_CYLINDRICAL = 4
MODEL_CODES = {
    "none": MODEL_NONE,
    "plumb_bob": MODEL_PLUMB_BOB,
    "rational_polynomial": MODEL_RATIONAL,
    "equidistant": MODEL_EQUIDISTANT,
    "cylindrical": MODEL_CYLINDRICAL,
}
CAM_PARAMS = 16
# The batch kernels always run threaded over poses: a calibration is one in-process optimisation
# that should use every core, unlike the per-frame engine stages (see pipeline.numba_flags).
_BATCH_FLAGS = {**NJIT_FLAGS, "parallel": True, "fastmath": True}
_EQUIDISTANT_MAX_THETA = math.radians(89.0)


@njit(inline="always", **NJIT_FLAGS)
def project_point(x: float, y: float, z: float, cam: np.ndarray, fscale: float) -> tuple[float, float, bool]:
    """Pixel (u, v) of one optical-frame point and whether it is in front of the camera and
    within the monotonic range of the distortion (image bounds are not checked here)."""
    model = int(cam[0])
    fx = cam[1] * fscale
    fy = cam[2] * fscale
    cx = cam[3]
    cy = cam[4]
    if model == MODEL_CYLINDRICAL:
        rho = math.sqrt(x * x + z * z)
        if rho <= 1e-9:
            return 0.0, 0.0, False
        return fx * math.atan2(x, z) + cx, fy * y / rho + cy, True
    if model == MODEL_EQUIDISTANT:
        if z <= 1e-9:
            return 0.0, 0.0, False
        r = math.sqrt(x * x + y * y)
        th = math.atan2(r, z)
        if th >= _EQUIDISTANT_MAX_THETA:
            return 0.0, 0.0, False
        th2 = th * th
        th_d = th * (1.0 + th2 * (cam[6] + th2 * (cam[7] + th2 * (cam[8] + th2 * cam[9]))))
        scale = th_d / r if r > 1e-12 else 1.0 / z
        return fx * x * scale + cx, fy * y * scale + cy, True
    if z <= 1e-9:
        return 0.0, 0.0, False
    xn = x / z
    yn = y / z
    if model == MODEL_NONE:
        return fx * xn + cam[5] * yn + cx, fy * yn + cy, True
    r2 = xn * xn + yn * yn
    if r2 > cam[14] * cam[14]:
        return 0.0, 0.0, False
    k1, k2, p1, p2, k3 = cam[6], cam[7], cam[8], cam[9], cam[10]
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if model == MODEL_RATIONAL:
        radial /= 1.0 + r2 * (cam[11] + r2 * (cam[12] + r2 * cam[13]))
    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
    return fx * xd + cam[5] * yd + cx, fy * yd + cy, True


@njit(**NJIT_FLAGS)
def project_points_kernel(points_cam: np.ndarray, cam: np.ndarray, width: int, height: int) -> tuple[
        np.ndarray, np.ndarray]:
    """Project (N, 3) optical-frame points; returns uv (N, 2) and valid (N,) (front, in image)."""
    n = points_cam.shape[0]
    uv = np.zeros((n, 2))
    valid = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        u, v, ok = project_point(points_cam[i, 0], points_cam[i, 1], points_cam[i, 2], cam, 1.0)
        uv[i, 0] = u
        uv[i, 1] = v
        valid[i] = ok and u >= -0.5 and u <= width - 0.5 and v >= -0.5 and v <= height - 0.5
    return uv, valid


@njit(inline="always", **NJIT_FLAGS)
def keys_weights(t: float) -> tuple[float, float, float, float]:
    """Keys cubic-convolution weights (a = -0.5) of taps at offsets -1, 0, 1, 2 for fraction t in [0, 1)."""
    t2 = t * t
    t3 = t2 * t
    w0 = -0.5 * t3 + t2 - 0.5 * t
    w1 = 1.5 * t3 - 2.5 * t2 + 1.0
    w2 = -1.5 * t3 + 2.0 * t2 + 0.5 * t
    w3 = 0.5 * t3 - 0.5 * t2
    return w0, w1, w2, w3


@njit(inline="always", **NJIT_FLAGS)
def sample_bicubic(planes: np.ndarray, u: float, v: float, out: np.ndarray) -> None:
    """Keys bicubic sample of every channel of ``planes`` (H, W, C) at pixel (u, v), edges clamped."""
    h = planes.shape[0]
    w = planes.shape[1]
    nc = planes.shape[2]
    fu = math.floor(u)
    fv = math.floor(v)
    iu = int(fu)
    iv = int(fv)
    wu0, wu1, wu2, wu3 = keys_weights(u - fu)
    wv0, wv1, wv2, wv3 = keys_weights(v - fv)
    for c in range(nc):
        out[c] = 0.0
    for j in range(4):
        row = min(max(iv - 1 + j, 0), h - 1)
        wv = wv0 if j == 0 else (wv1 if j == 1 else (wv2 if j == 2 else wv3))
        for i in range(4):
            col = min(max(iu - 1 + i, 0), w - 1)
            wgt = wv * (wu0 if i == 0 else (wu1 if i == 1 else (wu2 if i == 2 else wu3)))
            for c in range(nc):
                out[c] += wgt * planes[row, col, c]


@njit(**NJIT_FLAGS)
def sample_bicubic_kernel(planes: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Keys bicubic samples (N, C) of ``planes`` (H, W, C) at pixels ``uv`` (N, 2)."""
    n = uv.shape[0]
    out = np.zeros((n, planes.shape[2]))
    tmp = np.zeros(planes.shape[2])
    for i in range(n):
        sample_bicubic(planes, uv[i, 0], uv[i, 1], tmp)
        out[i, :] = tmp
    return out


@njit(inline="always", **NJIT_FLAGS)
def _in_view(u: float, v: float, width: int, height: int, mask: np.ndarray) -> bool:
    """Whether pixel (u, v) lies in the image and its valid ``mask`` (H, W); a (1, 1) mask: every pixel is valid."""
    if not (u >= 0.0 and u <= width - 1.0 and v >= 0.0 and v <= height - 1.0):
        return False
    if mask.shape[0] == 1 and mask.shape[1] == 1:
        return True
    return mask[int(v + 0.5), int(u + 0.5)] != 0


@njit(inline="always", **NJIT_FLAGS)
def _pose_pixel(R: np.ndarray, points: np.ndarray, i: int, cam: np.ndarray, fs: float, width: int,
                height: int, mask: np.ndarray) -> tuple[float, float, bool]:
    """Pixel of lidar point i under the 4x4 pose R and whether it is in view (front, image, mask)."""
    x0 = points[i, 0]
    y0 = points[i, 1]
    z0 = points[i, 2]
    x = R[0, 0] * x0 + R[0, 1] * y0 + R[0, 2] * z0 + R[0, 3]
    y = R[1, 0] * x0 + R[1, 1] * y0 + R[1, 2] * z0 + R[1, 3]
    z = R[2, 0] * x0 + R[2, 1] * y0 + R[2, 2] * z0 + R[2, 3]
    u, v, ok = project_point(x, y, z, cam, fs)
    return u, v, ok and _in_view(u, v, width, height, mask)


@njit(inline="always", **NJIT_FLAGS)
def sample_bicubic2(planes: np.ndarray, u: float, v: float) -> tuple[float, float]:
    """Keys bicubic sample of a 2-channel (H, W, 2) image at (u, v): unrolled interior fast path,
    clamped edges otherwise (the values of ``sample_bicubic``; float32 or int16 planes: to float32 rounding)."""
    h = planes.shape[0]
    w = planes.shape[1]
    fu = math.floor(u)
    fv = math.floor(v)
    iu = int(fu) - 1
    iv = int(fv) - 1
    wu0, wu1, wu2, wu3 = keys_weights(u - fu)
    wv0, wv1, wv2, wv3 = keys_weights(v - fv)
    a = 0.0
    b = 0.0
    if iu >= 0 and iv >= 0 and iu + 3 < w and iv + 3 < h:
        # each row's taps in float32, the planes' precision (float32, or int16 steps): float32 planes then need
        # no conversion per tap (a GOM call 10 % faster); the rows are summed in float64
        t = np.float32
        f0, f1, f2, f3 = t(wu0), t(wu1), t(wu2), t(wu3)
        for j in range(4):
            wv = wv0 if j == 0 else (wv1 if j == 1 else (wv2 if j == 2 else wv3))
            row = iv + j
            a += wv * (f0 * planes[row, iu, 0] + f1 * planes[row, iu + 1, 0]
                       + f2 * planes[row, iu + 2, 0] + f3 * planes[row, iu + 3, 0])
            b += wv * (f0 * planes[row, iu, 1] + f1 * planes[row, iu + 1, 1]
                       + f2 * planes[row, iu + 2, 1] + f3 * planes[row, iu + 3, 1])
        return a, b
    c0 = min(max(iu, 0), w - 1)
    c1 = min(max(iu + 1, 0), w - 1)
    c2 = min(max(iu + 2, 0), w - 1)
    c3 = min(max(iu + 3, 0), w - 1)
    for j in range(4):
        wv = wv0 if j == 0 else (wv1 if j == 1 else (wv2 if j == 2 else wv3))
        row = min(max(iv + j, 0), h - 1)
        a += wv * (wu0 * planes[row, c0, 0] + wu1 * planes[row, c1, 0] + wu2 * planes[row, c2, 0]
                   + wu3 * planes[row, c3, 0])
        b += wv * (wu0 * planes[row, c0, 1] + wu1 * planes[row, c1, 1] + wu2 * planes[row, c2, 1]
                   + wu3 * planes[row, c3, 1])
    return a, b


@njit(**_BATCH_FLAGS)
def gom_batch_kernel(points: np.ndarray, lidar_c2: np.ndarray, lidar_s2: np.ndarray, lidar_mag: np.ndarray,
                     grad_planes: np.ndarray, mask: np.ndarray, cam: np.ndarray, poses: np.ndarray,
                     focal_scale: np.ndarray, roll2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GOM sums for a batch of poses (paper eq. 9-11).

    ``lidar_c2, lidar_s2`` are cos/sin of twice the lidar gradient orientation, ``lidar_mag`` its
    magnitude, ``grad_planes`` (H, W, 2) the image gradient (gx, gy). ``roll2`` (P, 2) holds cos/sin
    of twice each pose's roll about the optical axis relative to the pose the lidar gradients were
    computed at; the lidar orientations are turned by it. Per pose returns
    ``(sum mu * alpha, sum mu, projected points)``; GOM = first / (2 * second). The angle difference
    of eq. 9 is taken through double-angle identities: cos 2(a - b) = cos2a cos2b + sin2a sin2b.
    """
    n_pose = poses.shape[0]
    n = points.shape[0]
    height = grad_planes.shape[0]
    width = grad_planes.shape[1]
    num = np.zeros(n_pose)
    den = np.zeros(n_pose)
    count = np.zeros(n_pose, dtype=np.int64)
    for p in prange(n_pose):
        R = poses[p]
        r00, r01, r02, r03 = R[0, 0], R[0, 1], R[0, 2], R[0, 3]
        r10, r11, r12, r13 = R[1, 0], R[1, 1], R[1, 2], R[1, 3]
        r20, r21, r22, r23 = R[2, 0], R[2, 1], R[2, 2], R[2, 3]
        fs = focal_scale[p]
        cr = roll2[p, 0]
        sr = roll2[p, 1]
        s_num = 0.0
        s_den = 0.0
        c = 0
        for i in range(n):
            x0 = points[i, 0]
            y0 = points[i, 1]
            z0 = points[i, 2]
            x = r00 * x0 + r01 * y0 + r02 * z0 + r03
            y = r10 * x0 + r11 * y0 + r12 * z0 + r13
            z = r20 * x0 + r21 * y0 + r22 * z0 + r23
            u, v, ok = project_point(x, y, z, cam, fs)
            if not ok or not _in_view(u, v, width, height, mask):
                continue
            gx, gy = sample_bicubic2(grad_planes, u, v)
            m2 = gx * gx + gy * gy
            c += 1
            if m2 <= 1e-20:
                continue
            mag_i = math.sqrt(m2)
            mu = mag_i * lidar_mag[i]
            lc2 = lidar_c2[i] * cr - lidar_s2[i] * sr
            ls2 = lidar_s2[i] * cr + lidar_c2[i] * sr
            cos2d = ((gx * gx - gy * gy) * lc2 + 2.0 * gx * gy * ls2) / m2
            s_num += mu * (cos2d + 1.0)
            s_den += mu
        num[p] = s_num
        den[p] = s_den
        count[p] = c
    return num, den, count


@njit(inline="always", **NJIT_FLAGS)
def _gom_term(gx: float, gy: float, m2: float, c2: float, s2: float, mag: float, cr: float,
              sr: float) -> tuple[float, float]:
    """One point's GOM numerator and weight (``gom_batch_kernel``'s loop body) for image gradient (gx, gy)
    of squared magnitude m2 > 0 and the lidar gradient's cos / sin of twice its orientation and magnitude."""
    mu = math.sqrt(m2) * mag
    lc2 = c2 * cr - s2 * sr
    ls2 = s2 * cr + c2 * sr
    cos2d = ((gx * gx - gy * gy) * lc2 + 2.0 * gx * gy * ls2) / m2
    return mu * (cos2d + 1.0), mu


@njit(inline="always", **NJIT_FLAGS)
def _pair_terms(planes: np.ndarray, u: float, v: float, i: int, in0: bool, in1: bool, lidar_c2: np.ndarray,
                lidar_s2: np.ndarray, lidar_mag: np.ndarray, cr: float, sr: float) -> tuple[float, float, float, float]:
    """Point i's GOM numerator and weight for channels 0 and 1 at pixel (u, v) of ``planes`` (0 for a channel
    that does not hold the point, or where the image gradient vanishes)."""
    gx, gy = sample_bicubic2(planes, u, v)
    m2 = gx * gx + gy * gy
    a0 = w0 = a1 = w1 = 0.0
    if m2 > 1e-20:
        if in0:
            a0, w0 = _gom_term(gx, gy, m2, lidar_c2[i, 0], lidar_s2[i, 0], lidar_mag[i, 0], cr, sr)
        if in1:
            a1, w1 = _gom_term(gx, gy, m2, lidar_c2[i, 1], lidar_s2[i, 1], lidar_mag[i, 1], cr, sr)
    return a0, w0, a1, w1


@njit(**_BATCH_FLAGS)
def gom_pair_batch_kernel(points: np.ndarray, lidar_c2: np.ndarray, lidar_s2: np.ndarray, lidar_mag: np.ndarray,
                          member: np.ndarray, planes0: np.ndarray, planes1: np.ndarray, n_planes: int,
                          mask: np.ndarray, mask1: np.ndarray, scale1: np.ndarray, cam: np.ndarray,
                          poses: np.ndarray, focal_scale: np.ndarray,
                          roll2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``gom_batch_kernel`` of two feature channels of one scan against ``n_planes`` (1 or 2) gradient planes
    of one camera in one pass: each point is projected once per pose and each plane sampled once, whichever
    channels hold the point.

    ``points`` (N, 3) is the union of the channels' points; ``lidar_c2, lidar_s2, lidar_mag`` and ``member``
    are (N, 2): a channel's values at the points it holds (``member`` 1). ``planes1`` and its valid ``mask1``
    are read only when ``n_planes`` is 2; their pixel is planes0's (u, v) times ``scale1`` (2,) (planes kept
    at a wider stride: planes0's stride over theirs, per axis). Returns ``(sum mu * alpha, sum mu, projected
    points)``, each (P, 2, 2) (plane, channel); per channel and plane they are ``gom_batch_kernel``'s sums on
    that channel's points alone (``cam`` scaled to each plane's pixels), added in the same order.
    """
    n_pose = poses.shape[0]
    n = points.shape[0]
    height = planes0.shape[0]
    width = planes0.shape[1]
    height1 = planes1.shape[0]
    width1 = planes1.shape[1]
    su = scale1[0]
    sv = scale1[1]
    num = np.zeros((n_pose, 2, 2))
    den = np.zeros((n_pose, 2, 2))
    count = np.zeros((n_pose, 2, 2), dtype=np.int64)
    for p in prange(n_pose):
        R = poses[p]
        r00, r01, r02, r03 = R[0, 0], R[0, 1], R[0, 2], R[0, 3]
        r10, r11, r12, r13 = R[1, 0], R[1, 1], R[1, 2], R[1, 3]
        r20, r21, r22, r23 = R[2, 0], R[2, 1], R[2, 2], R[2, 3]
        fs = focal_scale[p]
        cr = roll2[p, 0]
        sr = roll2[p, 1]
        n00 = n01 = n10 = n11 = 0.0
        d00 = d01 = d10 = d11 = 0.0
        c00 = c01 = c10 = c11 = 0
        for i in range(n):
            x0 = points[i, 0]
            y0 = points[i, 1]
            z0 = points[i, 2]
            x = r00 * x0 + r01 * y0 + r02 * z0 + r03
            y = r10 * x0 + r11 * y0 + r12 * z0 + r13
            z = r20 * x0 + r21 * y0 + r22 * z0 + r23
            u, v, ok = project_point(x, y, z, cam, fs)
            if not ok or not _in_view(u, v, width, height, mask):
                continue
            in0 = member[i, 0] != 0
            in1 = member[i, 1] != 0
            a0, w0, a1, w1 = _pair_terms(planes0, u, v, i, in0, in1, lidar_c2, lidar_s2, lidar_mag, cr, sr)
            n00 += a0
            d00 += w0
            n01 += a1
            d01 += w1
            c00 += in0
            c01 += in1
            if n_planes < 2:
                continue
            u1 = u * su
            v1 = v * sv
            if not _in_view(u1, v1, width1, height1, mask1):
                continue
            a0, w0, a1, w1 = _pair_terms(planes1, u1, v1, i, in0, in1, lidar_c2, lidar_s2, lidar_mag, cr, sr)
            n10 += a0
            d10 += w0
            n11 += a1
            d11 += w1
            c10 += in0
            c11 += in1
        num[p, 0, 0], num[p, 0, 1], num[p, 1, 0], num[p, 1, 1] = n00, n01, n10, n11
        den[p, 0, 0], den[p, 0, 1], den[p, 1, 0], den[p, 1, 1] = d00, d01, d10, d11
        count[p, 0, 0], count[p, 0, 1], count[p, 1, 0], count[p, 1, 1] = c00, c01, c10, c11
    return num, den, count


@njit(**_BATCH_FLAGS)
def levinson_batch_kernel(points: np.ndarray, lidar_weight: np.ndarray, edge_planes: np.ndarray,
                          mask: np.ndarray, cam: np.ndarray, poses: np.ndarray,
                          focal_scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Levinson & Thrun score per pose: sum of lidar depth-discontinuity weight x edge image value
    (bicubic, ``edge_planes`` (H, W, 1)), and the number of projected points."""
    n_pose = poses.shape[0]
    n = points.shape[0]
    height = edge_planes.shape[0]
    width = edge_planes.shape[1]
    score = np.zeros(n_pose)
    count = np.zeros(n_pose, dtype=np.int64)
    for p in prange(n_pose):
        R = poses[p]
        fs = focal_scale[p]
        e = np.zeros(1)
        s = 0.0
        c = 0
        for i in range(n):
            u, v, ok = _pose_pixel(R, points, i, cam, fs, width, height, mask)
            if not ok:
                continue
            sample_bicubic(edge_planes, u, v, e)
            s += lidar_weight[i] * e[0]
            c += 1
        score[p] = s
        count[p] = c
    return score, count


@njit(**_BATCH_FLAGS)
def nmi_batch_kernel(points: np.ndarray, lidar_bin: np.ndarray, intensity_planes: np.ndarray,
                     mask: np.ndarray, cam: np.ndarray, poses: np.ndarray, focal_scale: np.ndarray,
                     bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised mutual information (paper eq. 3) per pose between the lidar feature (pre-binned,
    ``lidar_bin`` int64 in [0, bins)) and the image intensity in [0, 1] (bicubic, (H, W, 1));
    returns (NMI, projected points). NMI is 0 where fewer than 2 points project."""
    n_pose = poses.shape[0]
    n = points.shape[0]
    height = intensity_planes.shape[0]
    width = intensity_planes.shape[1]
    out = np.zeros(n_pose)
    count = np.zeros(n_pose, dtype=np.int64)
    for p in prange(n_pose):
        R = poses[p]
        fs = focal_scale[p]
        hist = np.zeros((bins, bins))
        e = np.zeros(1)
        c = 0
        for i in range(n):
            u, v, ok = _pose_pixel(R, points, i, cam, fs, width, height, mask)
            if not ok:
                continue
            sample_bicubic(intensity_planes, u, v, e)
            b = int(e[0] * bins)
            b = min(max(b, 0), bins - 1)
            hist[lidar_bin[i], b] += 1.0
            c += 1
        count[p] = c
        if c < 2:
            continue
        out[p] = _nmi_from_hist(hist, float(c))
    return out, count


@njit(**NJIT_FLAGS)
def _nmi_from_hist(hist: np.ndarray, total: float) -> float:
    bins = hist.shape[0]
    h_joint = 0.0
    h_a = 0.0
    h_b = 0.0
    for a in range(bins):
        row = 0.0
        for b in range(bins):
            q = hist[a, b]
            row += q
            if q > 0.0:
                pq = q / total
                h_joint -= pq * math.log(pq)
        if row > 0.0:
            pr = row / total
            h_a -= pr * math.log(pr)
    for b in range(bins):
        col = 0.0
        for a in range(bins):
            col += hist[a, b]
        if col > 0.0:
            pc = col / total
            h_b -= pc * math.log(pc)
    if h_joint <= 0.0:
        return 0.0
    return (h_a + h_b) / h_joint


@njit(**_BATCH_FLAGS)
def gom_affine_batch_kernel(pixels_uv: np.ndarray, src_c2: np.ndarray, src_s2: np.ndarray,
                            src_mag: np.ndarray, grad_planes: np.ndarray, mask: np.ndarray,
                            affines: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GOM sums for a batch of 2-D affine maps ``affines`` (P, 2, 3) taking source pixels (N, 2)
    into the base image; source gradient orientations are carried through the affine's linear part.
    Returns (sum mu * alpha, sum mu, pixels in view) per affine."""
    n_pose = affines.shape[0]
    n = pixels_uv.shape[0]
    height = grad_planes.shape[0]
    width = grad_planes.shape[1]
    num = np.zeros(n_pose)
    den = np.zeros(n_pose)
    count = np.zeros(n_pose, dtype=np.int64)
    for p in prange(n_pose):
        A = affines[p]
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        if abs(det) < 1e-12:
            continue
        # gradients map by the inverse transpose of the linear part
        ia = A[1, 1] / det
        ib = -A[1, 0] / det
        ic = -A[0, 1] / det
        id_ = A[0, 0] / det
        s_num = 0.0
        s_den = 0.0
        c = 0
        for i in range(n):
            u = A[0, 0] * pixels_uv[i, 0] + A[0, 1] * pixels_uv[i, 1] + A[0, 2]
            v = A[1, 0] * pixels_uv[i, 0] + A[1, 1] * pixels_uv[i, 1] + A[1, 2]
            if not _in_view(u, v, width, height, mask):
                continue
            gx, gy = sample_bicubic2(grad_planes, u, v)
            m2 = gx * gx + gy * gy
            c += 1
            if m2 <= 1e-20:
                continue
            # source gradient direction from its double-angle form: rotate via half-angle vector
            ch = math.sqrt(max(0.0, 0.5 * (1.0 + src_c2[i])))
            sh = math.sqrt(max(0.0, 0.5 * (1.0 - src_c2[i])))
            if src_s2[i] < 0.0:
                sh = -sh
            tx = ia * ch + ib * sh
            ty = ic * ch + id_ * sh
            tn = tx * tx + ty * ty
            if tn <= 1e-20:
                continue
            c2 = (tx * tx - ty * ty) / tn
            s2 = 2.0 * tx * ty / tn
            mu = math.sqrt(m2) * src_mag[i]
            cos2d = ((gx * gx - gy * gy) * c2 + 2.0 * gx * gy * s2) / m2
            s_num += mu * (cos2d + 1.0)
            s_den += mu
        num[p] = s_num
        den[p] = s_den
        count[p] = c
    return num, den, count
