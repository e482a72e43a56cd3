"""Atomic outputs: write under a temporary name in the same folder, rename into place on success."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from fleetcal.pipeline.errors import InputError


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink(missing_ok=True)


@contextmanager
def atomic_path(final_path: str | os.PathLike[str], overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path to write ``final_path`` (a file or a folder) at, renamed on success.

    The temporary path is ``<folder>/.<name>.tmp-XXXX/<name>`` (same file system, same base name, so
    a rosbag2 folder keeps its storage file names). On a clean exit it replaces ``final_path``
    (an existing file or folder is replaced when ``overwrite``, else InputError); on an exception it
    is removed and the exception propagates. Nothing needs to be created at the yielded path.
    """
    final = Path(final_path)
    parent = final.parent
    if not parent.is_dir():
        raise InputError(f"output folder {parent} does not exist")
    if final.exists() and not overwrite:
        raise InputError(f"output {final} exists already")
    staging = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=parent))
    temp = staging / final.name
    try:
        yield temp
        if not (temp.exists() or temp.is_symlink()):
            raise InputError(f"nothing was written for {final}")
        if final.exists() and (final.is_dir() or temp.is_dir()):
            os.replace(final, staging / f"{final.name}.old")
        os.replace(temp, final)
    finally:
        _remove(staging)
