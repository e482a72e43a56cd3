"""Memory-lean registration prep: voxel downsampling first (sort on int64 keys, float32 kept), the
voxel cap of ``prepare_pointset``, and equality with the plain NumPy (np.unique) reference."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError
from fleetcal.stages.registration import RegistrationConfig, prepare_pointset, voxel_downsample
from fleetcal.stages.registration.voxel import coarsen_keys, voxel_downsample_capped, voxel_keys


def unique_reference(
    points: NDArray[np.floating], voxel: float, channels: NDArray[np.floating]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """The previous implementation: float64 copy, np.unique(return_inverse), bincount per column."""
    pts = np.asarray(points, dtype=np.float64)
    cells = np.floor(pts / voxel).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    values = np.concatenate([pts, np.asarray(channels, dtype=np.float64)], axis=1)
    sums = np.stack([np.bincount(inverse, weights=values[:, c]) for c in range(values.shape[1])], axis=1)
    means = sums / counts[:, None]
    return means[:, :3], means[:, 3:], counts


def sort_rows(*arrays: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    order = np.lexsort(arrays[0].T[::-1])
    return [a[order] for a in arrays]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_voxel_downsample_equals_unique_reference_bit_for_bit(dtype: type) -> None:
    rng = np.random.default_rng(3)
    pts: NDArray[np.floating] = rng.uniform(-20, 20, (50_000, 3)).astype(dtype)
    ch: NDArray[np.floating] = rng.random((50_000, 2)).astype(dtype)
    out_pts, out_ch, counts = voxel_downsample(pts, 0.5, ch)
    ref_pts, ref_ch, ref_counts = unique_reference(pts, 0.5, ch)
    assert out_pts.dtype == np.float64 and out_pts.shape == ref_pts.shape
    got = sort_rows(out_pts, out_ch, counts.astype(np.float64))
    want = sort_rows(ref_pts, ref_ch, ref_counts.astype(np.float64))
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)  # same summation order: identical floats
    assert counts.sum() == 50_000


def test_voxel_downsample_valid_mask_equals_filtering_first() -> None:
    rng = np.random.default_rng(4)
    pts = rng.uniform(-5, 5, (20_000, 3)).astype(np.float32)
    ch = rng.random((20_000, 1))
    pts[::7] = np.nan
    ch[::11] = np.inf
    valid = np.asarray(np.isfinite(pts).all(axis=1) & np.isfinite(ch).all(axis=1))
    got = voxel_downsample_capped(pts, 0.3, ch, valid=valid)
    want = voxel_downsample(pts[valid], 0.3, ch[valid])
    for g, w in zip(got[:3], want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert got[3] == 0.3
    # all invalid: empty output; voxel 0: the valid points unchanged
    none = voxel_downsample_capped(pts, 0.3, ch, valid=np.zeros(20_000, dtype=bool))
    assert none[0].shape == (0, 3) and none[2].shape == (0,)
    raw = voxel_downsample_capped(pts, 0.0, ch, valid=valid)
    np.testing.assert_array_equal(raw[0], pts[valid].astype(np.float64))


def test_coarsen_keys_equals_keys_of_the_doubled_grid() -> None:
    rng = np.random.default_rng(5)
    pts = rng.uniform(-300, 300, (10_000, 3))
    for levels in (1, 3):
        coarse = coarsen_keys(voxel_keys(pts, 0.25), levels)
        cells = np.floor(np.floor(pts / 0.25) / 2**levels).astype(np.int64)
        # equal coarse keys <=> equal coarse cells
        _, inv_keys = np.unique(coarse, return_inverse=True)
        _, inv_cells = np.unique(cells, axis=0, return_inverse=True)
        pairs = np.unique(np.stack([inv_keys.ravel(), inv_cells.ravel()], axis=1), axis=0)
        assert pairs.shape[0] == np.unique(inv_keys).shape[0] == np.unique(inv_cells).shape[0]
    invalid = np.array([-1, 5], dtype=np.int64)
    assert coarsen_keys(invalid, 2)[0] == -1


def test_voxel_cap_doubles_the_voxel_until_it_fits() -> None:
    rng = np.random.default_rng(6)
    pts = rng.uniform(-10, 10, (200_000, 3)).astype(np.float32)  # a volume: ~8x fewer voxels per doubling
    ch = rng.random((200_000, 1)).astype(np.float32)
    uncapped = voxel_downsample(pts, 0.1, ch)[0].shape[0]
    assert uncapped > 150_000
    out_pts, _, counts, voxel = voxel_downsample_capped(pts, 0.1, ch, max_voxels=5_000)
    assert out_pts.shape[0] <= 5_000
    levels = round(np.log2(voxel / 0.1))
    assert voxel == pytest.approx(0.1 * 2**levels) and levels >= 1
    # one level less would not have fitted
    assert voxel_downsample(pts, voxel / 2, ch)[0].shape[0] > 5_000
    # the means are those of the original points over the coarse cells (grid aligned at the origin)
    cells = np.floor(np.floor(pts.astype(np.float64) / 0.1) / 2**levels).astype(np.int64)
    _, inverse, ref_counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    ref = np.stack([np.bincount(inverse.ravel(), weights=pts[:, c]) for c in range(3)], axis=1) / ref_counts[:, None]
    got, want = sort_rows(out_pts, counts.astype(np.float64)), sort_rows(ref, ref_counts.astype(np.float64))
    np.testing.assert_allclose(got[0], want[0], atol=1e-9)
    np.testing.assert_array_equal(got[1], want[1])
    assert counts.sum() == 200_000
    with pytest.raises(ConfigError):
        voxel_downsample_capped(pts, 0.1, max_voxels=0)


def test_prepare_pointset_caps_points_and_counts_drops(caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(7)
    pts = rng.uniform(-10, 10, (60_000, 3)).astype(np.float32)
    pts[:100] = np.nan
    intensity = rng.random(60_000).astype(np.float32)
    config = RegistrationConfig(method="mcgicp", channels="intensity", voxel_size_m=0.1, k_neighbors=10)
    with caplog.at_level(logging.WARNING, logger="fleetcal.stages.registration.pointset"):
        capped = prepare_pointset(pts, {"intensity": intensity}, config, max_points=2_000)
    assert capped.n_points <= 2_000 and capped.dropped_points == 100
    assert "max_points=2000" in caplog.text
    assert capped.covariances.shape == (capped.n_points, 3, 3)
    # without the cap: identical to downsampling the finite points with the plain function
    full = prepare_pointset(pts, {"intensity": intensity}, config, max_points=None)
    ref_pts, ref_ch, _ = voxel_downsample(pts[100:], 0.1, intensity[100:, None])
    np.testing.assert_array_equal(full.points_xyz, ref_pts)
    np.testing.assert_array_equal(full.channels, ref_ch)
    assert full.dropped_points == 100
