"""``cfbci router``: a Zenoh router that joins hosts, and can enforce a deployment's policy.

A router-mode Zenoh session on the given endpoints, until SIGINT or SIGTERM. With a
``--zenoh-config`` file it is the deployment's gatekeeper (TLS, user/password
authentication, access control: see ``docs/deployment.md``); without one it only relays.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

log = logging.getLogger("cfbci.service.router")

#: First line the router prints once its Zenoh session is open (the endpoints follow).
READY = "router listening on"


def run_router(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zenoh_config: Path | None = None,
    on_ready: Callable[[list[str]], None] | None = None,
) -> None:
    """Run a Zenoh router until SIGINT or SIGTERM, then close it and return.

    Parameters
    ----------
    listen, connect : sequence of str
        Endpoints (see `wire.zenoh_config.router_config`).
    zenoh_config : Path or None
        Zenoh JSON5 configuration merged over the router defaults.
    on_ready : callable, optional
        Called with the listen endpoints once the router is open; by default they are
        printed to standard output as ``router listening on EP [EP ...]``.

    Raises
    ------
    FileNotFoundError, ValueError
        A missing or bad configuration, or no endpoint to listen on.
    RuntimeError
        If Zenoh cannot open the router (e.g. the port is taken, a certificate is missing).
    """
    import json

    import zenoh

    from wire.zenoh_config import router_config

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    config = router_config(listen, connect, zenoh_config)
    endpoints = json.loads(config.get_json("listen/endpoints"))
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        try:
            session = zenoh.open(config)
        except zenoh.ZError as error:
            raise RuntimeError(f"cannot open the Zenoh router on {endpoints}: {error}") from None
        with session:
            (on_ready or _print_ready)(endpoints)
            log.info("router %s on %s", session.info.zid(), endpoints)
            stop.wait()
        log.info("router stopped")
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _print_ready(endpoints: list[str]) -> None:
    print(READY, " ".join(endpoints), flush=True)
