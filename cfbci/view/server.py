"""The server of ``cfbci view``: the live view of sessions in a web browser, fed from Zenoh.

One process is both a Zenoh peer and an HTTP server (aiohttp). It subscribes to every
session's ``config``, ``move``, ``state``, ``event``, ``truth`` and ``epoch``
(``cfbci/**/<kind>``, docs/protocol.md), keeps what the pages show of each session
(`cfbci.view.model`) and sends it to the pages over a WebSocket: a snapshot when a page
starts following a session, then one patch per message. Pages and scripts are package files
(``cfbci/view/static``): nothing is fetched from elsewhere.

Routes:

* ``/``: the operator view (belief heat map, confidence, targets, accuracy, latency, a
  session picker, the commands of `cfbci.view.operator`); ``/?session=ID`` follows ``ID``.
* ``/subject``: the subject view (the grid and the agent only, full screen, for the stimulus
  screen); ``/subject?session=ID``.
* ``/stimulus``: with a stimulus, its page's WebSocket (`cfbci.view.stimulus`).
* ``/ws``: the WebSocket, out: ``{"type": "sessions", "sessions": [...]}`` on a change of the
  list, then for the followed session ``{"type": "snapshot", ...}`` and ``{"type": "update",
  "session", "set", "append"}`` (or ``"reset"``); in: ``{"follow": ID}``.

Access (`Access`, `Guard`), checked on every request, the page files and the
WebSocket included, in this order:

* ``Host`` must name the view: the address it is bound to (unless a wildcard such as
  ``0.0.0.0``), ``localhost``, ``127.0.0.1`` or ``[::1]``, on its port, or a name given with
  ``--allow-host``. This refuses DNS rebinding (another site's name made to resolve to the
  view's address).
* ``Origin``, when the request has one (a browser sends it with every WebSocket), must be
  ``http://`` and one of those host names and port, or an origin given with
  ``--allow-origin``: a page of another site cannot follow the sessions.
* The access token (a random one per start unless given, printed in the addresses): in the
  query (``?token=...``), or in the cookie ``cfbci-view-<port>`` that a response to a
  request with a valid token in its query sets (HttpOnly, SameSite=Strict, for the browser's
  session), so that reloads, the page's files and its WebSocket need no token in their
  address. Compared in constant time.

A refused request gets 403 and a line that says why. Every response says
``Referrer-Policy: no-referrer`` (the token in an address never leaves in a Referer) and
``X-Frame-Options: DENY``.

The moves, states and events come from the service the view connects to. The configs, truths
and epochs come from the sources: the view listens on a loopback endpoint of its own (a free
port unless ``--listen`` is given), so that sources, told of it by the service's Zenoh
gossip, connect to it. A source that reaches the view only after sending its config (or a
view started later) leaves the view without the config: the grid is then inferred from the
states (`cfbci.view.model.layout_of`), the threshold is the default and the number of
steps unknown; a source that connects to the view's endpoint itself is sure to be seen
whole. Like a recorder, the view subscribes to configs: a subscriber to a config key is no
proof that the service is up.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import re
import signal
import socket
import urllib.parse
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh
from aiohttp import WSMsgType, web

from cfbci.view.model import SessionBook
from cfbci.view.operator import Operator
from wire import protocol
from wire.protocol import NO_SESSION, ProtocolError
from wire.transport import Pump, Received
from wire.zenoh_config import free_tcp_endpoint, peer_config

if TYPE_CHECKING:
    from cfbci.view.stimulus import Stimulus, StimulusSettings

log = logging.getLogger("cfbci.view")

#: The page files, shipped as package data.
STATIC = Path(__file__).with_name("static")
#: Message kinds the view subscribes to, on every session.
KINDS = ("config", "move", "state", "event", "truth", "epoch")
#: Messages waiting for one page; a page that falls this far behind is disconnected (it
#: reconnects and starts again from a snapshot).
CLIENT_BACKLOG = 4096
#: What an access token may hold, and its shortest length.
TOKEN_CHARACTERS = re.compile(r"[A-Za-z0-9._~-]*")
TOKEN_LENGTH = 16
#: Addresses that bind every interface: no host name of their own.
WILDCARDS = ("", "0.0.0.0", "::")
#: Host names every view answers to (on its port).
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
#: Headers of every response.
SECURITY_HEADERS = {"Referrer-Policy": "no-referrer", "X-Frame-Options": "DENY",
                    "X-Content-Type-Options": "nosniff"}


def check_token(token: str, source: str = "the token") -> None:
    """Refuse a token that is too short or needs escaping in an address.

    Raises
    ------
    ValueError
        Naming ``source`` (e.g. ``--token``) and what is wrong, never the token.
    """
    if not TOKEN_CHARACTERS.fullmatch(token):
        bad = sorted({c for c in token if not TOKEN_CHARACTERS.fullmatch(c)})
        raise ValueError(f"{source} may hold only the characters A-Z, a-z, 0-9, '.', '_', "
                         f"'~' and '-'; got {''.join(bad)!r}")
    if len(token) < TOKEN_LENGTH:
        raise ValueError(f"{source} must be at least {TOKEN_LENGTH} characters long; got "
                         f"{len(token)}")


def _host_port(value: str, default_port: int = 80) -> tuple[str, int]:
    """``(name, port)`` of ``NAME``, ``NAME:PORT`` or ``[IPv6]:PORT`` (a ``Host`` header's
    form), the name in lower case.

    Raises
    ------
    ValueError
        If ``value`` is not of that form.
    """
    parts = urllib.parse.urlsplit(f"//{value}")
    if not parts.hostname or parts.path or parts.query or parts.fragment or "@" in value:
        raise ValueError(f"{value!r} is not NAME or NAME:PORT")
    port = parts.port  # ValueError if not a port
    return parts.hostname, default_port if port is None else port


def _origin(value: str) -> tuple[str, str, int]:
    """``(scheme, name, port)`` of an origin ``http(s)://NAME[:PORT]`` (a trailing ``/``
    allowed).

    Raises
    ------
    ValueError
        If ``value`` is not of that form.
    """
    parts = urllib.parse.urlsplit(value)
    default = {"http": 80, "https": 443}.get(parts.scheme)
    extra = parts.path not in ("", "/") or parts.query or parts.fragment
    if default is None or not parts.netloc or extra:
        raise ValueError(f"{value!r} is not an origin http(s)://NAME[:PORT]")
    return (parts.scheme, *_host_port(parts.netloc, default))


def _shown_host(name: str, port: int) -> str:
    return f"[{name}]:{port}" if ":" in name else f"{name}:{port}"


@dataclass(frozen=True)
class Access:
    """Who may use the view.

    Attributes
    ----------
    token : str
        The token every request must carry (`check_token`).
    allow_hosts : tuple of str
        More host names the view may be reached under (a reverse proxy's, a machine
        name): ``NAME`` (on the view's port) or ``NAME:PORT``.
    allow_origins : tuple of str
        More origins ``http(s)://NAME[:PORT]`` whose pages may use the view.

    Raises
    ------
    ValueError
        On a bad token, host name or origin, naming it.
    """

    token: str
    allow_hosts: tuple[str, ...] = ()
    allow_origins: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        check_token(self.token)
        for option, values, parse in (("--allow-host", self.allow_hosts, _host_port),
                                      ("--allow-origin", self.allow_origins, _origin)):
            for value in values:
                try:
                    parse(value)
                except ValueError as error:
                    raise ValueError(f"{option}: {error}") from None


class Guard:
    """The checks of every request to a view bound to ``host`` and ``port`` (see the
    module): `middleware` refuses and sets the cookie, `prepare` adds the
    headers."""

    def __init__(self, access: Access, host: str, port: int) -> None:
        self.cookie = f"cfbci-view-{port}"
        self._token = access.token.encode()
        names = [*LOOPBACK_NAMES] + ([] if host in WILDCARDS else [host.strip("[]").lower()])
        self.hosts = {(name, port) for name in names} | {
            _host_port(value, port) for value in access.allow_hosts
        }
        self.origins = {_origin(value) for value in access.allow_origins}

    def refusal(self, request: web.Request) -> str | None:
        """Why ``request`` is refused (a line for the 403 answer), or None."""
        host = request.headers.get("Host", "")
        try:
            known = _host_port(host) in self.hosts
        except ValueError:
            known = False
        if not known:
            served = ", ".join(sorted(_shown_host(*pair) for pair in self.hosts))
            return (f"cfbci view does not answer to the host name {host!r} (only to "
                    f"{served}): another site's name for this address is refused (DNS "
                    "rebinding). To reach the view under that name, start it with "
                    "--allow-host NAME[:PORT].")
        origin = request.headers.get("Origin")
        if origin is not None:
            try:
                scheme, *pair = _origin(origin)
                allowed = (scheme == "http" and tuple(pair) in self.hosts) or (
                    (scheme, *pair) in self.origins
                )
            except ValueError:
                allowed = False
            if not allowed:
                return (f"a page of {origin!r} may not use cfbci view: only its own pages "
                        "may. To allow that origin (e.g. a reverse proxy), start the view "
                        "with --allow-origin ORIGIN.")
        given = request.query.get("token", request.cookies.get(self.cookie))
        if given is None or not hmac.compare_digest(given.encode(), self._token):
            return ("cfbci view needs its access token: open the address it printed when it "
                    "started (it ends in ?token=...), or add ?token=TOKEN to this one.")
        return None

    @web.middleware
    async def middleware(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        """Refuse a request that fails a check with 403; pass the others on, and set the
        cookie on the answer to a valid token in the query."""
        problem = self.refusal(request)
        if problem is not None:
            log.warning("refused %s %s: %s", request.method, request.path, problem)
            return web.Response(status=403, text=f"403 Forbidden: {problem}\n")
        response = await handler(request)
        if "token" in request.query and not response.prepared and response.status < 400:
            response.set_cookie(self.cookie, self._token.decode(), httponly=True,
                                samesite="Strict", path="/")
        return response

    @staticmethod
    async def prepare(_: web.Request, response: web.StreamResponse) -> None:
        """Add `SECURITY_HEADERS` to a response (every one, refusals included)."""
        response.headers.update(SECURITY_HEADERS)


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

    def __init__(self, hide_truth: bool = False) -> None:
        self.book = SessionBook(hide_truth)
        self.pages: set[_Page] = set()
        self.stimulus: Stimulus | None = None
        self.operator = Operator()  # the operator page's commands, POST /control

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
        page.push(json.dumps({"type": "snapshot", **self.book.view(session).snapshot()}))

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

    def app(self, guard: Guard) -> web.Application:
        """The aiohttp application: the two pages, their files and the WebSocket, every
        request checked by ``guard``."""

        def page(name: str) -> Callable[[web.Request], Any]:
            async def handler(_: web.Request) -> web.FileResponse:
                return web.FileResponse(STATIC / name, headers={"Cache-Control": "no-cache"})

            return handler

        app = web.Application(middlewares=[guard.middleware])
        app.on_response_prepare.append(guard.prepare)
        app.router.add_get("/", page("operator.html"))
        app.router.add_get("/subject", page("subject.html"))
        app.router.add_get("/ws", self.websocket)
        self.operator.routes(app)  # POST /control and /start
        if self.stimulus is not None:
            app.router.add_get("/stimulus", self.stimulus.socket)
            app.on_startup.append(self.stimulus.start)
            app.on_shutdown.append(self.stimulus.close)
        app.router.add_static("/static", STATIC)
        return app


def _bind(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host`` and ``port`` (0: a free one).

    Raises
    ------
    ValueError
        If the address cannot be bound.
    """
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        sock = socket.socket(family, kind, proto)
    except OSError as error:
        raise ValueError(f"cannot serve HTTP on {host}:{port}: {error}") from None
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
    except OSError as error:
        sock.close()
        raise ValueError(f"cannot serve HTTP on {host}:{port}: {error}") from None
    return sock


def base_address(host: str, port: int) -> str:
    """The address of a view bound to ``host`` and ``port``, as a browser on this machine
    opens it (a wildcard address as the loopback one)."""
    name = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host.strip("[]"))
    return f"http://{_shown_host(name, port)}"


async def _serve(
    zenoh_config: zenoh.Config,
    sock: socket.socket,
    guard: Guard,
    server: ViewServer,
    on_ready: Callable[[], None],
) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(signum, stop.set)
    runner = web.AppRunner(server.app(guard))
    await runner.setup()
    with zenoh.open(zenoh_config) as session, server.operator.attached(session, zenoh_config):
        sink = _LoopSink(loop, server.receive)
        pumps = [Pump(session, f"{protocol.PREFIX}/**/{kind}", kind, sink) for kind in KINDS]
        try:
            await web.SockSite(runner, sock).start()
            on_ready()
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
    access: Access,
    host: str = "127.0.0.1",
    port: int = 8080,
    hide_truth: bool = False,
    on_ready: Callable[[str], None],
    stimulus: StimulusSettings | None = None,
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
    access : Access
        The token and the extra host names and origins allowed (see the module).
    host : str
        Address the HTTP server binds (``0.0.0.0`` to serve other machines).
    port : int
        HTTP port; 0 picks a free one.
    hide_truth : bool
        Take in no truth message (`cfbci.view.model.SessionBook`).
    on_ready : callable
        ``on_ready(address)`` once the server accepts connections: its
        `base_address`, e.g. ``http://127.0.0.1:8080`` (without the token).
    stimulus : StimulusSettings or None
        Make the subject page the stimulus program (`cfbci.view.stimulus`).

    Raises
    ------
    FileNotFoundError, ValueError
        On a bad ``zenoh_config`` file, or an HTTP address that cannot be bound.
    """
    if not listen and zenoh_config is None:
        listen = [free_tcp_endpoint()]
    config = peer_config(listen, connect, zenoh_config)  # a bad file fails before serving
    sock = _bind(host, port)
    bound = sock.getsockname()[1]
    guard = Guard(access, host, bound)
    server = ViewServer(hide_truth)
    if stimulus is not None:
        from cfbci.view.stimulus import Stimulus  # pylsl only for a stimulus
        server.stimulus = Stimulus(stimulus, _Page)
    try:
        asyncio.run(_serve(config, sock, guard, server,
                           lambda: on_ready(base_address(host, bound))))
    finally:
        sock.close()
