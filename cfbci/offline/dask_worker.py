"""What every Dask worker that runs cfbci's jobs does first (a worker plugin).

Its own module so that importing `cfbci.offline.parallel` (and so the CLI) does not import
Dask distributed, which takes seconds; `cfbci.offline.parallel.run_parallel` imports it only
to run on a cluster.
"""

from __future__ import annotations

from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from cfbci.memory import keep_freed_memory


class KeepFreedMemory(WorkerPlugin):
    """Runs `cfbci.memory.keep_freed_memory` in every worker of the cluster, those
    that join or restart later included."""

    name = "cfbci-keep-freed-memory"

    def setup(self, worker: Any) -> None:
        keep_freed_memory()
