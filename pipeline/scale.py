"""Where the pipeline renders map tiles: in this process, or on a Dask cluster.

The tiled maps and their algorithms live in :mod:`mapping.tiling` (built by
:meth:`mapping.build.MapBuilder.tiled_map`); this module only provides the engines that render their tiles.

Engines (``scale.scheduler`` in the configuration, ``--scheduler`` on the command line):

- ``null`` (default): tiles one after another in this process, each tile's queries on numba's threads;
- ``local``: a :class:`distributed.LocalCluster` of ``scale.workers`` processes with
  ``scale.threads_per_worker`` threads each, started for the run and closed after it;
- ``tcp://HOST:PORT`` (any Dask scheduler address): a running cluster. Its workers must import this project:
  start them from the checkout, e.g. ``cd CHECKOUT && PYTHONPATH=. dask worker tcp://HOST:PORT``.

A Dask render scatters its :class:`~mapping.tiling.render.RenderJob` (the indexed beams, the grid, the map
factory with the learnt parameters, the covariances) to every worker once, then maps one task per tile; each
task selects its tile's support, builds the map of it and queries the tile, and returns the float32 layers.
Results are the same bit for bit as the in-process engine's (a tile's numbers depend only on its support and
its queries, not on where or in which order it runs). Numba's thread pool inside a worker is set to the cores
left per worker thread, so that workers do not oversubscribe the machine.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

from mapping.tiling import RenderJob, TileRenderer, TileResult, render_serial, render_tile
from pipeline.errors import PipelineError
from pipeline.scale_config import ScaleConfig


def _render_task(tile: int, job: RenderJob, numba_threads: int | None) -> TileResult:
    """One Dask task: render ``tile``, numba limited to ``numba_threads`` threads in this worker thread."""
    import numba

    if numba_threads is None:
        from distributed import get_worker

        numba_threads = max(1, (os.cpu_count() or 1) // max(get_worker().state.nthreads, 1))
    numba.set_num_threads(min(numba_threads, numba.config.NUMBA_NUM_THREADS))
    return render_tile(job, tile)


@contextmanager
def _quiet_cluster_logs() -> Iterator[None]:
    """Silence the local cluster's own log lines below CRITICAL, in this process and in the workers it
    spawns (through the environment they inherit). When a run is interrupted or fails, the cluster's
    shutdown races (heartbeats to a closed scheduler, cancelled tasks) print pages of tracebacks that hide
    the one line the command line prints; a task's own error still reaches the run through its future.
    Loggers below those names with a level of their own are silenced too: distributed's configuration sets
    ``tornado.application`` to ERROR, which let an interrupt's race in its ``sync`` print a traceback."""
    bases = ("distributed", "tornado", "asyncio")
    names = [*bases] + [
        name
        for name, logger in logging.root.manager.loggerDict.items()
        if isinstance(logger, logging.Logger)
        and logger.level != logging.NOTSET
        and name.startswith(tuple(f"{base}." for base in bases))
    ]
    levels = {name: logging.getLogger(name).level for name in names}
    env_key = "DASK_LOGGING__DISTRIBUTED"
    previous_env = os.environ.get(env_key)
    os.environ[env_key] = "critical"
    for name in names:
        logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        gc.collect()  # "Task exception was never retrieved" is logged when a failed task is collected
        for name, level in levels.items():
            logging.getLogger(name).setLevel(level)
        if previous_env is None:
            os.environ.pop(env_key, None)
        else:
            os.environ[env_key] = previous_env


@contextmanager
def _children_ignore_sigint() -> Iterator[None]:
    """Start processes that ignore SIGINT: Ctrl-C in a terminal reaches the whole process group, and the
    local cluster's nannies and workers would each print a KeyboardInterrupt traceback while this process
    shuts them down cleanly (an ignored signal stays ignored across fork and exec). The price: a Ctrl-C
    pressed during the cluster's start (about a second) is ignored here too; blocking the signal instead
    would not keep it, since any thread of this process that does not block it (BLAS, numba) may receive
    it and discard it. Only the main thread may change handlers; elsewhere this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)


class DaskEngine:
    """Renders tiles on a Dask cluster: a local one (``"local"``) or a running scheduler by address."""

    def __init__(
        self, scheduler: str, workers: int = 2, threads_per_worker: int = 1, connect_timeout_s: float = 20.0
    ) -> None:
        self.scheduler = scheduler
        self.connect_timeout_s = connect_timeout_s
        self.workers = workers
        self.threads_per_worker = threads_per_worker
        self.client = None
        self._cluster = None
        self._quiet = None
        self.numba_threads: int | None = None

    def __enter__(self) -> DaskEngine:
        from distributed import Client, LocalCluster

        try:
            if self.scheduler == "local":
                self._quiet = _quiet_cluster_logs()
                self._quiet.__enter__()
                with _children_ignore_sigint():
                    self._cluster = LocalCluster(
                        n_workers=self.workers,
                        threads_per_worker=self.threads_per_worker,
                        processes=True,
                        dashboard_address=None,
                    )
                self.client = Client(self._cluster)
                cores = os.cpu_count() or 1
                self.numba_threads = max(1, cores // (self.workers * self.threads_per_worker))
            else:
                self.client = Client(self.scheduler, timeout=f"{self.connect_timeout_s}s")
        except (OSError, TimeoutError) as exc:
            self.__exit__()
            raise PipelineError(f"cannot reach the Dask scheduler {self.scheduler!r}: {exc}") from None
        return self

    def __exit__(self, *exc: object) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
        if self._quiet is not None:
            self._quiet.__exit__(None, None, None)
            self._quiet = None

    def __call__(self, job: RenderJob, tiles: Iterable[int]) -> Iterator[TileResult]:
        from distributed import KilledWorker, as_completed

        if self.client is None:
            raise RuntimeError("DaskEngine must be used inside a 'with' block")
        tiles = [int(t) for t in tiles]
        if not tiles:
            return
        shared = self.client.scatter(job, broadcast=True, hash=False)
        futures = self.client.map(
            _render_task, tiles, job=shared, numba_threads=self.numba_threads, pure=False
        )
        try:
            for fut in as_completed(futures):
                try:
                    result = fut.result()
                except KilledWorker as exc:  # a worker died (out of memory, killed) on this tile, repeatedly
                    raise PipelineError(
                        f"Dask workers died rendering a map tile ({' '.join(str(exc).split())[:200]}): "
                        "give them more memory, or render in this process"
                    ) from None
                yield result
        finally:
            self.client.cancel([*futures, shared])


@contextmanager
def tile_engine(cfg: ScaleConfig) -> Iterator[TileRenderer]:
    """The engine of ``cfg.scheduler``, open for the duration of the block."""
    if cfg.scheduler is None:
        yield render_serial
        return
    with DaskEngine(cfg.scheduler, cfg.workers, cfg.threads_per_worker, cfg.connect_timeout_s) as engine:
        yield engine


def engine_name(cfg: ScaleConfig) -> str:
    """``"serial"``, ``"dask-local"`` or ``"dask tcp://..."``, for summaries."""
    if cfg.scheduler is None:
        return "serial"
    return "dask-local" if cfg.scheduler == "local" else f"dask {cfg.scheduler}"
