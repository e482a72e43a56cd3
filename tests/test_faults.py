"""Faults: a full output filesystem, an output folder that cannot be written (both really
fail for root: a 1 MiB tmpfs and ``chattr +i``), and proof that no command ever opens an input log
for writing (read-only copies, sha256 + mtime unchanged, and an audit hook on every ``open``).

A dask worker killed mid-run is covered by ``tests/test_engine.py::
test_killed_worker_tasks_are_retried_and_run_completes`` and the SIGKILLed ``batch`` + resume by
``tests/test_batch.py``; they are not duplicated here.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from tests import badinputs as bi
from tests.test_bad_inputs import ALLOWED_STDERR, run_cli

WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
FAST_CONFIG = """[calibration]
frames = 1
particles = 20
"""


def sha256_and_mtime(path: Path) -> dict[str, tuple[str, int]]:
    files = sorted(path.rglob("*")) if path.is_dir() else [path]
    return {str(f): (hashlib.sha256(f.read_bytes()).hexdigest(), f.stat().st_mtime_ns) for f in files if f.is_file()}


def one_error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert "Traceback" not in stderr
    assert all(line.startswith(ALLOWED_STDERR) for line in lines), stderr
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1, stderr
    return errors[0]


def assert_no_partial_outputs(out: Path) -> None:
    """Whatever is in ``out`` is complete: no temp files left, every Parquet table readable."""
    leftovers = [p for p in out.rglob("*") if p.is_file() and (".tmp" in p.name or p.name.startswith("."))]
    assert not leftovers, leftovers
    for table in out.rglob("*.parquet"):
        pq.read_table(table)


# --- a full output filesystem -------------------------------------------------------------------


@pytest.fixture
def tiny_fs(tmp_path: Path) -> Iterator[Path]:
    """A 1 MiB tmpfs (root with CAP_SYS_ADMIN); skipped where mounting is not allowed."""
    mount_point = tmp_path / "tiny"
    mount_point.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount_point)],
                          capture_output=True, text=True)  # fmt: skip
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({proc.stderr.strip()})")
    try:
        yield mount_point
    finally:
        subprocess.run(["umount", "-l", str(mount_point)], check=False)


def fill(mount_point: Path, leave_bytes: int) -> None:
    stat = os.statvfs(mount_point)
    free = stat.f_bavail * stat.f_frsize
    (mount_point / "ballast").write_bytes(b"\0" * max(free - leave_bytes, 0))


@pytest.mark.parametrize("command", ["map", "calibrate"])
def test_full_output_filesystem_gives_clear_error_and_no_partial_files(
    command: str, tmp_path: Path, tiny_fs: Path
) -> None:
    log = bi.write_scene(tmp_path / "in.mcap", bi.SceneSpec(frames=3))
    before = sha256_and_mtime(log)
    fill(tiny_fs, leave_bytes=8 * 1024)
    out = tiny_fs / "out"
    config = tmp_path / "fast.toml"
    config.write_text(FAST_CONFIG)
    extra = ["--workers", "0"] if command == "map" else ["--config", str(config)]
    outcome = run_cli([command, str(log), *extra, "-q", "--out", str(out)])
    assert outcome.exit_code == 1, outcome.stderr
    error = one_error_line(outcome.stderr)
    assert "No space left on device" in error, error
    assert sha256_and_mtime(log) == before
    if out.exists():
        assert_no_partial_outputs(out)


def test_output_folder_that_cannot_be_written(tmp_path: Path) -> None:
    """``chattr +i`` makes the folder unwritable even for root; skipped where chattr is refused."""
    log = bi.write_scene(tmp_path / "in.mcap", bi.SceneSpec(frames=3))
    out = tmp_path / "out"
    out.mkdir()
    if subprocess.run(["chattr", "+i", str(out)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not permitted here")
    try:
        outcome = run_cli(["map", str(log), "--workers", "0", "-q", "--out", str(out)])
    finally:
        subprocess.run(["chattr", "-i", str(out)], check=False)
    assert outcome.exit_code == 1
    error = one_error_line(outcome.stderr)
    assert "Operation not permitted" in error or "Permission denied" in error, error
    assert list(out.iterdir()) == []


def test_output_under_a_file_is_a_clear_error(tmp_path: Path) -> None:
    log = bi.write_scene(tmp_path / "in.mcap", bi.SceneSpec(frames=3))
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    outcome = run_cli(["map", str(log), "--workers", "0", "-q", "--out", str(blocker / "out")])
    assert outcome.exit_code == 1
    assert "cannot create output folder" in one_error_line(outcome.stderr)


# --- inputs are never opened for writing --------------------------------------------------------

_AUDIT: dict[str, Any] = {"watch": (), "writes": []}


def _audit(event: str, args: tuple[Any, ...]) -> None:
    watch = _AUDIT["watch"]
    if not watch:
        return
    if event == "open":
        path, mode, flags = args
        if not isinstance(path, (str, bytes, os.PathLike)):
            return
        name = os.path.realpath(os.fsdecode(path))
        writing = (isinstance(mode, str) and any(c in mode for c in "wax+")) or (
            isinstance(flags, int) and mode is None and flags & WRITE_FLAGS
        )
        if writing and any(name == w or name.startswith(w + os.sep) for w in watch):
            _AUDIT["writes"].append((name, mode, flags))
    elif event == "sqlite3.connect":
        database = os.fsdecode(args[0]) if args and isinstance(args[0], (str, bytes, os.PathLike)) else ""
        if any(w in database for w in watch) and "immutable=1" not in database and "mode=ro" not in database:
            _AUDIT["writes"].append((database, "sqlite3", None))


sys.addaudithook(_audit)  # cannot be removed; inert while nothing is watched


def read_only_copy(src: Path, dst: Path) -> Path:
    if src.is_dir():
        shutil.copytree(src, dst)
        for f in dst.iterdir():
            f.chmod(0o444)
        dst.chmod(0o555)
    else:
        shutil.copyfile(src, dst)
        dst.chmod(0o444)
    return dst


@pytest.mark.parametrize("fmt", ["mcap", "ros1", "ros2"])
def test_no_command_opens_an_input_log_for_writing(fmt: str, tmp_path: Path) -> None:
    name = {"mcap": "in.mcap", "ros1": "in.bag", "ros2": "in_bag"}[fmt]
    (tmp_path / "src").mkdir()
    src = bi.write_scene(tmp_path / "src" / name, bi.SceneSpec(frames=3, fmt=fmt))  # type: ignore[arg-type]
    log = read_only_copy(src, tmp_path / name)
    config = tmp_path / "fast.toml"
    config.write_text(FAST_CONFIG)
    before = sha256_and_mtime(log)
    commands = [
        ["inspect", str(log)],
        ["calibrate", str(log), "--config", str(config), "--no-report"],
        ["map", str(log)],
        ["process", str(log), "--frames", "1", "--config", str(config)],
    ]
    _AUDIT["watch"], _AUDIT["writes"] = (os.path.realpath(log),), []
    try:
        for i, argv in enumerate(commands):
            out = ["--out", str(tmp_path / f"out{i}")] if argv[0] != "inspect" else []
            outcome = run_cli([*argv, "--workers", "0", "-q", *out])
            assert outcome.exit_code == 0, (argv, outcome.stderr)
    finally:
        _AUDIT["watch"] = ()
    assert _AUDIT["writes"] == []
    assert sha256_and_mtime(log) == before


def test_audit_hook_sees_a_write_mode_open(tmp_path: Path) -> None:
    """The audit above can fail: a write-mode open of a watched path is recorded."""
    target = tmp_path / "watched.mcap"
    target.write_bytes(b"x")
    _AUDIT["watch"], _AUDIT["writes"] = (os.path.realpath(target),), []
    try:
        with open(target, "ab"):
            pass
        fd = os.open(target, os.O_RDWR)
        os.close(fd)
        with open(target, "rb"):
            pass
    finally:
        _AUDIT["watch"] = ()
    assert [w[1] for w in _AUDIT["writes"]] == ["a", None]
