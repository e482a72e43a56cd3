"""One place for the numba compilation flags every ``*_kernels.py`` module uses.

Kernels are compiled ``@njit(nogil=True, cache=True)``; ``fastmath`` and ``parallel`` come from here so
that a deployment can change them in one spot (environment ``FLEETCAL_NUMBA_FASTMATH`` /
``FLEETCAL_NUMBA_PARALLEL``, ``1`` or ``0``, read once at import). ``parallel`` is off by default: the
engine runs one single-threaded worker process per core, and threads inside a kernel would only
oversubscribe the cores.
"""

from __future__ import annotations

import os
from typing import Any


def _env_flag(name: str, default: bool) -> bool:
    value = os.environ.get(name)
    if value is None or value.strip() == "":
        return default
    return value.strip().lower() in ("1", "true", "yes", "on")


FASTMATH: bool = _env_flag("FLEETCAL_NUMBA_FASTMATH", False)
PARALLEL: bool = _env_flag("FLEETCAL_NUMBA_PARALLEL", False)

NJIT_FLAGS: dict[str, Any] = {"nogil": True, "cache": True, "fastmath": FASTMATH}
"""Keyword arguments for ``numba.njit`` in every kernel module."""

NJIT_PARALLEL_FLAGS: dict[str, Any] = {**NJIT_FLAGS, "parallel": PARALLEL}
"""Same, for kernels written with ``numba.prange`` that may run threaded."""
