"""numba metric kernels against slow NumPy references, and the GOM landscape on a synthetic scene."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.transforms import apply, from_xyz_rpy
from fleetcal.stages.calibration import (
    CalibrationProblem,
    GomScorer,
    GradientPlanes,
    LevinsonScorer,
    NmiScorer,
    SolverConfig,
    calibrate_affine,
    compute_sphere_gradients,
    score_landscape,
)
from fleetcal.stages.calibration import metric_kernels as mk
from fleetcal.stages.calibration.affine import affine_matrices
from fleetcal.stages.calibration.gom_channels import GomChannels
from fleetcal.stages.calibration.metrics import (
    ALL_VALID,
    blur_thinning,
    gom_reference,
    least_blur_px,
    project_points,
    sample_bicubic,
)
from fleetcal.stages.calibration.sphere_gradients import sphere_coordinates, sphere_neighbours
from fleetcal.stages.image_gradients import (
    QUANTA_PER_GREY_LEVEL,
    compute_image_gradients,
    quantised,
    sampling_stride,
    subsampled,
)
from tests.test_calibration_synthetic import (
    make_scene,
    perturb,
    render_image,
    synthetic_camera,
    synthetic_frame,
    true_T_camera_lidar,
)

K = np.array([[600.0, 0.3, 330.0], [0.0, 590.0, 245.0], [0.0, 0.0, 1.0]])
CAMERAS = {
    "none": CameraModel(640, 480, K, np.zeros(0), "none"),
    "plumb_bob": CameraModel(640, 480, K, np.array([-0.28, 0.09, 0.001, -0.0015, -0.01]), "plumb_bob"),
    "rational_polynomial": CameraModel(
        640, 480, K, np.array([0.5, -0.1, 0.001, 0.002, 0.01, 0.8, -0.05, 0.02]), "rational_polynomial"),
    "equidistant": CameraModel(640, 480, np.array([[280.0, 0, 320], [0, 280.0, 240], [0, 0, 1]]),
                               np.array([0.05, -0.01, 0.002, -0.0005]), "equidistant"),
    "cylindrical": CameraModel(2000, 500, np.array([[318.0, 0, 1000], [0, 300.0, 250], [0, 0, 1]]),
                               np.zeros(0), "cylindrical"),
    # zero coefficients (rectified images) are scored as a pinhole: the same pixels, no radius limit
    "plumb_bob zero": CameraModel(640, 480, K, np.zeros(5), "plumb_bob"),
    "rational_polynomial zero": CameraModel(640, 480, K, np.zeros(8), "rational_polynomial"),
}


def random_points(n: int, seed: int) -> NDArray[np.float64]:
    """Points all around the camera, including behind it and on its axis."""
    rng = np.random.default_rng(seed)
    pts = rng.standard_normal((n, 3)) * [4.0, 3.0, 6.0] + [0.0, 0.0, 3.0]
    pts[0] = [0.0, 0.0, 5.0]
    pts[1] = [0.0, 0.0, -5.0]
    return pts


@pytest.mark.parametrize("model", list(CAMERAS))
def test_projection_matches_camera_model(model: str) -> None:
    camera = CAMERAS[model]
    pts = random_points(4000, seed=1)
    uv_ref, valid_ref = camera.project(pts)
    uv, valid = project_points(pts, camera)
    assert valid.sum() > 300
    np.testing.assert_array_equal(valid, valid_ref)
    np.testing.assert_allclose(uv[valid], uv_ref[valid], atol=1e-9)


def keys_reference(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Keys (a = -0.5) kernel value at distance t."""
    a = -0.5
    t = np.abs(t)
    return np.where(t <= 1, (a + 2) * t**3 - (a + 3) * t**2 + 1,
                    np.where(t < 2, a * t**3 - 5 * a * t**2 + 8 * a * t - 4 * a, 0.0))


def bicubic_reference(image: NDArray[np.float64], uv: NDArray[np.float64]) -> NDArray[np.float64]:
    """Slow Keys bicubic: sum over the 4x4 taps with the kernel evaluated at true distances."""
    h, w = image.shape
    out = np.zeros(len(uv))
    for k, (u, v) in enumerate(uv):
        iu, iv = int(np.floor(u)), int(np.floor(v))
        for row in range(iv - 1, iv + 3):
            for col in range(iu - 1, iu + 3):
                weight = keys_reference(np.array(u - col)) * keys_reference(np.array(v - row))
                out[k] += weight * image[min(max(row, 0), h - 1), min(max(col, 0), w - 1)]
    return out


def test_bicubic_matches_reference_and_reproduces_cubics() -> None:
    rng = np.random.default_rng(2)
    image = rng.standard_normal((30, 40))
    uv = np.column_stack([rng.uniform(-0.5, 39.5, 500), rng.uniform(-0.5, 29.5, 500)])
    uv[:4] = np.array([[0, 0], [39, 29], [10.0, 12.0], [17.25, 3.75]])
    ref = bicubic_reference(image, uv)
    got = sample_bicubic(image, uv)[:, 0]
    np.testing.assert_allclose(got, ref, atol=1e-10)
    assert got[2] == pytest.approx(image[12, 10])  # interpolating: exact at pixel centres
    # Keys a=-0.5 reproduces quadratics exactly away from the border
    vv, uu = np.mgrid[0:30, 0:40].astype(np.float64)
    quad = 0.5 * uu**2 - 0.3 * uu * vv + 2 * vv + 1
    inner = np.column_stack([rng.uniform(2, 37, 200), rng.uniform(2, 27, 200)])
    truth = 0.5 * inner[:, 0] ** 2 - 0.3 * inner[:, 0] * inner[:, 1] + 2 * inner[:, 1] + 1
    np.testing.assert_allclose(sample_bicubic(quad, inner)[:, 0], truth, atol=1e-9)
    # two channels, constant image
    planes = np.stack([np.full((30, 40), 3.0), np.full((30, 40), -1.0)], axis=2)
    np.testing.assert_allclose(sample_bicubic(planes, uv), np.tile([3.0, -1.0], (len(uv), 1)), atol=1e-12)


def gom_numpy(points: NDArray[np.float64], lgx: NDArray[np.float64], lgy: NDArray[np.float64],
              lmag: NDArray[np.float64], igx: NDArray[np.float64], igy: NDArray[np.float64],
              camera: CameraModel, T: NDArray[np.float64],
              mask: NDArray[np.bool_] | None = None) -> tuple[float, int]:
    """Reference GOM: CameraModel.project, reference bicubic, explicit angles (eq. 9-11); points whose nearest
    pixel is outside ``mask`` (H, W) are left out."""
    uv, valid = camera.project(apply(T, points))
    h, w = igx.shape
    valid &= (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
    if mask is not None:
        near = np.floor(uv[valid] + 0.5).astype(np.int64)
        valid[np.flatnonzero(valid)] = mask[near[:, 1], near[:, 0]]
    gx = bicubic_reference(igx, uv[valid])
    gy = bicubic_reference(igy, uv[valid])
    return gom_reference(lgx[valid], lgy[valid], lmag[valid], gx, gy), int(valid.sum())


@pytest.mark.parametrize("model", ["plumb_bob", "plumb_bob zero", "equidistant", "cylindrical", "masked"])
def test_gom_kernel_matches_numpy_reference(model: str) -> None:
    camera = CAMERAS["plumb_bob" if model == "masked" else model]
    rng = np.random.default_rng(3)
    pts = random_points(800, seed=4)
    lgx, lgy, lmag = rng.standard_normal(800), rng.standard_normal(800), rng.random(800)
    shape = (camera.height, camera.width)
    # float32, as Sobel gives them and the scorer keeps them: the reference then sees the same values
    igx = np.asarray(cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 2.0), dtype=np.float32)
    igy = np.asarray(cv2.GaussianBlur(rng.standard_normal(shape), (0, 0), 2.0), dtype=np.float32)
    mask = None
    if model == "masked":  # the left third and a band of rows invalid
        mask = np.ones(shape, dtype=bool)
        mask[:, : camera.width // 3] = False
        mask[100:140] = False
    scorer = GomScorer(pts, lgx, lgy, lmag, GradientPlanes.of(igx, igy, camera, mask), camera)
    poses = np.stack([np.eye(4), from_xyz_rpy(0.1, -0.05, 0.2, 3, -2, 10), from_xyz_rpy(0, 0, 0, 0, 90, 0)])
    batch = scorer.score(poses)
    for k, T in enumerate(poses):
        ref, n = gom_numpy(pts, lgx, lgy, lmag, igx, igy, camera, T, mask)
        assert batch.counts[k] == n
        assert batch.scores[k] == pytest.approx(ref, abs=1e-6)  # float32 taps: about 1e-8 off
    if mask is not None:  # the mask left points out
        assert sum(gom_numpy(pts, lgx, lgy, lmag, igx, igy, camera, T)[1] for T in poses) > batch.counts.sum() + 50
    # aligned gradients score 1, perpendicular 0, uncorrelated about 0.5
    uv, valid = camera.project(pts)
    inside = valid & (uv[:, 0] <= camera.width - 1) & (uv[:, 1] <= camera.height - 1)
    g = sample_bicubic(np.stack([igx, igy], 2), uv[inside])
    assert gom_reference(g[:, 0], g[:, 1], np.ones(len(g)), -g[:, 0], -g[:, 1]) == pytest.approx(1.0)
    perpendicular = gom_reference(-g[:, 1], g[:, 0], np.ones(len(g)), g[:, 0], g[:, 1])
    assert perpendicular == pytest.approx(0.0, abs=1e-12)
    assert batch.scores[0] == pytest.approx(0.5, abs=0.1)  # unrelated gradients: chance level


def test_gom_scorer_against_blurred_planes_shares_the_lidar_side() -> None:
    """``subset(every third point).against(image.blurred(s))`` scores like a scorer built from every third point
    and the Gaussian-blurred gradients, without copying the frame's planes for each channel."""
    camera = CAMERAS["plumb_bob"]
    rng = np.random.default_rng(5)
    pts = random_points(900, seed=6)
    lgx, lgy, lmag = rng.standard_normal(900), rng.standard_normal(900), rng.random(900)
    shape = (camera.height, camera.width)
    igx, igy = rng.standard_normal(shape), rng.standard_normal(shape)
    image = GradientPlanes.of(igx, igy, camera)
    scorer = GomScorer(pts, lgx, lgy, lmag, image, camera)
    twin = scorer.subset(np.arange(0, 900, 3)).against(image.blurred(3.0))
    blur = [cv2.GaussianBlur(g, (0, 0), 3.0) for g in (igx, igy)]
    fresh = GomScorer(pts[::3], lgx[::3], lgy[::3], lmag[::3], GradientPlanes.of(*blur, camera), camera)
    poses = np.stack([np.eye(4), from_xyz_rpy(0.05, 0.0, -0.1, 1, 2, -3)])
    np.testing.assert_allclose(twin.score(poses).scores, fresh.score(poses).scores, atol=1e-12)
    assert twin.score(poses).counts.tolist() == fresh.score(poses).counts.tolist()
    assert scorer.image.planes is image.planes and twin.image.mask is image.mask
    assert not np.allclose(twin.score(poses).scores, scorer.score(poses).scores)


def test_blurred_along_smooths_one_image_direction_only() -> None:
    """Across-ring smoothing along v: a horizontal line of gradient spreads into a Gaussian of the given
    sigma along v, while gradients constant along v (a vertical edge) are left as they were."""
    camera = CAMERAS["plumb_bob"]
    h, w = camera.height, camera.width
    gy = np.zeros((h, w))
    gy[240, :] = 1.0  # a horizontal edge's gradient
    gx = np.zeros((h, w))
    gx[:, 320] = 1.0  # a vertical edge's gradient
    smoothed = GradientPlanes.of(gx, gy, camera).blurred_along(np.array([0.0, 1.0]), 4.0)
    profile = smoothed.planes[:, 100, 1]
    rows = np.arange(h)
    assert profile.sum() == pytest.approx(1.0, rel=1e-3)
    assert np.sqrt(np.sum(profile * (rows - 240.0) ** 2) / profile.sum()) == pytest.approx(4.0, rel=0.05)
    np.testing.assert_allclose(smoothed.planes[:, :, 0], gx, atol=1e-9)
    across = GradientPlanes.of(gx, gy, camera).blurred_along(np.array([1.0, 0.0]), 4.0)  # along u instead
    np.testing.assert_allclose(across.planes[:, :, 1], gy, atol=1e-9)
    assert across.planes[100, 320, 0] < 0.15


def test_gom_empty_and_bad_inputs() -> None:
    camera = CAMERAS["plumb_bob"]
    zeros = np.zeros((camera.height, camera.width))
    image = GradientPlanes.of(zeros, zeros, camera)
    behind = np.array([[0.0, 0.0, -5.0]] * 3)
    batch = GomScorer(behind, np.ones(3), np.ones(3), np.ones(3), image, camera).score(np.eye(4))
    assert batch.counts[0] == 0 and batch.scores[0] == 0.0
    with pytest.raises(ProcessingError, match="NaN"):
        GomScorer(np.array([[np.nan, 0, 1.0]]), np.ones(1), np.ones(1), np.ones(1), image, camera)
    with pytest.raises(ProcessingError, match="does not match camera"):
        GradientPlanes.of(zeros[:10], zeros[:10], camera)
    with pytest.raises(ProcessingError, match="does not match camera"):
        wide = np.zeros((500, 2000))
        GomScorer(behind, np.ones(3), np.ones(3), np.ones(3), GradientPlanes.of(wide, wide, CAMERAS["cylindrical"]),
                  camera)
    with pytest.raises(ProcessingError, match="values for"):
        GomScorer(behind, np.ones(2), np.ones(3), np.ones(3), image, camera)


def test_nmi_and_levinson_match_numpy_reference() -> None:
    camera = CAMERAS["none"]
    rng = np.random.default_rng(5)
    pts = random_points(3000, seed=6)
    values = rng.random(3000)
    intensity = np.clip(cv2.GaussianBlur(rng.random((480, 640)), (0, 0), 3.0) * 2 - 0.5, 0, 1).astype(np.float32)
    T = from_xyz_rpy(0.05, 0, 0, 1, 2, -1)
    uv, valid = camera.project(apply(T, pts))
    valid &= (uv[:, 0] <= 639) & (uv[:, 1] <= 479)
    sampled = bicubic_reference(intensity, uv[valid])
    bins = 16
    hist, _, _ = np.histogram2d(np.clip((values[valid] * bins).astype(int), 0, bins - 1),
                                np.clip((sampled * bins).astype(int), 0, bins - 1), bins=bins,
                                range=[[0, bins], [0, bins]])
    p = hist / hist.sum()

    def entropy(q: NDArray[np.float64]) -> float:
        q = q[q > 0]
        return float(-np.sum(q * np.log(q)))

    nmi_ref = (entropy(p.sum(1)) + entropy(p.sum(0))) / entropy(p.ravel())
    nmi = NmiScorer(pts, values, intensity, camera, bins=bins).score(T)
    assert nmi.scores[0] == pytest.approx(nmi_ref, rel=1e-9)
    assert 1.0 <= nmi.scores[0] <= 2.0
    grey_u8 = np.rint(intensity * 255).astype(np.uint8)  # build_frame keeps the equalised grey as 8 bits
    as_u8 = NmiScorer(pts, values, grey_u8, camera, bins=bins).score(T).scores[0]
    assert as_u8 == NmiScorer(pts, values, grey_u8 / np.float32(255), camera, bins=bins).score(T).scores[0]
    assert as_u8 == pytest.approx(nmi_ref, rel=0.02)
    lev = LevinsonScorer(pts, values, intensity, camera).score(T)
    assert lev.scores[0] == pytest.approx(np.sum(values[valid] * sampled) / values.sum(), rel=1e-9)


def test_sphere_gradients_follow_image_axes() -> None:
    """A value ramp increasing to the right (camera +x) gives gradients pointing along +u, and a ramp
    increasing downwards gives +v: the sphere is oriented like the image."""
    az, el = np.meshgrid(np.radians(np.linspace(-20, 20, 81)), np.radians(np.linspace(-10, 10, 41)))
    pts_cam = np.column_stack([np.sin(az.ravel()) * np.cos(el.ravel()), np.sin(el.ravel()),
                               np.cos(az.ravel()) * np.cos(el.ravel())]) * 10.0
    T = true_T_camera_lidar()
    pts_lidar = apply(np.asarray(np.linalg.inv(T), dtype=np.float64), pts_cam)
    right = compute_sphere_gradients(pts_lidar, pts_cam[:, 0], T)
    down = compute_sphere_gradients(pts_lidar, pts_cam[:, 1], T)
    inner = (np.abs(az.ravel()) < np.radians(18)) & (np.abs(el.ravel()) < np.radians(8))
    assert np.all(np.abs(np.cos(right.orientation[inner])) > 0.99) and np.all(right.gx[inner] > 0)
    assert np.all(np.abs(np.sin(down.orientation[inner])) > 0.99) and np.all(down.gy[inner] > 0)
    # Algorithm 1 by hand for one point
    uvs = sphere_coordinates(pts_cam)
    nb = sphere_neighbours(uvs, 8)
    i = int(np.flatnonzero(inner)[10])
    d = uvs[i] - uvs[nb[i]]
    dv = pts_cam[i, 0] - pts_cam[nb[i], 0]
    assert right.gx[i] == pytest.approx(np.sum(dv * d[:, 0]) / 8)
    assert right.magnitude[i] == pytest.approx(np.sum(np.abs(dv)) / 8)


def test_gom_is_maximal_at_truth_on_synthetic_scene() -> None:
    frame = synthetic_frame(0, blur_sigma_px=2.0)
    T_true = true_T_camera_lidar()
    problem = CalibrationProblem([frame], T_true, SolverConfig(search_deg=3.0, search_m=0.3))
    at_truth = problem.evaluate(np.zeros((1, 6)))[0]
    assert at_truth > 0.75
    rng = np.random.default_rng(7)
    off = []
    for _ in range(12):
        x = np.zeros(6)
        axis = rng.standard_normal(3)
        x[:3] = axis / np.linalg.norm(axis) * 1.0  # 1 degree
        off.append(x)
        y = np.zeros(6)
        shift = rng.standard_normal(3)
        y[3:] = shift / np.linalg.norm(shift) * 0.05  # 5 cm
        off.append(y)
    scores = problem.evaluate(np.array(off))
    assert np.all(scores < at_truth), scores
    assert at_truth - scores.max() > 0.002
    land = score_landscape(problem, np.zeros(6), axes=(0, 1), half_width=(2.0, 2.0), steps=9)
    assert land.argmax_offsets() == (0.0, 0.0)
    assert land.scores.shape == (9, 9)


def test_gradients_kept_at_the_blurs_stride_score_as_the_whole_image() -> None:
    """An image blurred by 3.2 px keeps its gradients at every second pixel (a quarter of the memory): GOM and
    Levinson score within 1.1e-3 / 3e-4 of the whole image's gradients at 61 poses up to 2 deg / 10 cm off the
    truth (GOM spans 0.37 over them), with the same best pose; planes blurred from the kept ones are the whole
    image's planes blurred, at the kept pixels."""
    full = synthetic_frame(0, blur_sigma_px=3.2)
    stride = sampling_stride(3.2)
    kept = replace(full, gradients=subsampled(full.gradients, stride))
    assert stride == 2 and kept.gradients.gxy.shape == (240, 320, 2)
    rng = np.random.default_rng(3)
    x = np.vstack([np.zeros(6), rng.uniform(-1, 1, (60, 6)) * [2, 2, 2, 0.1, 0.1, 0.1]])
    for metric, tolerance in (("gom", 1.1e-3), ("levinson", 3e-4)):
        config = SolverConfig(search_deg=3.0, search_m=0.3, metric=metric)
        whole = CalibrationProblem([full], true_T_camera_lidar(), config).evaluate(x)
        at_stride = CalibrationProblem([kept], true_T_camera_lidar(), config).evaluate(x)
        assert np.max(np.abs(whole - at_stride)) < tolerance, metric
        assert np.argmax(whole) == np.argmax(at_stride)
    camera = full.camera
    blurred = GradientPlanes.of_stacked(full.gradients.gxy, camera).blurred(6.0)
    blurred_kept = GradientPlanes.of_stacked(kept.gradients.gxy, camera, stride=stride).blurred(6.0)
    assert blurred_kept.stride == 2 and blurred_kept.mask is ALL_VALID
    valid = np.ones((camera.height, camera.width), dtype=bool)
    valid[:, :31] = False
    masked = GradientPlanes.of_stacked(kept.gradients.gxy, camera, valid, stride=stride).blurred(6.0)
    np.testing.assert_array_equal(masked.mask, valid[::2, ::2])
    scale = float(np.abs(blurred.planes).max())
    np.testing.assert_allclose(blurred_kept.planes[5:-5, 5:-5], blurred.planes[::2, ::2][5:-5, 5:-5], atol=0.03 * scale)
    with pytest.raises(ProcessingError, match="kept at a stride of 2 pixels"):
        GradientPlanes.of_stacked(full.gradients.gxy, camera, stride=2)


def test_int16_gradients_score_as_the_float_ones_in_half_the_memory() -> None:
    """Gradients held as int16 steps of 1/32 grey level (``quantised``) read back within 1/64 grey level, are
    scored in place (no float copy) and exactly as float32 planes of the same steps, and score within 1e-5 of the
    float gradients at 61 poses, with and without ring-smoothed twins (planes filtered from the int16 ones); a
    swarm's frames are scored from float32 copies of them, to the same scores."""
    frame = synthetic_frame(0)
    steps = quantised(frame.gradients)
    assert steps.gxy.dtype == np.int16 and steps.gxy.nbytes * 2 == frame.gradients.gxy.nbytes
    assert steps.scale == QUANTA_PER_GREY_LEVEL and quantised(steps) is steps
    assert np.max(np.abs(steps.gx - frame.gradients.gx)) <= 1 / 64 + 1e-4
    np.testing.assert_allclose(steps.magnitude, frame.gradients.magnitude, atol=0.03)
    camera = frame.camera
    as_float = GradientPlanes.of_stacked(steps.gxy.astype(np.float32), camera)
    as_steps = GradientPlanes.of_stacked(steps.gxy, camera)
    assert np.shares_memory(as_steps.planes, steps.gxy)
    rng = np.random.default_rng(5)
    pts = rng.uniform([-4, -3, 4], [4, 3, 12], (3000, 3))
    lgx, lgy = rng.normal(size=3000), rng.normal(size=3000)
    T = np.stack([from_xyz_rpy(*rng.uniform(-0.05, 0.05, 3), *rng.uniform(-0.02, 0.02, 3)) for _ in range(8)])
    exact = [GomScorer(pts, lgx, lgy, np.hypot(lgx, lgy), planes, camera).score(T).scores
             for planes in (as_float, as_steps)]
    np.testing.assert_array_equal(exact[0], exact[1])
    stepped = replace(frame, gradients=steps)
    x = np.vstack([np.zeros(6), rng.uniform(-1, 1, (60, 6)) * [2, 2, 2, 0.1, 0.1, 0.1]])
    for smoothing in ("off", "on"):
        config = SolverConfig(search_deg=3.0, search_m=0.3, ring_smoothing=smoothing)
        floats = CalibrationProblem([frame], true_T_camera_lidar(), config).evaluate(x)
        problem = CalibrationProblem([stepped], true_T_camera_lidar(), config)
        np.testing.assert_allclose(problem.evaluate(x), floats, atol=1e-5)
        swarm = problem.search_view(0)  # the swarm's frames sampled from float32 copies, to the same scores
        assert problem.full.scorers[0][0].image.planes.dtype == np.int16
        assert all(s.image.planes.dtype == np.float32 for s in swarm.scorers[0])
        assert problem.search_view(0) is swarm
        np.testing.assert_array_equal(problem.evaluate(x, swarm), problem.evaluate(x))


@pytest.mark.parametrize("direction_deg, sigma_px, stride", [(90.0, 10.0, 2), (90.0, 10.0, 1), (60.0, 12.0, 1),
                                                           (45.0, 9.0, 2), (0.0, 6.0, 1), (90.0, 1.0, 2)])
def test_blur_thinning_keeps_the_widest_strides_the_two_blurs_allow(direction_deg: float, sigma_px: float,
                                                                    stride: int) -> None:
    """The Gaussian of covariance S = b^2 I + sigma^2 d d^T (b: the least blur of the planes' stride) responds on
    the thinned grid's Nyquist lines (1 / (2 s) cycles per pixel along u, any v; and along v) at most 1e-3 of its
    peak, and above it one stride of the planes further (or the thinning is 1)."""
    d = np.array([np.cos(np.radians(direction_deg)), np.sin(np.radians(direction_deg))])
    b = least_blur_px(stride)
    S = b**2 * np.eye(2) + sigma_px**2 * np.outer(d, d)
    f_other = np.linspace(-1.0, 1.0, 4001)

    def peak_on_nyquist(s_px: int, axis: int) -> float:
        f = np.zeros((f_other.size, 2))
        f[:, axis], f[:, 1 - axis] = 1.0 / (2.0 * s_px), f_other
        return float(np.max(np.exp(-2.0 * np.pi**2 * np.einsum("ni,ij,nj->n", f, S, f))))

    for axis, k in enumerate(blur_thinning(d, sigma_px, b, stride)):
        assert k == 1 or peak_on_nyquist(k * stride, axis) <= 1e-3
        assert peak_on_nyquist((k + 1) * stride, axis) > 1e-3
    assert blur_thinning(np.array([0.0, 1.0]), 10.0, least_blur_px(2), 2) == (1, 4)  # 1600 px images, 32 beams


def test_planes_smoothed_across_rings_and_thinned_score_as_the_whole_planes() -> None:
    """Gradients smoothed by 10 px along v and thinned to every eighth row (an eighth of the memory) are the
    whole smoothed planes at the kept rows, and score, as a twin of the frame's GOM scorer, within 2.5e-3 (1e-3
    on average) of them at 61 poses up to 2 deg / 10 cm off, where the twin's GOM spans 0.36, with the same best
    pose; in one pass with the scan's channels as one by one."""
    frame = synthetic_frame(0)
    camera = frame.camera
    image = GradientPlanes.of_stacked(frame.gradients.gxy, camera)
    whole = image.blurred_along(np.array([0.0, 1.0]), 10.0)
    thinned = image.blurred_along(np.array([0.0, 1.0]), 10.0, thinned=True)
    assert thinned.strides == (1, 8) and thinned.planes.shape == (60, 640, 2) and thinned.mask is ALL_VALID
    valid = np.ones((camera.height, camera.width), dtype=bool)
    valid[:37] = False
    masked = GradientPlanes.of_stacked(frame.gradients.gxy, camera, valid).blurred_along(np.array([0.0, 1.0]), 10.0,
                                                                                          thinned=True)
    np.testing.assert_array_equal(masked.mask, valid[::8])
    np.testing.assert_array_equal(thinned.planes, whole.planes[::8])
    scorer = CalibrationProblem([frame], true_T_camera_lidar(), SolverConfig()).scorers[0][0]
    assert isinstance(scorer, GomScorer) and scorer.image.planes is frame.gradients.gxy
    points = scorer.points
    poses = np.stack([true_T_camera_lidar()] + [perturb(true_T_camera_lidar(), 2.0, 0.1, 40 + k) for k in range(60)])
    at_whole, at_thinned = scorer.against(whole).score(poses), scorer.against(thinned).score(poses)
    gap = np.abs(at_whole.scores - at_thinned.scores)
    assert gap.max() < 2.5e-3 and gap.mean() < 1e-3 and np.ptp(at_whole.scores) > 0.3
    assert np.argmax(at_whole.scores) == np.argmax(at_thinned.scores)
    assert np.max(np.abs(at_whole.counts - at_thinned.counts)) <= 0.01 * at_whole.counts.max()
    together = GomChannels(np.ones((1, points.shape[0]), dtype=bool), [scorer], thinned).score(poses)
    np.testing.assert_array_equal(together[1].counts, at_thinned.counts)
    np.testing.assert_allclose(together[1].scores, at_thinned.scores, rtol=0, atol=1e-12)
    with pytest.raises(ProcessingError, match="kept at a stride of 1 x 4 pixels"):
        scorer.against(GradientPlanes(thinned.planes, thinned.mask, 1, 4))


def test_camera_stage_keeps_gradients_at_the_stride_of_its_blur() -> None:
    """A 1920 x 1208 image (default blur 3.1 px) keeps its gradients at every second pixel; a 1242 px one (2 px)
    at every pixel."""
    from fleetcal.pipeline.frames import CameraFrame
    from fleetcal.stages.calibration.frame import camera_feature_stage, default_blur_sigma_px

    for width, height, stride in ((1920, 1208, 2), (1242, 375, 1)):
        camera = CameraModel(width, height, K, np.zeros(5), "plumb_bob")
        image = np.random.default_rng(1).integers(0, 256, (height, width), dtype=np.uint8)
        features = camera_feature_stage(CameraFrame(1, "/cam", "cam", image, "mono8", camera=camera))
        assert sampling_stride(default_blur_sigma_px(width)) == stride == features.gradients.stride
        assert features.gradients.gxy.shape == (-(-height // stride), -(-width // stride), 2)


def test_affine_gom_kernel_matches_numpy_reference() -> None:
    """The camera-camera GOM kernel against the reference: pixels mapped by each affine, the base gradient sampled
    by the reference bicubic, the moving gradient carried by the inverse transpose of the map's linear part."""
    rng = np.random.default_rng(7)
    height, width = 40, 50
    planes = rng.normal(size=(height, width, 2))
    uv = rng.uniform([0.0, 0.0], [width - 1.0, height - 1.0], size=(300, 2))
    gx, gy = rng.normal(size=300), rng.normal(size=300)
    theta = np.arctan2(gy, gx)
    params = np.array([[0.0, 0.0, 0.0, 1.0, 1.0, 0.0], [2.5, -1.2, 4.0, 1.03, 0.98, 0.02]])
    affines = affine_matrices(params, ((width - 1) / 2, (height - 1) / 2))
    num, den, count = mk.gom_affine_batch_kernel(uv, np.cos(2 * theta), np.sin(2 * theta), np.hypot(gx, gy),
                                                 planes, np.ones((height, width), np.uint8), affines)
    for k, A in enumerate(affines):
        mapped = uv @ A[:, :2].T + A[:, 2]
        inside = np.all((mapped >= 0) & (mapped <= [width - 1.0, height - 1.0]), axis=1)
        carried = np.column_stack([gx, gy])[inside] @ np.linalg.inv(A[:, :2])
        image_gx = bicubic_reference(planes[:, :, 0], mapped[inside])
        image_gy = bicubic_reference(planes[:, :, 1], mapped[inside])
        assert count[k] == inside.sum()
        assert num[k] / (2 * den[k]) == pytest.approx(
            gom_reference(carried[:, 0], carried[:, 1], np.hypot(gx, gy)[inside], image_gx, image_gy), abs=1e-9)


def test_affine_camera_camera_recovers_known_warp() -> None:
    camera = synthetic_camera()
    image = render_image(make_scene(4), camera, true_T_camera_lidar())
    params = np.array([6.0, -4.0, 1.5, 1.02, 0.99, 0.01])
    centre = ((camera.width - 1) / 2, (camera.height - 1) / 2)
    A = affine_matrices(params, centre)[0]
    moving = cv2.warpAffine(image, cv2.invertAffineTransform(A), (camera.width, camera.height),
                            flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    moving = 255 - moving  # the other modality: inverted contrast
    base = compute_image_gradients(image, blur_sigma_px=1.5)
    mov = compute_image_gradients(moving, blur_sigma_px=1.5)
    result = calibrate_affine(base.gx, base.gy, mov.gx, mov.gy, search_px=12, search_deg=3,
                              keep_fraction=0.05, n_particles=60, max_iterations=60, seed=0)
    grid = np.array([[100.0, 100.0], [500.0, 100.0], [320.0, 400.0]])
    mapped_true = grid @ A[:, :2].T + A[:, 2]
    mapped = grid @ result.A_base_moving[:, :2].T + result.A_base_moving[:, 2]
    assert np.max(np.linalg.norm(mapped - mapped_true, axis=1)) < 0.5
    assert result.score > result.initial_score
