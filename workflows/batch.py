"""``fleetcal batch``: process many logs in parallel on dask, one task per log, with a manifest.

Each log gets its own output folder ``DIR/<log stem>`` (``-2``, ``-3`` ... appended when stems
collide, in input order). Inside a task the per-log recipe (``workflows.process.process_log`` with
``workers=0``) runs in-process; the client collects one ``LogOutcome`` per log and rewrites
``DIR/manifest.parquet`` atomically after every finished log, so a killed batch keeps what was done.
A failing log is recorded (``status="failed"`` and its one-line error) and never stops the batch.

``resume=True`` skips logs whose folder is complete (``result.json`` present, written last by
``process_log``): their manifest row is carried over with ``status="skipped"``; partial folders are
removed and redone. Without ``resume`` every log is redone from an empty folder.

At the end a fleet summary (``DIR/fleet.parquet``) lists, per rig (lidar frame, camera frame), the
calibrated ``T_camera_lidar`` of every log in time order (``log_start_ns``) with the change from the
previous log, flagged as drift beyond ``drift_deg`` / ``drift_m``.

Manifest columns (one row per log, input order): ``path, out_dir, status (ok|failed|skipped), error,
started_ns, finished_ns, runtime_s, log_start_ns, map_points`` and per lidar/camera pair, as lists in
the same order: ``camera_topics`` (list<string>), ``verdicts`` (list<string>), ``scores``
(list<double>), ``translations_held`` (list<bool>: the translation was kept at the log's, not estimated;
``CalibrationConfig.translation``), ``translations_weak`` (list<string>: the camera axes along which the
log fixes the translation only weakly, comma-separated, e.g. ``"x,z"``, followed by `` of <frame>`` where they
are another camera's, the reference camera of a ``--joint`` rig; ``CalibrationResult.weak_translation_axes``).
"""

from __future__ import annotations

import glob
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.errors import ConfigError, FleetcalError, InputError
from fleetcal.pipeline.progress import Progress
from fleetcal.pipeline.transforms import from_quat, rotation_error_deg, translation_error_m
from fleetcal.stages.sinks.tables import POSE_FIELDS, RPY_FIELDS, write_rows

__all__ = [
    "FLEET_FILE",
    "FLEET_SCHEMA",
    "MANIFEST_FILE",
    "MANIFEST_SCHEMA",
    "BatchResult",
    "LogJob",
    "LogOutcome",
    "ProcessSummary",
    "fleet_summary",
    "plan_jobs",
    "process_with_fleetcal",
    "read_manifest",
    "resolve_inputs",
    "run_batch",
    "run_log",
]

log = logging.getLogger(__name__)

MANIFEST_FILE = "manifest.parquet"
FLEET_FILE = "fleet.parquet"
LOG_SUFFIXES = (".mcap", ".bag", ".db3")
"""Files a glob keeps (other matches, e.g. ``*.truth.json`` beside simulated logs, are ignored)."""
LIST_SUFFIXES = (".txt", ".list", ".lst")
"""An input file with one of these suffixes is a list of logs, one per line (``#`` comments)."""
_GLOB_CHARS = frozenset("*?[")

Status = Literal["ok", "failed", "skipped"]

MANIFEST_SCHEMA = pa.schema(
    [
        ("path", pa.string()),
        ("out_dir", pa.string()),
        ("status", pa.string()),
        ("error", pa.string()),
        ("started_ns", pa.int64()),
        ("finished_ns", pa.int64()),
        ("runtime_s", pa.float64()),
        ("log_start_ns", pa.int64()),
        ("camera_topics", pa.list_(pa.string())),
        ("verdicts", pa.list_(pa.string())),
        ("scores", pa.list_(pa.float64())),
        ("translations_held", pa.list_(pa.bool_())),
        ("translations_weak", pa.list_(pa.string())),
        ("map_points", pa.int64()),
    ]
)

FLEET_SCHEMA = pa.schema(
    [
        ("lidar_frame", pa.string()),
        ("camera_frame", pa.string()),
        ("camera_topic", pa.string()),
        ("path", pa.string()),
        ("out_dir", pa.string()),
        ("log_start_ns", pa.int64()),
        ("verdict", pa.string()),
        ("translation_held", pa.bool_()),
        ("translation_weak_axes", pa.string()),
        ("score", pa.float64()),
        *POSE_FIELDS,
        *RPY_FIELDS,
        ("change_deg", pa.float64()),
        ("change_m", pa.float64()),
        ("drift", pa.bool_()),
    ]
)


@dataclass(frozen=True)
class LogJob:
    """One log of the batch.

    Attributes:
        index: position in the input order.
        path: the log (a file, or a ROS 2 bag folder) as given (the manifest's ``path``).
        out_dir: its output folder (absolute).
        source: the log's absolute path, made on the client; the worker opens this one (remote
            workers may run in another folder).
    """

    index: int
    path: str
    out_dir: str
    source: str = ""

    def __post_init__(self) -> None:
        if not self.source:
            object.__setattr__(self, "source", os.path.abspath(self.path))


@dataclass
class ProcessSummary:
    """What the batch keeps of one processed log.

    Attributes:
        log_start_ns: first message time of the log, ns.
        calibrations: per lidar/camera pair, at least ``camera_topic``, ``verdict``, ``score``.
        map_points: points of the written map (None when no map was made).
        stage_times_s: wall time per stage, s.
    """

    log_start_ns: int | None
    calibrations: list[dict[str, Any]] = field(default_factory=list)
    map_points: int | None = None
    stage_times_s: dict[str, float] = field(default_factory=dict)


ProcessFn = Callable[[list[str], Path, Config], ProcessSummary]
"""``fn(log_paths, out_dir, config)``: process one log into ``out_dir`` (in-process), or raise."""
CompleteFn = Callable[[Path], bool]
"""``fn(out_dir)``: True when ``out_dir`` holds the finished outputs of a log."""


@dataclass
class LogOutcome:
    """One manifest row (see the module docstring) plus the stage times of a fresh run."""

    path: str
    out_dir: str
    status: Status
    error: str | None = None
    started_ns: int | None = None
    finished_ns: int | None = None
    runtime_s: float | None = None
    log_start_ns: int | None = None
    camera_topics: list[str] = field(default_factory=list)
    verdicts: list[str] = field(default_factory=list)
    scores: list[float] = field(default_factory=list)
    translations_held: list[bool] = field(default_factory=list)
    translations_weak: list[str] = field(default_factory=list)
    map_points: int | None = None
    stage_times_s: dict[str, float] = field(default_factory=dict)

    def row(self) -> dict[str, Any]:
        """The manifest row (``MANIFEST_SCHEMA`` columns)."""
        return {name: getattr(self, name) for name in MANIFEST_SCHEMA.names}

    def set_pairs(self, calibrations: Sequence[Mapping[str, Any]]) -> LogOutcome:
        """Fill the per-pair lists from ``process`` calibration summaries (``result.json``); returns self."""
        self.camera_topics = [str(c.get("camera_topic", "")) for c in calibrations]
        self.verdicts = [str(c.get("verdict", "")) for c in calibrations]
        self.scores = [float(c.get("score", float("nan"))) for c in calibrations]
        self.translations_held = [bool(c.get("translation_held", False)) for c in calibrations]
        self.translations_weak = [_weak_axes(c) for c in calibrations]
        return self

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> LogOutcome:
        return cls(
            path=str(row["path"]),
            out_dir=str(row["out_dir"]),
            status=row["status"],
            error=row.get("error"),
            started_ns=row.get("started_ns"),
            finished_ns=row.get("finished_ns"),
            runtime_s=row.get("runtime_s"),
            log_start_ns=row.get("log_start_ns"),
            camera_topics=list(row.get("camera_topics") or []),
            verdicts=list(row.get("verdicts") or []),
            scores=[float(s) for s in row.get("scores") or []],
            translations_held=[bool(h) for h in row.get("translations_held") or []],
            translations_weak=[str(w) for w in row.get("translations_weak") or []],
            map_points=row.get("map_points"),
        )


@dataclass
class BatchResult:
    """Outcome of ``run_batch``.

    Attributes:
        out_dir: the batch output folder.
        outcomes: one per log, input order.
        fleet: fleet summary rows (``FLEET_SCHEMA`` columns), per rig in time order.
        runtime_s: wall time of the batch, s.
    """

    out_dir: Path
    outcomes: list[LogOutcome]
    fleet: list[dict[str, Any]]
    runtime_s: float

    @property
    def manifest_path(self) -> Path:
        return self.out_dir / MANIFEST_FILE

    @property
    def fleet_path(self) -> Path:
        return self.out_dir / FLEET_FILE

    def count(self, status: Status) -> int:
        return sum(o.status == status for o in self.outcomes)

    @property
    def ok(self) -> bool:
        """True when no log failed."""
        return self.count("failed") == 0

    def to_json(self) -> dict[str, Any]:
        return {
            "out": str(self.out_dir),
            "manifest": str(self.manifest_path),
            "fleet_file": str(self.fleet_path),
            "logs": len(self.outcomes),
            "ok": self.count("ok"),
            "failed": self.count("failed"),
            "skipped": self.count("skipped"),
            "runtime_s": self.runtime_s,
            "manifest_rows": [o.row() for o in self.outcomes],
            "fleet": self.fleet,
        }


# ------------------------------------------------------------------------------------------ inputs
def resolve_inputs(inputs: Sequence[str]) -> list[str]:
    """Log paths from globs, plain paths and list files, de-duplicated, in input order.

    A glob (``"logs/*.mcap"``, ``"fleet/**/*"``) keeps its sorted matches that are logs: ``.mcap``,
    ``.bag`` and ``.db3`` files and folders; a file inside a ROS 2 bag folder (``metadata.yaml``, a
    ``.db3``/``.mcap`` storage file) stands for its folder, so a bag folder counts as one log. A plain
    path is kept as given even when it does not exist (the log then fails with a clear error). A
    ``.txt``/``.list``/``.lst`` file lists logs, one per line; blank lines and ``#`` comments are
    ignored; relative lines are relative to the list file's folder; lines may be globs.

    Raises:
        InputError: a list file cannot be read, or nothing at all matched.
    """
    logs: list[str] = []
    seen: set[str] = set()
    unmatched: list[str] = []

    def add(path: str) -> None:
        key = os.path.normpath(os.path.abspath(path))
        if key not in seen:
            seen.add(key)
            logs.append(path)

    for item in inputs:
        if Path(item).suffix.lower() in LIST_SUFFIXES and Path(item).is_file():
            for entry in _read_list_file(Path(item)):
                _expand(entry, add, unmatched)
        else:
            _expand(item, add, unmatched)
    if not logs:
        raise InputError(f"no logs match {' '.join(inputs)}")
    for pattern in unmatched:
        log.warning("batch: %s matches nothing", pattern)
    return logs


def _read_list_file(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read the list file {path}: {err}") from err
    entries = []
    for line in text.splitlines():
        entry = line.split("#", 1)[0].strip()
        if entry:
            entries.append(entry if os.path.isabs(entry) else str(path.parent / entry))
    return entries


def _expand(item: str, add: Callable[[str], None], unmatched: list[str]) -> None:
    if not _GLOB_CHARS & set(item):
        add(_bag_folder_of(item) or item)
        return
    matches = sorted(glob.glob(item, recursive=True))
    for match in matches:
        folder = _bag_folder_of(match)
        if folder is not None:
            add(folder)
        elif os.path.isdir(match) or Path(match).suffix.lower() in LOG_SUFFIXES:
            add(match)
        else:
            log.debug("batch: ignoring %s (not a log file)", match)
    if not matches:
        unmatched.append(item)


def _bag_folder_of(path: str) -> str | None:
    """The ROS 2 bag folder that ``path`` is or lies in (a folder with ``metadata.yaml``), else None."""
    p = Path(path)
    if p.is_dir():
        return str(p) if (p / "metadata.yaml").is_file() else None
    if p.is_file() and (p.parent / "metadata.yaml").is_file() and p.suffix.lower() in (".yaml", *LOG_SUFFIXES):
        return str(p.parent) if str(p.parent) not in ("", ".") else os.getcwd()
    return None


def log_stem(path: str) -> str:
    """Folder name for a log: the file stem, the bag folder name, or ``log`` when there is none."""
    p = Path(os.path.normpath(path))
    if p.name == "metadata.yaml":
        p = p.parent
    name = p.name if p.is_dir() else p.stem
    return name.lstrip(".") or "log"


def plan_jobs(log_paths: Sequence[str], out_root: Path) -> list[LogJob]:
    """One job per log; output folders named by stem, ``-2``, ``-3`` ... appended on collisions."""
    used: set[str] = set()
    jobs = []
    for index, path in enumerate(log_paths):
        stem = log_stem(path)
        name, n = stem, 1
        while name.lower() in used:
            n += 1
            name = f"{stem}-{n}"
        used.add(name.lower())
        jobs.append(LogJob(index=index, path=str(path), out_dir=str((out_root / name).absolute())))
    return jobs


# ------------------------------------------------------------------------------------- one log
def process_with_fleetcal(paths: list[str], out_dir: Path, config: Config) -> ProcessSummary:
    """The real per-log recipe: ``workflows.process.process_log(..., workers=0)``, summarised."""
    from fleetcal.workflows.process import process_log

    result = process_log(paths, out_dir, config, workers=0, quiet=True)
    mapping = result.mapping or {}
    map_points = mapping.get("map_points")
    return ProcessSummary(
        log_start_ns=int(result.log_start_ns),
        calibrations=[dict(c) for c in result.calibrations],
        map_points=int(map_points) if map_points is not None else None,
        stage_times_s={k: float(v) for k, v in result.stage_times_s.items()},
    )


def fleetcal_is_complete(out_dir: Path) -> bool:
    """``workflows.process.is_complete``: the folder holds the finished outputs of its log."""
    from fleetcal.workflows.process import is_complete

    return bool(is_complete(out_dir))


def _weak_axes(calibration: Mapping[str, Any]) -> str:
    """A calibration summary's weakly fixed translation axes as the manifest stores them: ``"x,z"`` (of its own
    camera), ``"x,z of cam_front_optical"`` (a ``--joint`` rig's reference camera), ``""`` (none)."""
    axes = ",".join(str(a) for a in calibration.get("weak_translation_axes") or [])
    frame = calibration.get("translation_axes_frame")
    if axes and frame and frame != calibration.get("camera_frame"):
        return f"{axes} of {frame}"
    return axes


def run_log(job: LogJob, config: Config, process_fn: ProcessFn = process_with_fleetcal) -> LogOutcome:
    """Process one log into ``job.out_dir`` and return its manifest row; never raises.

    This is the dask task. A ``FleetcalError`` becomes ``status="failed"`` with its one-line message;
    any other exception too, marked as an internal error with its type.
    """
    started_ns = time.time_ns()
    t0 = time.perf_counter()
    outcome = LogOutcome(path=job.path, out_dir=job.out_dir, status="failed", started_ns=started_ns)
    try:
        out_dir = Path(job.out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        summary = process_fn([job.source], out_dir, config)
    except FleetcalError as err:
        outcome.error = str(err) or type(err).__name__
    except MemoryError:
        outcome.error = "out of memory"
    except Exception as err:  # one bad log never stops the batch
        log.debug("batch: %s failed", job.path, exc_info=True)
        outcome.error = f"internal error ({type(err).__name__}: {err})"
    else:
        outcome.status = "ok"
        outcome.log_start_ns = summary.log_start_ns
        outcome.set_pairs(summary.calibrations)
        outcome.map_points = summary.map_points
        outcome.stage_times_s = dict(summary.stage_times_s)
    outcome.finished_ns = time.time_ns()
    outcome.runtime_s = time.perf_counter() - t0
    return outcome


# ------------------------------------------------------------------------------------- the batch
def run_batch(
    inputs: Sequence[str],
    out_dir: str | os.PathLike[str],
    config: Config,
    *,
    resume: bool = False,
    scheduler: str | None = None,
    workers: int | None = None,
    drift_deg: float = 0.5,
    drift_m: float = 0.05,
    quiet: bool = True,
    process_fn: ProcessFn = process_with_fleetcal,
    is_complete: CompleteFn = fleetcal_is_complete,
) -> BatchResult:
    """Process every log of ``inputs`` (see ``resolve_inputs``) into ``out_dir/<stem>``.

    Args:
        inputs: globs, log paths or list files.
        out_dir: batch output folder (created); holds the per-log folders, the manifest and fleet.
        config: per-log configuration (passed to ``process_fn`` unchanged).
        resume: skip complete folders (manifest rows carried over), redo partial ones.
        scheduler: ``tcp://HOST:PORT`` of a dask scheduler (None: a local cluster).
        workers: local single-threaded worker processes (None: one per core, at most one per log;
            0: in-process, one log after the other).
        drift_deg, drift_m: change of ``T_camera_lidar`` between consecutive logs of a rig that is
            flagged as drift, degrees / metres.
        quiet: no progress bar.
        process_fn: the per-log recipe (injected in tests); must be importable by dask workers.
        is_complete: whether a log's folder is finished (used by ``resume``).

    Raises:
        InputError: nothing matched, or the output folder cannot be made.
        ConfigError: bad workers/scheduler/threshold values, or the scheduler cannot be reached.
    """
    t0 = time.perf_counter()
    if workers is not None and workers < 0:
        raise ConfigError(f"workers must be >= 0, got {workers}")
    if scheduler is not None and workers == 0:
        raise ConfigError("workers=0 (in-process) cannot be combined with a scheduler address")
    if not (np.isfinite(drift_deg) and drift_deg >= 0 and np.isfinite(drift_m) and drift_m >= 0):
        raise ConfigError(f"drift thresholds must be finite and >= 0, got {drift_deg} deg, {drift_m} m")
    root = Path(out_dir)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"cannot create output folder {root}: {err.strerror or err}") from err
    jobs = plan_jobs(resolve_inputs(inputs), root)
    _check_no_log_inside_outputs(jobs)
    previous = {Path(o.out_dir).name: o for o in read_manifest(root)} if resume else None
    done, todo = _triage(jobs, previous, is_complete)

    def record(outcome: LogOutcome, index: int) -> None:
        done[index] = outcome
        write_manifest(root, [done[i] for i in sorted(done)])

    if done:
        write_manifest(root, [done[i] for i in sorted(done)])
    with Progress(len(todo), desc="batch", quiet=quiet, unit="logs") as progress:
        if todo and scheduler is None and workers == 0:
            for job in todo:
                record(run_log(job, config, process_fn), job.index)
                progress.update()
        elif todo:
            _run_on_dask(todo, config, process_fn, scheduler, workers, record, progress)
    outcomes = [done[i] for i in sorted(done)]
    write_manifest(root, outcomes)
    fleet = fleet_summary(outcomes, drift_deg=drift_deg, drift_m=drift_m)
    write_rows(fleet, FLEET_SCHEMA, root / FLEET_FILE)
    return BatchResult(out_dir=root, outcomes=outcomes, fleet=fleet, runtime_s=time.perf_counter() - t0)


def _triage(jobs: Sequence[LogJob], previous: dict[str, LogOutcome] | None,
            is_complete: CompleteFn) -> tuple[dict[int, LogOutcome], list[LogJob]]:
    """The outcomes known before any work (by job index) and the jobs to run. With ``previous`` (resume: the
    old manifest's rows by folder name) a complete folder is skipped, its row carried over; every other job's
    folder is cleared first, and one that cannot be is a failed outcome."""
    done: dict[int, LogOutcome] = {}
    todo: list[LogJob] = []
    for job in jobs:
        folder = Path(job.out_dir)
        if previous is not None and folder.is_dir() and is_complete(folder):
            old = previous.get(folder.name) or _outcome_from_result_file(job)
            carried = LogOutcome.from_row(old.row()) if old is not None else LogOutcome(job.path, job.out_dir, "ok")
            carried.path, carried.out_dir = job.path, job.out_dir
            carried.status, carried.error = "skipped", None
            done[job.index] = carried
            continue
        try:
            if folder.is_dir():
                shutil.rmtree(folder)
            elif folder.exists():
                folder.unlink()
        except OSError as err:
            reason = f"cannot clear the output folder {folder}: {err.strerror or err}"
            done[job.index] = LogOutcome(job.path, job.out_dir, "failed", error=reason)
            continue
        todo.append(job)
    return done, todo


def _check_no_log_inside_outputs(jobs: Sequence[LogJob]) -> None:
    """Refuse a plan whose output folders (cleared before processing) would hold one of the logs."""
    folders = {Path(job.out_dir).resolve() for job in jobs}
    for job in jobs:
        log_path = Path(job.path).resolve()
        for folder in folders:
            if log_path == folder or folder in log_path.parents:
                raise InputError(f"output folder {folder} would overwrite the log {job.path}; choose another --out")


def _run_on_dask(
    jobs: list[LogJob],
    config: Config,
    process_fn: ProcessFn,
    scheduler: str | None,
    workers: int | None,
    record: Callable[[LogOutcome, int], None],
    progress: Progress,
) -> None:
    """One task per log on a dask cluster; ``record`` is called as each finishes (any order)."""
    from distributed import as_completed

    from fleetcal.pipeline.engine import dask_client

    n = workers if workers is not None else (os.cpu_count() or 1)
    client, cluster = dask_client(scheduler, max(1, min(n, len(jobs))))
    try:
        token = uuid.uuid4().hex[:8]
        futures = {
            client.submit(run_log, job, config, process_fn, key=f"fleetcal-log-{job.index}-{token}", pure=False): job
            for job in jobs
        }
        for future in as_completed(futures):
            job = futures[future]
            try:
                outcome = future.result()
            except Exception as err:  # the worker died (KilledWorker) or the task could not run
                outcome = LogOutcome(
                    path=job.path,
                    out_dir=job.out_dir,
                    status="failed",
                    error=f"task failed on the cluster ({type(err).__name__}: {err})",
                    finished_ns=time.time_ns(),
                )
            record(outcome, job.index)
            progress.update()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _outcome_from_result_file(job: LogJob) -> LogOutcome | None:
    """A manifest row rebuilt from a complete folder's ``result.json`` (resume without a manifest row)."""
    try:
        from fleetcal.workflows.process import load_result

        result = load_result(Path(job.out_dir))
    except (ImportError, OSError, ValueError, KeyError, TypeError):
        return None
    map_points = (result.mapping or {}).get("map_points")
    return LogOutcome(
        path=job.path,
        out_dir=job.out_dir,
        status="ok",
        runtime_s=result.runtime_s,
        log_start_ns=result.log_start_ns,
        map_points=int(map_points) if map_points is not None else None,
    ).set_pairs(result.calibrations)


# --------------------------------------------------------------------------------------- tables
def write_manifest(root: Path, outcomes: Sequence[LogOutcome]) -> Path:
    """Write ``root/manifest.parquet`` atomically (one row per log)."""
    return write_rows([o.row() for o in outcomes], MANIFEST_SCHEMA, root / MANIFEST_FILE)


def read_manifest(root: Path) -> list[LogOutcome]:
    """The rows of ``root/manifest.parquet``; empty when there is none or it cannot be read."""
    path = root / MANIFEST_FILE
    if not path.is_file():
        return []
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowException) as err:
        log.warning("batch: ignoring unreadable manifest %s (%s)", path, err)
        return []
    return [LogOutcome.from_row(row) for row in table.to_pylist()]


def fleet_summary(
    outcomes: Sequence[LogOutcome], drift_deg: float = 0.5, drift_m: float = 0.05
) -> list[dict[str, Any]]:
    """Per rig (lidar frame, camera frame), its ``T_camera_lidar`` over the logs in time order.

    Reads each ok/skipped log's ``calibration.parquet`` (DESIGN.md columns); the verdict comes from
    the manifest row (matched by camera topic). ``change_deg`` / ``change_m`` are the rotation angle
    and translation distance from the previous log of the same rig (null for the first); ``drift`` is
    True when either exceeds its threshold. Logs without ``log_start_ns`` sort last, then by path.
    """
    rows = [row for outcome in outcomes if outcome.status != "failed" for row in _fleet_rows(outcome)]
    rows.sort(
        key=lambda r: (
            str(r["lidar_frame"]),
            str(r["camera_frame"]),
            r["log_start_ns"] is None,
            r["log_start_ns"] or 0,
            r["path"],
        )
    )
    _mark_changes(rows, drift_deg, drift_m)
    return rows


def _fleet_rows(outcome: LogOutcome) -> list[dict[str, Any]]:
    """One fleet row per camera of a processed log: its ``calibration.parquet`` row with the manifest's verdict,
    held translation and weak axes; none where the table is missing or unreadable (a warning)."""
    path = Path(outcome.out_dir) / "calibration.parquet"
    if not path.is_file():
        return []
    try:
        calibrations = pq.read_table(path).to_pylist()
    except (OSError, pa.ArrowException) as err:
        log.warning("batch: cannot read %s (%s)", path, err)
        return []
    verdicts = dict(zip(outcome.camera_topics, outcome.verdicts, strict=False))
    held = dict(zip(outcome.camera_topics, outcome.translations_held, strict=False))
    weak = dict(zip(outcome.camera_topics, outcome.translations_weak, strict=False))
    rows = []
    for cal in calibrations:
        row = {name: cal.get(name) for name in FLEET_SCHEMA.names}
        row.update(
            path=outcome.path,
            out_dir=outcome.out_dir,
            log_start_ns=outcome.log_start_ns,
            verdict=verdicts.get(str(cal.get("camera_topic"))),
            translation_held=held.get(str(cal.get("camera_topic"))),
            translation_weak_axes=weak.get(str(cal.get("camera_topic"))),
        )
        rows.append(row)
    return rows


def _mark_changes(rows: list[dict[str, Any]], drift_deg: float, drift_m: float) -> None:
    """Set each row's change from the previous row of its rig (rows in time order) and whether it drifted."""
    previous: dict[tuple[str, str], np.ndarray] = {}
    for row in rows:
        rig = (str(row["lidar_frame"]), str(row["camera_frame"]))
        try:
            T = from_quat([row["tx_m"], row["ty_m"], row["tz_m"]], [row["qx"], row["qy"], row["qz"], row["qw"]])
        except (FleetcalError, TypeError, ValueError):
            row.update(change_deg=None, change_m=None, drift=False)
            continue
        before = previous.get(rig)
        if before is None:
            row.update(change_deg=None, change_m=None, drift=False)
        else:
            change_deg = rotation_error_deg(before, T)
            change_m = translation_error_m(before, T)
            row.update(change_deg=change_deg, change_m=change_m, drift=change_deg > drift_deg or change_m > drift_m)
        previous[rig] = T
