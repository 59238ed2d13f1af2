"""A service (or any function) in a spawned process, stopped with SIGTERM.

Spawned, not forked: a forked child's Zenoh session silently drops messages. The process
must exit cleanly on SIGTERM (the service closes its recordings first); a process that
does not end within the timeout is killed, and any exit status but 0 is an error.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from multiprocessing.process import BaseProcess
from typing import Any

#: Seconds a stopped process may take to exit before it is killed.
STOP_TIMEOUT = 60.0
SPAWN = multiprocessing.get_context("spawn")


@contextmanager
def spawned(
    target: Callable[..., Any],
    *args: Any,
    name: str = "cfbci-service",
    **kwargs: Any,
) -> Iterator[BaseProcess]:
    """Run ``target(*args, **kwargs)`` in a spawned process for the ``with`` block.

    Raises
    ------
    RuntimeError
        When the process exits with another status than 0 after SIGTERM (killed: it did
        not end within `STOP_TIMEOUT` seconds).
    """
    process = SPAWN.Process(target=target, args=args, kwargs=kwargs, name=name)
    process.start()
    try:
        yield process
    finally:
        process.terminate()
        process.join(STOP_TIMEOUT)
        if process.is_alive():
            process.kill()
            process.join()
    if process.exitcode != 0:
        raise RuntimeError(f"{name} exited with status {process.exitcode} after SIGTERM")
