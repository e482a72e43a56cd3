"""The calibrate workflow's search progress line (``workflows.calibrate.search_progress``)."""

from __future__ import annotations

import time

import pytest

from fleetcal.stages.calibration.calibrator import SearchProgress
from fleetcal.workflows.calibrate import search_progress


def report(iteration: int) -> SearchProgress:
    return SearchProgress(run=2, runs=3, iteration=iteration, best_score=0.7, elapsed_s=1.0, fraction=0.4, eta_s=1.5)


def test_the_search_line_names_run_iteration_and_best_score_at_most_once_a_second(
        capsys: pytest.CaptureFixture[str]) -> None:
    with search_progress(quiet=False) as progress:
        time.sleep(1.05)  # the bar stays silent for the first second
        for iteration in range(1, 40):
            progress(report(iteration))
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("calibration search run 2/3 iteration 1 best 0.7000 40/100 %")
    assert len(lines) == 2  # the first report and the closing line: not one per iteration off a terminal


def test_quiet_search_prints_nothing(capsys: pytest.CaptureFixture[str]) -> None:
    with search_progress(quiet=True) as progress:
        time.sleep(1.05)
        progress(report(1))
    assert capsys.readouterr().err == ""
