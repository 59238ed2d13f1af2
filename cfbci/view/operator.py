"""The operator page's commands: ``POST /control`` of ``cfbci view``, published on Zenoh.

The page posts ``{"session": ID, "command": "pause" | "resume" | "end" | "target"}`` (with
``"target"``: the target the subject chose) and the view publishes the ``control``
message (docs/protocol.md, "Operator controls") with its own Zenoh session, so with its own
credentials where access control is on (the operator role, docs/deployment.md). The
answer is ``{"sent": COMMAND, "seq": N}`` once published, or status 400 with
``{"error": WHY}`` for a request that breaks the protocol; the service's answer comes
back to the page as the session's events (``session_paused``, ..., or an ``error``).
The request passes the view's guard first (token, ``Host``, ``Origin``): a page of another
site cannot post.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from contextlib import contextmanager

import zenoh
from aiohttp import web

from wire.operator import control_fields
from wire.protocol import ProtocolError
from wire.transport import Outbox

log = logging.getLogger("cfbci.view")

#: The largest request body read, bytes.
MAX_REQUEST = 4096


class Operator:
    """Publishes the operator page's commands once the view's Zenoh session is open."""

    def __init__(self) -> None:
        self._outbox: Outbox | None = None

    @contextmanager
    def attached(self, session: zenoh.Session) -> Iterator[None]:
        """Publish with ``session`` in the ``with`` block; the publishers undeclared after."""
        self._outbox = Outbox(session)
        try:
            yield
        finally:
            self._outbox.close()
            self._outbox = None

    async def post(self, request: web.Request) -> web.Response:
        """``POST /control``: publish one command (see the module docstring)."""
        try:
            if request.content_length is None or request.content_length > MAX_REQUEST:
                raise ValueError(f"a command is a JSON object of at most {MAX_REQUEST} bytes")
            body = json.loads(await request.text())
            if not isinstance(body, dict) or not isinstance(body.get("session"), str):
                raise ValueError('a command is {"session": ID, "command": ..., "target": ...}')
            fields = control_fields(body.get("command"), body.get("target"))
            if self._outbox is None:
                raise ValueError("the view is not connected to Zenoh yet")
            sent = self._outbox.send("control", body["session"], fields)
        except (ValueError, ProtocolError) as error:  # ProtocolError: a bad id or target
            return web.json_response({"error": str(error)}, status=400)
        log.info("operator: %s on session %r", fields, body["session"])
        return web.json_response({"sent": fields["command"], "seq": sent.seq})
