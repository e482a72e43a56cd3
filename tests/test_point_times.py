"""One rule for what a scan's per-point times are (``pipeline.point_times``), shared by calibration,
mapping, ``process`` and ``inspect``."""

from __future__ import annotations

import numpy as np
import pytest

from fleetcal.pipeline.point_times import MAX_SWEEP_S, classify_point_times, max_offset_s

SWEEP_S = np.linspace(0.0, 0.099, 1000)  # a 10 Hz sweep stamped at its start


def test_a_sweep_stamped_at_its_start_or_end() -> None:
    for times in (SWEEP_S, SWEEP_S - 0.099):
        result = classify_point_times(times)
        assert result.kind == "sweep" and result.all_finite
        assert (result.first_s, result.last_s) == (pytest.approx(times.min()), pytest.approx(times.max()))


def test_one_capture_time_is_constant() -> None:
    assert classify_point_times(np.zeros(100)).kind == "constant"
    assert classify_point_times(np.full(100, 0.05) + np.linspace(0, 0.9e-3, 100)).kind == "constant"
    assert classify_point_times(np.linspace(0, 1.1e-3, 100)).kind == "sweep"


def test_another_clock_is_foreign() -> None:
    assert classify_point_times(SWEEP_S - 21_933_112.3).kind == "foreign"  # PJLab rig1's offset
    assert classify_point_times(np.full(10, 1e7)).kind == "foreign"  # constant, but not this stamp's
    assert classify_point_times(np.r_[SWEEP_S, 5.0]).kind == "foreign"  # merged over 5 s


def test_a_known_scan_interval_tightens_the_limit() -> None:
    late = SWEEP_S + 0.3  # 0.3..0.4 s after a stamp: fine for some 2 Hz lidar, not for a 10 Hz one
    assert classify_point_times(late).kind == "sweep"
    assert classify_point_times(late, interval_s=0.1).kind == "foreign"
    assert max_offset_s(0.1) == pytest.approx(0.2)
    assert max_offset_s(1.0) == MAX_SWEEP_S and max_offset_s(None) == MAX_SWEEP_S and max_offset_s(0.0) == MAX_SWEEP_S


def test_missing_and_nan_times() -> None:
    assert classify_point_times(None).kind == "none"
    assert classify_point_times(np.array([])).kind == "none"
    assert classify_point_times(np.full(5, np.nan)).kind == "none"
    with_nan = classify_point_times(np.r_[SWEEP_S, np.nan])
    assert with_nan.kind == "sweep" and not with_nan.all_finite
    assert with_nan.last_s == pytest.approx(0.099)
