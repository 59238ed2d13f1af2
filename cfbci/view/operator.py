"""The operator page's commands (``POST /control``) and session starts (``/start``).

The page posts ``{"session": ID, "command": "pause" | "resume" | "end" | "target"}`` (with
``"target"``: the target the subject chose) and the view publishes the ``control``
message (docs/protocol.md, "Operator controls") with its own Zenoh session, so with its own
credentials where access control is on (the operator role, docs/deployment.md). The
answer is ``{"sent": COMMAND, "seq": N}`` once published, or status 400 with
``{"error": WHY}`` for a request that breaks the protocol; the service's answer comes
back to the page as the session's events (``session_paused``, ..., or an ``error``).

``POST /start`` starts a session, its source in a process of its own connected to the
view's Zenoh endpoints, after checking it as the source and the service would; a refusal
is status 400 with ``{"error": WHY}``, shown inline. ``"source"`` chooses the source:

* ``"simulated"`` (the default): the simulated user. The page posts its settings
  (`start_settings`: ``session``, ``world``, ``frame``, ``grid``, ``steps``, ``seed``,
  ``dataset`` ("synthetic" or a dataset file on the view's machine), ``accuracy`` (the
  synthetic generator's), ``learner`` (settings by name) and ``interval`` (seconds
  between a move and its answer)); the view checks them (the dataset read,
  `cfbci.service.admission.check_config` with the default limits, the protocol's
  fields) and runs `acquisition.simulated_source.run_source`.
* ``"lsl"``: LSL streams through ``cfbci lsl-bridge``: the EEG stream, the onset-marker
  stream and the bridge's options (`cfbci.view.lsl_start`, which checks them); the view
  runs that ``cfbci lsl-bridge`` command line.

The answer is ``{"started": ID, "config": ..., "command": CLI}`` (``command``: the
``cfbci`` command line of an LSL start). ``GET /start`` says whether starts are possible
(``{"disabled": WHY or null, "started": [...]}``, each source started with ``session``,
``command`` and ``exit``, its exit status or null while it runs), and ``GET
/lsl-streams`` lists the LSL streams on the network (``{"streams": [...]}``,
`cfbci.view.lsl_start.list_streams`). A view that is a Zenoh client of a router
(``mode: "client"``) or logs in with a user starts nothing: its sources would connect
to its endpoints without credentials of their own. The sources started are stopped with
the view.

Every request passes the view's guard first (token, ``Host``, ``Origin``): a page of
another site cannot post.
"""

from __future__ import annotations

import asyncio
import json
import logging
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh
from aiohttp import web

from cfbci.service.admission import Rejection, check_config
from cfbci.service.limits import ServiceLimits
from cfbci.service.process import SPAWN
from cfbci.view.lsl_start import check_bridge, list_streams, typed_settings
from wire import protocol
from wire.operator import control_fields
from wire.protocol import ProtocolError
from wire.transport import Outbox

if TYPE_CHECKING:
    from acquisition.simulated_source import SourceSettings

log = logging.getLogger("cfbci.view")

#: The largest request body read, bytes.
MAX_REQUEST = 4096
#: Seconds a source is given to end after SIGTERM when the view stops.
STOP_SECONDS = 10.0


@dataclass
class Started:
    """A source started from the page: its session, its command line (LSL), its process."""

    session: str
    command: str | None
    process: BaseProcess | subprocess.Popen[bytes]

    def exit_status(self) -> int | None:
        """The process's exit status, None while it runs."""
        if isinstance(self.process, subprocess.Popen):
            return self.process.poll()
        return self.process.exitcode

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after `STOP_SECONDS`; wait for the end."""
        self.process.terminate()
        if isinstance(self.process, subprocess.Popen):
            try:
                self.process.wait(STOP_SECONDS)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        else:
            self.process.join(STOP_SECONDS)
            if self.process.exitcode is None:
                self.process.kill()
                self.process.join()


def start_refusal(config: zenoh.Config) -> str | None:
    """Why a view with this Zenoh configuration starts no session (None: it may)."""
    mode = json.loads(config.get_json("mode"))
    user = json.loads(config.get_json("transport/auth/usrpwd/user") or "null")
    if mode != "client" and not user:
        return None
    login = f"as user {user!r}" if user else f"in {mode} mode"
    return (f"Starting sessions here is off: this view logs in to Zenoh {login} (its "
            "--zenoh-config file), and a source it started would connect to its endpoints "
            "without credentials of its own, which a router with access control refuses. "
            "Start the session's source from a terminal with its user's file (cfbci source "
            "--zenoh-config source.json5 ..., docs/deployment.md).")


class Operator:
    """Publishes the operator page's commands once the view's Zenoh session is open, and
    starts sessions."""

    def __init__(self) -> None:
        self._outbox: Outbox | None = None
        self._endpoints: list[str] = []  # where the sources started here connect
        self._refusal: str | None = "the view is not connected to Zenoh yet"
        self._started: list[Started] = []
        self._listed: set[str] = set()  # the LSL stream names last listed

    def routes(self, app: web.Application) -> None:
        """Add ``POST /control``, ``GET`` and ``POST /start`` and ``GET /lsl-streams``."""
        app.router.add_post("/control", self.post)
        app.router.add_get("/start", self.status)
        app.router.add_post("/start", self.start)
        app.router.add_get("/lsl-streams", self.streams)

    @contextmanager
    def attached(self, session: zenoh.Session, config: zenoh.Config) -> Iterator[None]:
        """Publish with ``session`` (opened with ``config``) in the ``with`` block; after
        it, undeclare the publishers and stop the sources started here."""
        self._outbox = Outbox(session)
        self._endpoints = [
            endpoint for key in ("listen/endpoints", "connect/endpoints")
            for endpoint in json.loads(config.get_json(key) or "[]")
        ]
        self._refusal = start_refusal(config)
        try:
            yield
        finally:
            self._outbox.close()
            self._outbox = None
            for started in self._started:
                started.stop()

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

    async def status(self, _: web.Request) -> web.Response:
        """``GET /start``: whether starts are possible, and the sources started."""
        return web.json_response({"disabled": self._refusal, "started": [
            {"session": s.session, "command": s.command, "exit": s.exit_status()}
            for s in self._started
        ]})

    async def streams(self, _: web.Request) -> web.Response:
        """``GET /lsl-streams``: the LSL streams on the network."""
        try:
            listed = await asyncio.get_running_loop().run_in_executor(None, list_streams)
        except ValueError as error:
            return web.json_response({"error": str(error)}, status=400)
        self._listed = {stream["name"] for stream in listed}
        return web.json_response({"streams": listed})

    async def start(self, request: web.Request) -> web.Response:
        """``POST /start``: check a session and start its source (see the module
        docstring)."""
        try:
            body = await _json(request)
            if self._refusal is not None:
                raise ValueError(self._refusal)
            source = body.get("source", "simulated")
            if source == "lsl":
                bridge = await asyncio.get_running_loop().run_in_executor(
                    None, check_bridge, body, self._endpoints, self._listed)
                process: BaseProcess | subprocess.Popen[bytes] = subprocess.Popen(
                    bridge.process_arguments, stdin=subprocess.DEVNULL)
                started = Started(bridge.session, bridge.shown, process)
                config = bridge.config
            elif source == "simulated":
                started, config = self._simulated(body)
            else:
                raise ValueError(f"setting 'source' must be 'simulated' or 'lsl'; got {source!r}")
        except ProtocolError as error:
            return web.json_response({"error": error.problem}, status=400)
        except (ValueError, OSError) as error:
            return web.json_response({"error": str(error)}, status=400)
        self._started.append(started)
        log.info("operator: started the %s source of session %r%s", source, started.session,
                 f": {started.command}" if started.command else "")
        return web.json_response({"started": started.session, "config": config,
                                  "command": started.command})

    def _simulated(self, body: dict[str, Any]) -> tuple[Started, dict[str, Any]]:
        """Check a simulated user's session and start its source: it and its config.

        Raises
        ------
        ValueError, OSError, ProtocolError
            Saying what the source or the service would refuse.
        """
        from acquisition.simulated_source import run_source, session_config  # the data stack

        settings = start_settings(body)
        config = session_config(settings)  # the dataset read, as the source does
        sid = settings.session
        check_config(config, ServiceLimits(), lambda problem: Rejection(problem, sid, 0, 0))
        protocol.encode(protocol.Message("config", sid, 0, 0, config))
        process = SPAWN.Process(target=run_source, args=(settings, [], self._endpoints),
                                name=f"cfbci-source-{sid}", daemon=True)
        process.start()
        return Started(sid, None, process), config


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


def start_settings(body: dict[str, Any]) -> SourceSettings:
    """The simulated source's settings of a ``POST /start`` body.

    Raises
    ------
    ValueError
        Naming a missing session id, an unknown setting, or one of the wrong type.
    """
    from acquisition.simulated_source import SourceSettings
    from acquisition.sources import DataSpec

    values = typed_settings(body, START_FIELDS)
    dataset = values["dataset"]
    path = None if dataset == "synthetic" else Path(dataset)
    data = DataSpec(path, values["accuracy"]) if "accuracy" in values else DataSpec(path)
    return SourceSettings(
        body["session"], data=data, seed=values["seed"], steps=values["steps"],
        grid=values["grid"], frame=values["frame"], learner=values["learner"],
        interval=values["interval"], world=values["world"],
    )
