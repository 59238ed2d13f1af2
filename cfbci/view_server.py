"""The server of ``cfbci view``: the live view of sessions in a web browser, fed from Zenoh.

One process is both a Zenoh peer and an HTTP server (aiohttp). It subscribes to every
session's ``config``, ``move``, ``state``, ``event``, ``truth`` and ``epoch``
(``cfbci/*/<kind>``, docs/protocol.md), keeps what the pages show of each session
(:mod:`cfbci.view_model`) and sends it to the pages over a WebSocket: a snapshot when a
page starts following a session, then one patch per message. Pages and scripts are
package files (``cfbci/view_static``): nothing is fetched from elsewhere.

Routes:

* ``/``: the operator view (grid and belief heat map, confidence and threshold, targets,
  balanced accuracy, latency; a session picker); ``/?session=ID`` follows ``ID``.
* ``/subject``: the subject view (the grid and the agent only, full screen, for the
  stimulus screen); ``/subject?session=ID``.
* ``/ws``: the WebSocket. The server sends ``{"type": "sessions", "sessions": [...]}``
  whenever the list of sessions changes, and for the followed session
  ``{"type": "snapshot", ...}`` then ``{"type": "update", "session", "set", "append"}``
  (or ``"reset"``); the page sends ``{"follow": ID}``.

The moves, states and events come from the service the view connects to. The configs,
truths and epochs come from the sources: the view listens on a loopback endpoint of its
own (a free port unless ``--listen`` is given), so that sources, told of it by the
service's Zenoh gossip, connect to it. A source that reaches the view only after sending
its config (or a view started later) leaves the view without the config: the grid is then
inferred from the states (:func:`cfbci.view_model.layout_of`), the threshold is the
default and the number of steps unknown; a source that connects to the view's endpoint
itself is sure to be seen whole. Like a recorder, the view subscribes to configs: a
subscriber to a config key is no proof that the service is up.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh
from aiohttp import WSMsgType, web

from cfbci.view_model import SessionBook, SessionView
from wire import protocol
from wire.protocol import NO_SESSION, ProtocolError
from wire.transport import Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

log = logging.getLogger("cfbci.view")

#: The page files, shipped as package data.
STATIC = Path(__file__).with_name("view_static")
#: Message kinds the view subscribes to, on every session.
KINDS = ("config", "move", "state", "event", "truth", "epoch")
#: Messages waiting for one page; a page that falls this far behind is disconnected (it
#: reconnects and starts again from a snapshot).
CLIENT_BACKLOG = 4096


class _LoopSink:
    """Where the Zenoh pumps put what they receive: handed to ``callback`` on the event loop
    (so that every session's bookkeeping runs on one thread)."""

    def __init__(
        self, loop: asyncio.AbstractEventLoop, callback: Callable[[Received], None]
    ) -> None:
        self._loop, self._callback = loop, callback

    def put(self, item: Received) -> None:
        self._loop.call_soon_threadsafe(self._callback, item)


class _Page:
    """One connected page: the session it follows and its outgoing messages."""

    def __init__(self, socket: web.WebSocketResponse) -> None:
        self.socket = socket
        self.session: str | None = None
        self.outbox: asyncio.Queue[str] = asyncio.Queue(CLIENT_BACKLOG)
        self.closing: asyncio.Future[Any] | None = None

    def push(self, text: str) -> None:
        """Queue a message; a page too far behind is closed (it reconnects)."""
        if self.closing is not None:
            return
        try:
            self.outbox.put_nowait(text)
        except asyncio.QueueFull:
            log.warning("a page fell %d messages behind: disconnected", CLIENT_BACKLOG)
            self.closing = asyncio.ensure_future(self.socket.close())

    async def write(self) -> None:
        """Send the queued messages, in order, until cancelled."""
        while True:
            await self.socket.send_str(await self.outbox.get())


class ViewServer:
    """The sessions seen on Zenoh and the pages following them (all on the event loop)."""

    def __init__(self) -> None:
        self.book = SessionBook()
        self.pages: set[_Page] = set()

    def receive(self, received: Received) -> None:
        """Take in one sample from Zenoh and tell the pages what changed."""
        try:
            message = protocol.decode(received.data, key_expr=received.key_expr)
        except ProtocolError as error:
            log.warning("dropped a message: %s", error)
            return
        if message.session == NO_SESSION:
            log.warning("service error about an unusable session: %s", message.fields)
            return
        try:
            patch, listing_changed = self.book.update(message, received.t_ns)
        except ValueError as error:
            log.warning("dropped %s of session %r seq %d: %s", message.kind, message.session,
                        message.seq, error)
            return
        if patch is not None:
            text = json.dumps({"type": "update", "session": message.session, **patch})
            for page in self.pages:
                if page.session == message.session:
                    page.push(text)
        if listing_changed:
            self._push_listing()

    def _push_listing(self, pages: Sequence[_Page] | None = None) -> None:
        text = json.dumps({"type": "sessions", "sessions": self.book.listing()})
        for page in self.pages if pages is None else pages:
            page.push(text)

    def _follow(self, page: _Page, data: str) -> None:
        try:
            session = json.loads(data)["follow"]
            protocol.key(session, "move")  # ProtocolError on a bad id
        except (ValueError, KeyError, TypeError) as error:
            problem = f"bad request {data[:100]!r}: {error}"
            page.push(json.dumps({"type": "error", "message": problem}))
            return
        page.session = session
        view = self.book.sessions.get(session) or SessionView(session)
        page.push(json.dumps({"type": "snapshot", **view.snapshot()}))

    async def websocket(self, request: web.Request) -> web.WebSocketResponse:
        """``/ws``: the session list, then the followed session's snapshot and patches."""
        socket = web.WebSocketResponse(heartbeat=20.0)
        await socket.prepare(request)
        page = _Page(socket)
        self.pages.add(page)
        writer = asyncio.ensure_future(page.write())
        self._push_listing([page])
        try:
            async for frame in socket:
                if frame.type == WSMsgType.TEXT:
                    self._follow(page, frame.data)
        finally:
            self.pages.discard(page)
            writer.cancel()
        return socket

    def app(self) -> web.Application:
        """The aiohttp application: the two pages, their files and the WebSocket."""

        def page(name: str) -> Callable[[web.Request], Any]:
            async def handler(_: web.Request) -> web.FileResponse:
                return web.FileResponse(STATIC / name, headers={"Cache-Control": "no-cache"})

            return handler

        app = web.Application()
        app.router.add_get("/", page("operator.html"))
        app.router.add_get("/subject", page("subject.html"))
        app.router.add_get("/ws", self.websocket)
        app.router.add_static("/static", STATIC)
        return app


async def _serve(
    zenoh_config: zenoh.Config,
    host: str,
    port: int,
    on_ready: Callable[[str, int], None],
) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    server = ViewServer()
    runner = web.AppRunner(server.app())
    await runner.setup()
    with zenoh.open(zenoh_config) as session:
        sink = _LoopSink(loop, server.receive)
        pumps = [Pump(session, f"{protocol.PREFIX}/*/{kind}", kind, sink) for kind in KINDS]
        try:
            site = web.TCPSite(runner, host, port)
            try:
                await site.start()
            except OSError as error:
                raise ValueError(f"cannot serve HTTP on {host}:{port}: {error}") from None
            on_ready(host, runner.addresses[0][1])
            await stop.wait()
        finally:
            for pump in pumps:
                pump.close()
            await runner.cleanup()


def run_view(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zenoh_config: Path | None = None,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    on_ready: Callable[[str, int], None],
) -> None:
    """Serve the view until SIGINT or SIGTERM.

    Parameters
    ----------
    listen : sequence of str
        Zenoh endpoints to listen on (default without ``zenoh_config``: a free loopback
        port, see the module).
    connect : sequence of str
        Zenoh endpoints to connect to (the service's, or a router's).
    zenoh_config : Path or None
        A Zenoh JSON5 file merged over the defaults (``wire.zenoh_config``), e.g. client
        mode, TLS and credentials for a router deployment (docs/deployment.md).
    host : str
        Address the HTTP server binds (``0.0.0.0`` to serve other machines).
    port : int
        HTTP port; 0 picks a free one.
    on_ready : callable
        ``on_ready(host, port)`` once the server accepts connections.

    Raises
    ------
    FileNotFoundError, ValueError
        On a bad ``zenoh_config`` file, or an HTTP address that cannot be bound.
    """
    if not listen and zenoh_config is None:
        listen = [free_tcp_endpoint()]
    config = peer_config(listen, connect, zenoh_config)  # a bad file fails before serving
    asyncio.run(_serve(config, host, port, on_ready))
