"""Dask worker plugins of the engine, in a module of their own: ``distributed`` takes about half a second
to import, which only runs on a dask cluster need (``Engine`` imports this module when it starts one)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin


class NumbaWarmup(WorkerPlugin):  # type: ignore[misc]
    """Worker plugin: run the warm-up functions once when a worker starts (also after a restart)."""

    name = "fleetcal-numba-warmup"

    def __init__(self, warmups: Sequence[Callable[[], None]]) -> None:
        self.warmups = tuple(warmups)

    def setup(self, worker: Any) -> None:
        for fn in self.warmups:
            fn()
