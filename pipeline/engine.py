"""Run a per-frame stage over a topic of a frame source on dask, in batches, streaming results as they finish.

The caller gives the frames as a ``FrameSource`` (``workflows.frame_sources.LogFrames`` opens and decodes a
log). The client asks the source only for the log times of the topic's messages (no decoding) and cuts them
into time ranges of ``batch_size`` messages. Each task is ``(source, topic, start_ns, end_ns, stage_fn)``:
the worker has the source decode the frames of its range (a log source opens the log itself by path), runs
the stage on each and returns only the stage results, so frames never travel through the client. At most
``max_in_flight`` tasks are submitted at a time (a sliding window), which bounds memory on long logs.

Frames whose stage raises ``InputError`` (no valid points, blank image...) or that cannot be decoded
are skipped and counted in ``Engine.stats``. Tasks are retried (``retries``) and distributed
reschedules the tasks of a worker that dies, so a lost worker does not fail the run.

``Engine(workers=0)`` runs the very same batch function in-process (debugging, tests);
``Engine(scheduler="tcp://HOST:PORT")`` uses an existing cluster; otherwise a ``LocalCluster`` with one
single-threaded worker process per core is started and closed with the engine.
"""

from __future__ import annotations

import logging
import os
import time
import uuid
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.config import EngineConfig
from fleetcal.pipeline.errors import ConfigError, FleetcalError, InputError, ProcessingError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.pipeline.progress import Progress

__all__ = [
    "BatchResult",
    "Engine",
    "EngineStats",
    "FrameBatch",
    "FrameSource",
    "SkipFn",
    "plan_batches",
    "plan_batches_at",
    "run_batch",
]

log = logging.getLogger(__name__)

_SKIP_EXAMPLES = 5

SkipFn = Callable[[str, str], None]
"""``skip(reason, message)``: count one skipped frame under ``reason``; ``message`` names it for the log."""


class FrameSource(Protocol):
    """Where the engine's frames come from (``workflows.frame_sources.LogFrames``: a log's files).

    A source must be picklable and small: every task carries it to its worker, which calls ``frames``.
    """

    def log_times(self, topic: str, start_ns: int | None, end_ns: int | None) -> NDArray[np.int64]:
        """Log times, ns, of the topic's messages with ``start_ns <= t < end_ns`` (None: unbounded),
        read without decoding (client side).

        Raises:
            InputError: unknown topic, a type the source cannot decode into frames.
        """
        ...

    def frames(self, topic: str, start_ns: int, end_ns: int, skip: SkipFn) -> Iterator[LidarFrame | CameraFrame]:
        """Decoded frames of the topic with ``start_ns <= log time < end_ns`` (worker side); a message that
        cannot be decoded is reported to ``skip`` and not yielded."""
        ...


@dataclass(frozen=True)
class FrameBatch:
    """One task: the messages of ``topic`` with ``start_ns <= log_time_ns < end_ns`` in ``source``.

    Attributes:
        index: position of the batch in log-time order.
        source: the frame source (a log's paths and how to open them).
        topic: lidar or camera topic.
        start_ns, end_ns: log-time range, ns (end exclusive).
        n_messages: messages of the topic in the range (counted on the client).
    """

    index: int
    source: FrameSource
    topic: str
    start_ns: int
    end_ns: int
    n_messages: int


@dataclass
class BatchResult:
    """What a worker sends back for one batch: stage results (log-time order) and skip counts."""

    index: int
    results: list[Any]
    frames_done: int
    skip_reasons: dict[str, int]
    skip_examples: list[str]
    worker_s: float
    worker_pid: int
    worker_cpu_s: float = 0.0


def dask_client(scheduler: str | None, n_workers: int, memory_limit: str | float | None = "auto") -> tuple[Any, Any]:
    """(client, local cluster or None): a client of the scheduler at ``scheduler`` (``tcp://HOST:PORT``),
    or, without one, of a new ``LocalCluster`` of ``n_workers`` single-threaded worker processes on this
    machine. The local cluster has no dashboard, and its scheduler's HTTP server (health and metrics)
    listens on a free localhost port, not on 8787 of every interface: jobs running side by side neither
    clash ("port 8787 is already in use") nor expose a server. Its workers log only CRITICAL records: a
    worker that fails a task reports it through the task's exception, and the ERROR records distributed
    writes while closing (a heartbeat in flight when the worker's connection pool closes) are noise.

    Raises:
        ConfigError: the scheduler cannot be reached.
    """
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            return Client(scheduler, timeout="10s"), None
        except (OSError, TimeoutError) as err:
            raise ConfigError(f"cannot connect to the dask scheduler at {scheduler}: {err}") from err
    cluster = LocalCluster(
        n_workers=n_workers,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
        silence_logs=logging.CRITICAL,
        memory_limit=memory_limit,
    )
    return Client(cluster), cluster


@dataclass
class EngineStats:
    """Counters of the last ``Engine.map_frames`` run.

    Attributes:
        frames_total: messages of the topic in the time range.
        frames_done: frames whose stage returned a result.
        frames_skipped: frames skipped (decode error, InputError in the stage, stage returned None).
        skip_reasons: skipped frames per reason.
        skip_examples: the first few skip messages, for the log.
        batches: tasks run.
        elapsed_s: wall time of the run, s.
        worker_s: summed wall time spent inside batches on the workers, s.
        worker_cpu_s: summed CPU time of the batches' worker processes, s.
    """

    frames_total: int = 0
    frames_done: int = 0
    frames_skipped: int = 0
    skip_reasons: dict[str, int] = field(default_factory=dict)
    skip_examples: list[str] = field(default_factory=list)
    batches: int = 0
    elapsed_s: float = 0.0
    worker_s: float = 0.0
    worker_cpu_s: float = 0.0
    _batch_indices: set[int] = field(default_factory=set, repr=False)

    @property
    def frames_per_s(self) -> float:
        return (self.frames_done + self.frames_skipped) / self.elapsed_s if self.elapsed_s > 0 else 0.0

    def add(self, batch: BatchResult) -> None:
        """Count a batch's result, or one part of it (``batch_parts``)."""
        self._batch_indices.add(batch.index)
        self.batches = len(self._batch_indices)
        self.frames_done += batch.frames_done
        self.worker_s += batch.worker_s
        self.worker_cpu_s += batch.worker_cpu_s
        for reason, count in batch.skip_reasons.items():
            self.frames_skipped += count
            self.skip_reasons[reason] = self.skip_reasons.get(reason, 0) + count
        room = _SKIP_EXAMPLES - len(self.skip_examples)
        if room > 0:
            self.skip_examples.extend(batch.skip_examples[:room])


def plan_batches(
    source: FrameSource,
    topic: str,
    batch_size: int = 32,
    start_ns: int | None = None,
    end_ns: int | None = None,
) -> list[FrameBatch]:
    """Cut the topic's messages into log-time ranges of ``batch_size`` messages (client side).

    Reads only the messages' log times (``source.log_times``, nothing is decoded). Messages sharing a
    log time never straddle two batches.

    Raises:
        InputError: unknown topic, a type the source cannot decode, ``batch_size < 1``; reader errors.
    """
    if batch_size < 1:
        raise InputError(f"batch_size must be >= 1, got {batch_size}")
    times = np.sort(np.asarray(source.log_times(topic, start_ns, end_ns), dtype=np.int64), kind="stable")
    if times.size == 0:
        return []
    starts = np.unique(times[::batch_size])
    ends = np.append(starts[1:], times[-1] + 1)
    counts = np.searchsorted(times, ends, side="left") - np.searchsorted(times, starts, side="left")
    return [
        FrameBatch(i, source, topic, int(s), int(e), int(c))
        for i, (s, e, c) in enumerate(zip(starts, ends, counts, strict=True))
    ]


def plan_batches_at(source: FrameSource, topic: str, log_times_ns: Sequence[int]) -> list[FrameBatch]:
    """One task per given log time (ns): only the topic's messages at those times are decoded (e.g. the
    frames a calibration chose by their stamps, spread over a long log)."""
    times = sorted({int(t) for t in log_times_ns})
    return [FrameBatch(i, source, topic, t, t + 1, 1) for i, t in enumerate(times)]


def run_batch(batch: FrameBatch, stage_fn: Callable[[Any], Any]) -> BatchResult:
    """Worker side: decode the batch's frames (``batch.source.frames``), run ``stage_fn`` on each.

    A frame is skipped (and counted by reason) when it cannot be decoded, when the stage raises
    ``InputError`` (including "no valid points" / "blank image"), or when the stage returns None.
    Any other exception fails the task (dask retries it).
    """
    return merge_parts(batch.index, list(batch_parts(batch, stage_fn)))


def batch_parts(batch: FrameBatch, stage_fn: Callable[[Any], Any]) -> Iterator[BatchResult]:
    """``run_batch`` one frame at a time: a ``BatchResult`` per frame (its result, or its skip) as soon as
    the stage is done with it, so that an in-process consumer can overlap its own work with the next
    frame's stage; a decode failure is a part of its own."""
    skipped: dict[str, int] = {}
    examples: list[str] = []

    def skip(reason: str, message: str) -> None:
        skipped[reason] = skipped.get(reason, 0) + 1
        examples.append(message)

    t0, cpu0 = time.perf_counter(), time.process_time()
    for frame in batch.source.frames(batch.topic, batch.start_ns, batch.end_ns, skip):
        results: list[Any] = []
        reason = _blank_reason(frame)
        if reason is not None:
            skip(reason, f"{batch.topic} @ {frame.stamp_ns}: {reason}")
        else:
            try:
                result = stage_fn(frame)
            except InputError as err:
                skip(f"stage {type(err).__name__}", f"{batch.topic} @ {frame.stamp_ns}: {err}")
                result = None
            else:
                if result is None:
                    skip("stage returned None", f"{batch.topic} @ {frame.stamp_ns}: stage returned None")
                else:
                    results.append(result)
        t1, cpu1 = time.perf_counter(), time.process_time()
        yield BatchResult(batch.index, results, len(results), dict(skipped), examples[:_SKIP_EXAMPLES],
                          t1 - t0, os.getpid(), cpu1 - cpu0)  # fmt: skip
        skipped.clear()
        examples.clear()
        t0, cpu0 = t1, cpu1
    if skipped:
        yield BatchResult(batch.index, [], 0, dict(skipped), examples[:_SKIP_EXAMPLES],
                          time.perf_counter() - t0, os.getpid(), time.process_time() - cpu0)  # fmt: skip


def merge_parts(index: int, parts: Sequence[BatchResult]) -> BatchResult:
    """One batch's ``BatchResult`` from its per-frame parts (``batch_parts``)."""
    skipped: dict[str, int] = {}
    examples: list[str] = []
    for part in parts:
        for reason, count in part.skip_reasons.items():
            skipped[reason] = skipped.get(reason, 0) + count
        examples.extend(part.skip_examples[: _SKIP_EXAMPLES - len(examples)])
    return BatchResult(
        index=index,
        results=[r for part in parts for r in part.results],
        frames_done=sum(part.frames_done for part in parts),
        skip_reasons=skipped,
        skip_examples=examples,
        worker_s=sum(part.worker_s for part in parts),
        worker_pid=os.getpid(),
        worker_cpu_s=sum(part.worker_cpu_s for part in parts),
    )


def _blank_reason(frame: LidarFrame | CameraFrame) -> str | None:
    if isinstance(frame, LidarFrame):
        pts = frame.points_xyz
        if pts.shape[0] == 0 or not np.isfinite(pts).all(axis=1).any():
            return "no valid points"
        return None
    image = frame.image
    if image.size == 0 or image.min() == image.max():
        return "blank image"
    return None


class Engine:
    """Where per-frame stages run: in-process, a local dask cluster, or an existing one.

    Args:
        scheduler: ``tcp://HOST:PORT`` of a running dask scheduler (None: local cluster).
        workers: local worker processes (None: one per core; 0: in-process, no dask).
        retries: times dask retries a failed task.
        max_in_flight: tasks submitted at once (None: 2 per worker + 1).
        quiet: no progress bar.
        warmups: functions run once per worker before any task, e.g. compiling the stages' numba kernels
            (``workflows.frame_sources.STAGE_WARMUPS``); none by default.
        memory_limit: per-worker memory limit of the local cluster (dask syntax, e.g. ``"2GiB"``).

    Use as a context manager; ``stats`` holds the counters of the last ``map_frames``.
    """

    def __init__(
        self,
        scheduler: str | None = None,
        workers: int | None = None,
        *,
        retries: int = 2,
        max_in_flight: int | None = None,
        quiet: bool = False,
        warmups: Sequence[Callable[[], None]] = (),
        memory_limit: str | float | None = "auto",
    ) -> None:
        if workers is not None and workers < 0:
            raise ConfigError(f"workers must be >= 0, got {workers}")
        if scheduler is not None and workers == 0:
            raise ConfigError("workers=0 (in-process) cannot be combined with a scheduler address")
        if max_in_flight is not None and max_in_flight < 1:
            raise ConfigError(f"max_in_flight must be >= 1, got {max_in_flight}")
        self.scheduler = scheduler
        self.workers = workers
        self.retries = retries
        self.quiet = quiet
        self.warmups = tuple(warmups)
        self.memory_limit = memory_limit
        self._max_in_flight = max_in_flight
        self.stats = EngineStats()
        self._client: Any = None
        self._cluster: Any = None
        self._warm_in_process = False

    @classmethod
    def from_config(
        cls, config: EngineConfig, quiet: bool = False, warmups: Sequence[Callable[[], None]] = ()
    ) -> Engine:
        """An engine from the ``[engine]`` section of ``pipeline.config.Config``."""
        return cls(
            scheduler=config.scheduler,
            workers=config.workers,
            retries=config.retries,
            max_in_flight=config.max_in_flight,
            quiet=quiet,
            warmups=warmups,
        )

    @property
    def in_process(self) -> bool:
        return self.workers == 0 and self.scheduler is None

    @property
    def client(self) -> Any:
        """The ``distributed.Client`` (started on first use); None when in-process."""
        if self.in_process:
            return None
        if self._client is None:
            self._start()
        return self._client

    def n_workers(self) -> int:
        """Workers now connected (1 when in-process)."""
        if self.in_process:
            return 1
        return max(1, len(self.client.nthreads()))

    def max_in_flight(self) -> int:
        """Tasks submitted at once: ``max_in_flight`` or 2 per connected worker + 1."""
        return self._max_in_flight or 2 * self.n_workers() + 1

    def _start(self) -> None:
        n = self.workers if self.workers is not None else (os.cpu_count() or 1)
        self._client, self._cluster = dask_client(self.scheduler, n, self.memory_limit)
        if self.warmups:
            from fleetcal.pipeline.worker_plugins import NumbaWarmup

            self._client.register_plugin(NumbaWarmup(self.warmups), name=NumbaWarmup.name)

    def close(self) -> None:
        """Close the client and the local cluster (a remote cluster keeps running)."""
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def map_frames(
        self,
        source: FrameSource,
        topic: str,
        stage_fn: Callable[[Any], Any],
        batch_size: int = 32,
        start_ns: int | None = None,
        end_ns: int | None = None,
        *,
        ordered: bool = False,
        desc: str | None = None,
        log_times_ns: Sequence[int] | None = None,
    ) -> Generator[Any, None, None]:
        """Run ``stage_fn(frame)`` on every frame of ``topic`` in the log-time range; yield results.

        Args:
            source: the frames, e.g. ``workflows.frame_sources.LogFrames(paths)`` (workers open the log by path).
            topic: a PointCloud2 (``LidarFrame``) or Image / CompressedImage (``CameraFrame``) topic.
            stage_fn: picklable function of one frame; raise ``InputError`` or return None to skip it.
            batch_size: frames per task.
            start_ns, end_ns: log-time range, ns (end exclusive); None for the whole log.
            ordered: yield in log-time order (buffers at most ``max_in_flight`` batches) instead of
                as batches complete.
            desc: progress-bar label (default: the topic).
            log_times_ns: only the messages at these log times, one task each (``start_ns`` / ``end_ns`` and
                ``batch_size`` are then not used).

        Yields:
            the stage's results; ``self.stats`` is complete once the iterator is exhausted.

        Raises:
            InputError: unknown topic or unsupported type; reader errors.
            ProcessingError: a stage failed with an unexpected error after the retries.
        """
        t0 = time.perf_counter()
        batches = (plan_batches(source, topic, batch_size, start_ns, end_ns) if log_times_ns is None
                   else plan_batches_at(source, topic, log_times_ns))
        self.stats = EngineStats(frames_total=sum(b.n_messages for b in batches))
        progress = Progress(self.stats.frames_total, desc=desc or topic, quiet=self.quiet)
        running = self._run_in_process(batches, stage_fn) if self.in_process else self._run_dask(
            batches, stage_fn, ordered
        )
        try:
            for batch_result in running:
                self.stats.add(batch_result)
                progress.update(batch_result.frames_done + sum(batch_result.skip_reasons.values()))
                yield from batch_result.results
        finally:
            running.close()
            self.stats.elapsed_s = time.perf_counter() - t0
            progress.close()
            if self.stats.frames_skipped:
                log.info("%s: skipped %d of %d frames: %s", topic, self.stats.frames_skipped,
                         self.stats.frames_total, self.stats.skip_reasons)

    def _run_in_process(
        self, batches: Iterable[FrameBatch], stage_fn: Callable[[Any], Any]
    ) -> Generator[BatchResult, None, None]:
        if not self._warm_in_process:
            for fn in self.warmups:
                fn()
            self._warm_in_process = True
        for batch in batches:
            try:
                yield from batch_parts(batch, stage_fn)
            except FleetcalError:
                raise
            except Exception as err:
                raise _stage_failure(batch, stage_fn, err) from err

    def _run_dask(
        self, batches: Sequence[FrameBatch], stage_fn: Callable[[Any], Any], ordered: bool
    ) -> Generator[BatchResult, None, None]:
        from distributed import as_completed

        client = self.client
        window = self.max_in_flight()
        run_id = uuid.uuid4().hex[:12]
        todo = iter(batches)
        in_flight: dict[str, FrameBatch] = {}
        ready: dict[int, BatchResult] = {}
        next_index = 0
        completed = as_completed()

        def submit_more() -> None:
            while len(in_flight) + len(ready) < window:
                batch = next(todo, None)
                if batch is None:
                    return
                future = client.submit(
                    run_batch, batch, stage_fn, key=f"fleetcal-batch-{run_id}-{batch.index}",
                    retries=self.retries, pure=False,
                )
                in_flight[future.key] = batch
                completed.add(future)

        submit_more()
        try:
            for future in completed:
                batch = in_flight.pop(future.key)
                try:
                    result: BatchResult = future.result()
                except FleetcalError:
                    raise
                except Exception as err:
                    raise _stage_failure(batch, stage_fn, err) from err
                finally:
                    future.release()
                if not ordered:
                    submit_more()
                    yield result
                    continue
                ready[result.index] = result
                while next_index in ready:
                    out = ready.pop(next_index)
                    next_index += 1
                    submit_more()
                    yield out
                submit_more()
        finally:
            for key in list(in_flight):
                client.cancel([key], force=True)
            completed.clear()


def _stage_failure(batch: FrameBatch, stage_fn: Callable[[Any], Any], err: BaseException) -> ProcessingError:
    inner = getattr(stage_fn, "func", stage_fn)
    name = getattr(inner, "__name__", "stage")
    return ProcessingError(
        f"{name} failed on {batch.topic} (log time {batch.start_ns}..{batch.end_ns}): "
        f"{type(err).__name__}: {err}"
    )
