"""Run independent jobs over worker processes with a progress bar.

Workers are started with the ``spawn`` method: a forked child inherits threads and
sessions (BLAS pools, Zenoh) in undefined states.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

T = TypeVar("T")


def run_parallel(
    function: Callable[[Any], T],
    jobs: Iterable[Any],
    *,
    workers: int,
    description: str,
    console: Console,
) -> list[T]:
    """``[function(job) for job in jobs]``, over ``workers`` processes, in job order."""
    jobs = list(jobs)
    results: list[T | None] = [None] * len(jobs)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=True) as progress:
        bar = progress.add_task(description, total=len(jobs))
        if workers <= 1:
            for index, job in enumerate(jobs):
                results[index] = function(job)
                progress.advance(bar)
        else:
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(workers, mp_context=context) as pool:
                futures = {pool.submit(function, job): i for i, job in enumerate(jobs)}
                for future in as_completed(futures):
                    results[futures[future]] = future.result()
                    progress.advance(bar)
    return results  # type: ignore[return-value]
