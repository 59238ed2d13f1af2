"""Run independent jobs on Dask distributed, with a progress bar, results in job order.

Where the jobs run is a `Scheduler`:

* **in this process**, one after the other: one worker (``--jobs 1``, or a single job) and
  no ``--scheduler``;
* **a local cluster** started for the run and closed after it: ``--scheduler local``, or
  more than one worker without ``--scheduler`` (the default ``--jobs`` is every core). It is
  a Dask ``LocalCluster`` of ``workers`` worker processes (spawned by Dask's nannies, one
  thread each), everything on loopback: scheduler, workers and the scheduler's HTTP
  endpoint (health checks; the dashboard only where bokeh is installed) on 127.0.0.1, at
  free ports;
* **an existing cluster**: ``--scheduler tcp://HOST:PORT`` joins its scheduler; its workers
  must run the same cfbci (they import the job functions by name) and see the files the
  jobs name (dataset paths, recordings, a report's output directory) at the same paths.

A job's result depends only on the job, so every place gives the same results (the tests
compare a local cluster with a single-process run). Every process that runs jobs first runs
`cfbci.memory.keep_freed_memory` (Dask workers through a worker plugin, so also those
that join the cluster later: `cfbci.offline.dask_worker.KeepFreedMemory`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from cfbci.memory import keep_freed_memory

T = TypeVar("T")

#: Seconds to wait for the scheduler of an existing cluster to answer.
CONNECT_TIMEOUT = 10.0
#: Where a local cluster's scheduler serves HTTP: loopback, a free port (not 8787, which
#: another cluster on the machine may hold).
LOOPBACK_ANY_PORT = "127.0.0.1:0"
_ADDRESS_SCHEMES = ("tcp://", "tls://", "ws://", "wss://")


@dataclass(frozen=True)
class Scheduler:
    """Where jobs run (see the module docstring).

    Attributes
    ----------
    address : str or None
        None: this process, or a local cluster when ``workers`` > 1; "local": a local
        cluster; else the address of an existing Dask scheduler (``tcp://HOST:PORT``).
    workers : int
        Worker processes of a local cluster (at most one per job is started); unused with
        an existing cluster, which has its own.
    connect_timeout : float
        Seconds to wait for an existing cluster's scheduler.
    """

    address: str | None = None
    workers: int = 1
    connect_timeout: float = CONNECT_TIMEOUT

    @classmethod
    def from_options(cls, scheduler: str | None, jobs: int) -> Scheduler:
        """The scheduler of ``--scheduler`` and ``--jobs`` (0: one worker per core).

        Raises
        ------
        ValueError
            If ``scheduler`` is neither "local" nor a scheduler address, if ``jobs`` is
            negative, or if ``jobs`` is given with an existing cluster.
        """
        if jobs < 0:
            raise ValueError(f"--jobs must be 0 (every core) or more; got {jobs}")
        if scheduler is not None and scheduler != "local":
            if not scheduler.startswith(_ADDRESS_SCHEMES):
                raise ValueError(
                    f"--scheduler must be 'local' or a Dask scheduler address such as "
                    f"tcp://HOST:PORT; got {scheduler!r}"
                )
            if jobs:
                raise ValueError(
                    f"--jobs sets the workers of a local cluster; the cluster at {scheduler} "
                    "has its own workers: leave --jobs out"
                )
        return cls(scheduler, jobs if jobs > 0 else (os.cpu_count() or 1))

    def describe(self) -> str:
        """A short description, e.g. ``local cluster, 2 workers``."""
        if self.address is None and self.workers <= 1:
            return "this process"
        if self.address in (None, "local"):
            return f"local cluster, {self.workers} worker{'s' if self.workers > 1 else ''}"
        return f"cluster at {self.address}"


def run_parallel(
    function: Callable[[Any], T],
    jobs: Iterable[Any],
    *,
    scheduler: Scheduler,
    description: str,
    console: Console,
) -> list[T]:
    """``[function(job) for job in jobs]``, where ``scheduler`` says, in job order.

    ``function`` must be importable by name (a module-level function of the project) and
    the jobs picklable. A job that raises stops the run with its exception.

    Raises
    ------
    ValueError
        If the scheduler of an existing cluster does not answer in time.
    """
    jobs = list(jobs)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=True) as progress:
        bar = progress.add_task(description, total=len(jobs))
        if scheduler.address is None and min(scheduler.workers, len(jobs)) <= 1:
            keep_freed_memory()
            results = []
            for job in jobs:
                results.append(function(job))
                progress.advance(bar)
            return results
        return _run_on_dask(function, jobs, scheduler, lambda: progress.advance(bar))


def _run_on_dask(
    function: Callable[[Any], T], jobs: Sequence[Any], scheduler: Scheduler,
    advance: Callable[[], None],
) -> list[T]:
    from distributed import Client, LocalCluster, as_completed  # here: a heavy import

    from cfbci.offline.dask_worker import KeepFreedMemory

    cluster = None
    if scheduler.address in (None, "local"):
        cluster = LocalCluster(
            n_workers=max(1, min(scheduler.workers, len(jobs))), threads_per_worker=1,
            processes=True, host="127.0.0.1", dashboard_address=LOOPBACK_ANY_PORT,
            # A job's error reaches the caller through its future; a worker's heartbeat to
            # the scheduler closed at the end of the run is logged as an ERROR traceback.
            silence_logs=logging.CRITICAL,
        )
        address = cluster.scheduler_address
    else:
        address = scheduler.address
    try:
        try:
            client = Client(address, timeout=scheduler.connect_timeout, set_as_default=False)
        except OSError as error:  # distributed's connection time-out is an OSError
            raise ValueError(
                f"--scheduler {address}: no Dask scheduler answered within "
                f"{scheduler.connect_timeout:g} s ({error})"
            ) from error
        with client:
            client.register_plugin(KeepFreedMemory())
            futures = client.map(function, jobs, pure=False)
            index = {future.key: i for i, future in enumerate(futures)}
            results: list[Any] = [None] * len(jobs)
            for future in as_completed(futures, loop=client.loop):
                results[index[future.key]] = future.result()
                advance()
            return results
    finally:
        if cluster is not None:
            cluster.close()
