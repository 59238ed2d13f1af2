"""The operator page's commands (``POST /control``) and session starts (``POST /start``).

The page posts ``{"session": ID, "command": "pause" | "resume" | "end" | "target"}`` (with
``"target"``: the target the subject chose) and the view publishes the ``control``
message (docs/protocol.md, "Operator controls") with its own Zenoh session, so with its own
credentials where access control is on (the operator role, docs/deployment.md). The
answer is ``{"sent": COMMAND, "seq": N}`` once published, or status 400 with
``{"error": WHY}`` for a request that breaks the protocol; the service's answer comes
back to the page as the session's events (``session_paused``, ..., or an ``error``).

``POST /start`` starts a session of the simulated user: the page posts its settings
(`start_settings`: ``session``, ``world``, ``frame``, ``grid``, ``steps``, ``seed``,
``dataset`` ("synthetic" or a dataset file on the view's machine), ``accuracy`` (the
synthetic generator's), ``learner`` (settings by name) and ``interval`` (seconds between
a move and its answer)); the view checks them as the source and the service would (the
dataset read, `cfbci.service.admission.check_config` with the default limits, the
protocol's fields) and answers 400 with ``{"error": WHY}``, shown inline, or starts the
simulated source (`acquisition.simulated_source.run_source`) in a process of its own,
connected to the view's Zenoh endpoints, and answers ``{"started": ID, "config": ...}``.
The sources it started are stopped with the view.

Both requests pass the view's guard first (token, ``Host``, ``Origin``): a page of another
site cannot post.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh
from aiohttp import web

from cfbci.service.admission import Rejection, check_config
from cfbci.service.limits import ServiceLimits
from cfbci.service.process import SPAWN
from wire import protocol
from wire.operator import control_fields
from wire.protocol import ProtocolError
from wire.transport import Outbox

if TYPE_CHECKING:
    from acquisition.simulated_source import SourceSettings

log = logging.getLogger("cfbci.view")

#: The largest request body read, bytes.
MAX_REQUEST = 4096


class Operator:
    """Publishes the operator page's commands once the view's Zenoh session is open."""

    def __init__(self) -> None:
        self._outbox: Outbox | None = None
        self._endpoints: list[str] = []  # where the sources started here connect
        self._sources: list[BaseProcess] = []

    def routes(self, app: web.Application) -> None:
        """Add ``POST /control`` and ``POST /start`` to the view's application."""
        app.router.add_post("/control", self.post)
        app.router.add_post("/start", self.start)

    @contextmanager
    def attached(self, session: zenoh.Session, config: zenoh.Config) -> Iterator[None]:
        """Publish with ``session`` (opened with ``config``) in the ``with`` block; after
        it, undeclare the publishers and stop the sources started here."""
        self._outbox = Outbox(session)
        self._endpoints = [
            endpoint for key in ("listen/endpoints", "connect/endpoints")
            for endpoint in json.loads(config.get_json(key) or "[]")
        ]
        try:
            yield
        finally:
            self._outbox.close()
            self._outbox = None
            for process in self._sources:
                process.terminate()
                process.join(10)

    async def post(self, request: web.Request) -> web.Response:
        """``POST /control``: publish one command (see the module docstring)."""
        try:
            body = await _json(request)
            if not isinstance(body.get("session"), str):
                raise ValueError('a command is {"session": ID, "command": ..., "target": ...}')
            fields = control_fields(body.get("command"), body.get("target"))
            if self._outbox is None:
                raise ValueError("the view is not connected to Zenoh yet")
            sent = self._outbox.send("control", body["session"], fields)
        except (ValueError, ProtocolError) as error:  # ProtocolError: a bad id or target
            return web.json_response({"error": str(error)}, status=400)
        log.info("operator: %s on session %r", fields, body["session"])
        return web.json_response({"sent": fields["command"], "seq": sent.seq})

    async def start(self, request: web.Request) -> web.Response:
        """``POST /start``: check a session's settings and start its simulated source
        (see the module docstring)."""
        from acquisition.simulated_source import run_source, session_config  # the data stack

        try:
            settings = start_settings(await _json(request))
            config = session_config(settings)  # the dataset read, as the source does
            sid = settings.session

            def reject(problem: str) -> Rejection:
                return Rejection(problem, sid, 0, 0)

            check_config(config, ServiceLimits(), reject)  # as the service would
            protocol.encode(protocol.Message("config", sid, 0, 0, config))
            if self._outbox is None:
                raise ValueError("the view is not connected to Zenoh yet")
        except ProtocolError as error:
            return web.json_response({"error": error.problem}, status=400)
        except (ValueError, OSError) as error:
            return web.json_response({"error": str(error)}, status=400)
        process = SPAWN.Process(target=run_source, args=(settings, [], self._endpoints),
                                name=f"cfbci-source-{sid}", daemon=True)
        process.start()
        self._sources = [p for p in self._sources if p.is_alive()] + [process]
        log.info("operator: started the simulated source of session %r", sid)
        return web.json_response({"started": sid, "config": config})


async def _json(request: web.Request) -> dict[str, Any]:
    """A request's JSON object body (at most `MAX_REQUEST` bytes).

    Raises
    ------
    ValueError
        On a missing, longer or non-object body.
    """
    if request.content_length is None or request.content_length > MAX_REQUEST:
        raise ValueError(f"a request is a JSON object of at most {MAX_REQUEST} bytes")
    body = json.loads(await request.text())
    if not isinstance(body, dict):
        raise ValueError("a request is a JSON object")
    return body


#: The settings of ``POST /start``: name -> (type, default; None: the source's).
START_FIELDS: dict[str, tuple[type, Any]] = {
    "world": (str, "grid"), "frame": (str, "feedback"), "grid": (int, 5),
    "steps": (int, 100), "seed": (int, 0), "dataset": (str, "synthetic"),
    "accuracy": (float, None), "learner": (dict, {}),
    "interval": (float, 1.0),
}


_KINDS = {int: "an integer", float: "a number", str: "a string", dict: "an object"}


def start_settings(body: dict[str, Any]) -> SourceSettings:
    """The simulated source's settings of a ``POST /start`` body.

    Raises
    ------
    ValueError
        Naming a missing session id, an unknown setting, or one of the wrong type.
    """
    from acquisition.simulated_source import SourceSettings
    from acquisition.sources import DataSpec

    unknown = sorted(set(body) - set(START_FIELDS) - {"session"})
    if unknown:
        raise ValueError(f"unknown setting(s) {', '.join(unknown)}; the settings are "
                         f"session, {', '.join(START_FIELDS)}")
    if not isinstance(body.get("session"), str) or not body["session"]:
        raise ValueError("give the session an id (a name, or USER/NAME)")
    values: dict[str, Any] = {}
    for name, (kind, default) in START_FIELDS.items():
        value = body.get(name, default)
        if value is None:  # the source's default
            continue
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool):
            raise ValueError(f"setting {name!r} must be {_KINDS[kind]}; got {value!r}")
        values[name] = value
    dataset = values["dataset"]
    path = None if dataset == "synthetic" else Path(dataset)
    data = DataSpec(path, values["accuracy"]) if "accuracy" in values else DataSpec(path)
    return SourceSettings(
        body["session"], data=data, seed=values["seed"], steps=values["steps"],
        grid=values["grid"], frame=values["frame"], learner=values["learner"],
        interval=values["interval"], world=values["world"],
    )
