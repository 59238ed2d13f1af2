"""``cfbci serve``: a `cfbci.service.loop.PipelineService` in its own process, until
SIGINT or SIGTERM."""

from __future__ import annotations

import json
import logging
import signal
from collections.abc import Sequence
from pathlib import Path

import zenoh

from cfbci.memory import keep_freed_memory
from cfbci.service.limits import ServiceLimits
from cfbci.service.loop import PipelineService, SessionEndHook
from wire.zenoh_config import peer_config

log = logging.getLogger("cfbci.service")


def serve(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    record_dir: Path | None = None,
    on_end: SessionEndHook | None = None,
    limits: ServiceLimits | None = None,
    zenoh_config: Path | None = None,
    resume: bool = True,
    service_id: str | None = None,
    prior_dir: Path | None = None,
) -> None:
    """Run a `PipelineService` until SIGINT or SIGTERM, then shut down cleanly.

    Recordings are closed and the Zenoh session is closed before returning. Meant as the
    main function of ``cfbci serve`` or of a spawned process.

    Parameters
    ----------
    listen, connect : sequence of str
        Zenoh endpoints (see `wire.zenoh_config.peer_config`).
    record_dir : Path or None
        Directory of the recordings (``<session>.mcap``); None records nothing. Unfinished
        sessions recorded there are resumed.
    on_end : callable or None
        See `PipelineService`.
    limits : ServiceLimits or None
        Default `cfbci.service.limits.ServiceLimits`.
    zenoh_config : Path or None
        Zenoh JSON5 configuration merged over the defaults (``--zenoh-config``).
    resume : bool
        Resume the unfinished sessions recorded in ``record_dir``.
    service_id : str or None
        See `PipelineService`.
    prior_dir : Path or None
        The prior store (`cfbci.service.priors`); default ``<record_dir>/priors``.
    """
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    keep_freed_memory()
    config = peer_config(listen, connect, zenoh_config)
    with zenoh.open(config) as session:
        service = PipelineService(
            session, record_dir, limits, on_end=on_end, resume=resume, service_id=service_id,
            prior_dir=prior_dir,
        )
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, lambda *_: service.stop())
        # The endpoints in force: the options', else the --zenoh-config file's.
        log.info("service %s serving on listen=%s connect=%s", service.registration.service,
                 json.loads(config.get_json("listen/endpoints")),
                 json.loads(config.get_json("connect/endpoints")))
        service.run()
    log.info("stopped")
