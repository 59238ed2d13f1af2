"""The subject page as the stimulus program (``cfbci view --stimulus``).

``cfbci lsl-bridge`` forwards every move of the service on an LSL marker stream (JSON
moves, ``acquisition.lsl_streams.move_marker``) and cuts each epoch around the stimulus
program's onset marker ``onset <step>``. With ``--stimulus``, the view is that program:

* a thread reads the bridge's move stream (resolved by name, again when lost) and hands
  every move to the event loop (`Stimulus.take_move`);
* one subject page at a time is *the stimulus page*: it opens a WebSocket of its own,
  ``/stimulus`` (guarded as every request to the view), and claims the role
  (``{"type": "stimulus"}``; a second page is told that another one has it, and gets the
  role when the first one leaves). The server
  sends it the settings, then pings it continuously; the page answers each ping with its
  clock (``performance.now()``), and the offset of the page's clock to this machine's LSL
  clock is estimated from the fastest round trips (``acquisition.clock_sync.ClockSync``,
  uncertainty kept);
* once the offset is known, the server sends the page each move to show (``show``, with a
  number of its own); the page shows it full screen no sooner than the inter-action
  interval after the last onset, in the frame of a ``requestAnimationFrame`` callback,
  and reports that callback's timestamp (the frame's start, in the page's clock), whether
  the page was visible, the intervals between the frames before and after it and the
  refresh period it measures (the median frame interval);
* the server maps the frame's start to the LSL clock and pushes ``onset <step>`` on its
  marker outlet (``--onsets``) with that timestamp. A show that was invalid (the page
  hidden, or a frame interval around it longer than ``frame_tolerance`` refresh periods:
  a dropped frame) is pushed as ``invalid-onset <step> <reason>``, which the bridge
  ignores as no onset, and the move is shown again after the interval, as the bridge's
  ``repeat`` asks for a move whose epoch could not be cut. A report of a show that is no
  longer current (a newer move came) is dropped.

Every onset, valid or not, is logged and, with ``onset_log``, appended to a JSON Lines
file. Messages of the stimulus socket:

* page to server: ``{"type": "stimulus"}``, ``{"type": "pong", "id", "page_ms"}``,
  ``{"type": "onset", "show", "step", "repeat", "frame_ms", "valid", "reason",
  "period_ms", "before_ms", "after_ms"}``;
* server to page: ``{"type": "stimulus", "settings" | "refused"}`` (a view without
  ``--stimulus`` has no ``/stimulus``: the page's socket never opens),
  ``{"type": "ping", "id"}``, ``{"type": "show", "show", "move"}``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import pylsl
from aiohttp import WSMsgType, web
from pylsl.util import LostError

from acquisition.clock_sync import ClockSync
from acquisition.lsl_bridge import DEFAULT_MOVES
from acquisition.lsl_streams import marker_outlet, parse_move_marker, resolve_inlet

log = logging.getLogger("cfbci.view.stimulus")

#: Name of the onset marker outlet (the bridge's ``--markers``).
DEFAULT_ONSETS = "cfbci-onsets"
#: Seconds between two pings: while the offset is not known yet, then once it is.
PING_FAST, PING_SLOW = 0.02, 0.25
#: Frames the photodiode patch stays white from an onset's frame (50 ms at 60 Hz).
PATCH_FRAMES = 3
#: Message types of the stimulus socket sent by a page.
PAGE_TYPES = ("stimulus", "pong", "onset")


class Page(Protocol):
    """A connected page (the view's): messages queued by ``push``, sent by ``write``."""

    def push(self, text: str) -> None: ...

    async def write(self) -> None: ...


@dataclass(frozen=True)
class StimulusSettings:
    """What the stimulus page shows and where the moves and onsets go.

    Attributes
    ----------
    moves : str
        Name of the bridge's LSL move stream.
    onsets : str
        Name of the onset marker outlet (the bridge's ``--markers``).
    interval : float
        Least time from one onset to the next, s (the inter-action interval).
    grid : int
        Side of the grid, cells.
    fixation : bool
        Show a fixation cross at the centre of the grid.
    target : int or None
        A cell shown to the subject as the target; None: none.
    frame_tolerance : float
        A frame interval beside an onset longer than this many refresh periods is a
        dropped frame: the onset is invalid.
    onset_log : Path or None
        A JSON Lines file every onset is appended to.
    photodiode_patch : bool
        Show a square in the bottom-left corner, black, and white for `PATCH_FRAMES`
        frames from each onset's frame: a place for a photodiode
        (``acquisition.photodiode``).
    """

    moves: str = DEFAULT_MOVES
    onsets: str = DEFAULT_ONSETS
    interval: float = 3.0
    grid: int = 5
    fixation: bool = True
    target: int | None = None
    frame_tolerance: float = 1.5
    onset_log: Path | None = None
    photodiode_patch: bool = False

    def __post_init__(self) -> None:
        if not self.interval >= 0:
            raise ValueError(f"--interval must be at least 0 s; got {self.interval}")
        if not 2 <= self.grid <= 64:
            raise ValueError(f"--grid must be in 2..64; got {self.grid}")
        if self.target is not None and not 0 <= self.target < self.grid**2:
            raise ValueError(f"--target must be a cell of the {self.grid}x{self.grid} grid, "
                             f"0..{self.grid**2 - 1}; got {self.target}")
        if not self.frame_tolerance > 1:
            raise ValueError(f"--frame-tolerance must be above 1 refresh period; got "
                             f"{self.frame_tolerance}")

    def for_page(self) -> dict[str, Any]:
        """What the page needs: interval (ms), grid, fixation, target, frame tolerance, and
        with a photodiode patch its frames."""
        return {"interval_ms": self.interval * 1e3, "grid": self.grid,
                "fixation": self.fixation, "target": self.target,
                "frame_tolerance": self.frame_tolerance,
                } | ({"patch_frames": PATCH_FRAMES} if self.photodiode_patch else {})


class _MoveReader(threading.Thread):
    """Reads the bridge's move stream (resolving it by name, again when lost) and hands
    every marker's text to ``deliver`` until ``stop`` is set."""

    def __init__(
        self, name: str, deliver: Callable[[str], None], stop: threading.Event
    ) -> None:
        super().__init__(name="stimulus-moves", daemon=True)
        self.stream, self.deliver, self.stop = name, deliver, stop

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                inlet = resolve_inlet(self.stream, 1.0, keep_running=lambda: not self.stop.is_set())
            except TimeoutError:
                continue
            log.info("reading the move stream %r", self.stream)
            try:
                while not self.stop.is_set():
                    # One sample at a time: a chunk's pull waits its whole timeout for
                    # more samples after the first, and a move would wait with it.
                    value, _ = inlet.pull_sample(timeout=0.05)
                    if value is not None:
                        self.deliver(value[0])
            except LostError:
                log.warning("the move stream %r was lost; resolving it again", self.stream)


class Stimulus:
    """The stimulus program's state, on the event loop: the move to show, the stimulus
    page and its clock, the onset outlet."""

    def __init__(
        self, settings: StimulusSettings, make_page: Callable[[web.WebSocketResponse], Page]
    ) -> None:
        self.settings, self.make_page = settings, make_page
        self.loop: asyncio.AbstractEventLoop | None = None
        self.outlet = marker_outlet(settings.onsets, f"cfbci-stimulus-{settings.onsets}")
        self.page: Page | None = None
        self.waiting: list[Page] = []  # pages refused the role, in order: the next ones
        self.clock = ClockSync()
        self.pings: dict[int, float] = {}  # ping id -> LSL clock when it was sent
        self.ping_id = 0
        self.pinger: asyncio.Future[None] | None = None
        self.move: dict[str, Any] | None = None  # the move to show
        self.show_id = 0  # number of the show the page was last sent
        self.shown = True  # whether the move was validly shown (or there is none)
        self.sent = False  # whether the page has the current show
        self.stop = threading.Event()
        self.reader = _MoveReader(settings.moves, self._from_thread, self.stop)

    async def start(self, _: web.Application) -> None:
        """Start reading the move stream (when the view's application starts)."""
        self.loop = asyncio.get_running_loop()
        self.reader.start()

    async def close(self, _: web.Application) -> None:
        """Stop reading the move stream and pinging (when the application shuts down)."""
        self.stop.set()
        if self.pinger is not None:
            self.pinger.cancel()
        await asyncio.to_thread(self.reader.join, 5.0)

    def _from_thread(self, text: str) -> None:
        assert self.loop is not None
        self.loop.call_soon_threadsafe(self.take_move, text)

    async def socket(self, request: web.Request) -> web.WebSocketResponse:
        """``/stimulus``: a page's stimulus socket, until it closes."""
        socket = web.WebSocketResponse(heartbeat=20.0)
        await socket.prepare(request)
        page = self.make_page(socket)
        writer = asyncio.ensure_future(page.write())
        try:
            async for frame in socket:
                if frame.type == WSMsgType.TEXT:
                    self.receive(page, frame.data)
        finally:
            self.leave(page)
            writer.cancel()
        return socket

    def take_move(self, text: str) -> None:
        """A move marker of the bridge: the move to show now (a newer move, or the same one
        asked for again, replaces the one shown)."""
        cells = self.settings.grid**2
        try:
            move = parse_move_marker(text)
            for state in (move["from_state"], move["to_state"]):
                if not (isinstance(state, int) and 0 <= state < cells):
                    raise ValueError(f"state {state!r} is no cell of the {self.settings.grid}"
                                     f"x{self.settings.grid} grid (is --grid the bridge's?)")
        except ValueError as error:
            log.error("move stream %r: %s; not shown", self.settings.moves, error)
            return
        log.info("move of step %d (repeat %d)", move["step"], move["repeat"])
        self.move, self.shown = move, False
        self._show()

    def _show(self) -> None:
        """Send the current move to the stimulus page as a new show, if there is a page
        whose clock is known."""
        self.sent = False
        if self.move is None or self.shown or self.page is None or not self.clock.ready:
            return
        self.show_id += 1
        self.page.push(json.dumps({"type": "show", "show": self.show_id, "move": self.move}))
        self.sent = True

    def receive(self, page: Page, data: str) -> None:
        """A message of a page's stimulus socket; one that is not JSON with a ``type`` of
        `PAGE_TYPES` is logged and ignored."""
        try:
            message = json.loads(data)
            kind = message["type"]
        except (ValueError, KeyError, TypeError):
            kind = None
        if kind not in PAGE_TYPES:
            log.warning("stimulus socket: bad message %r; ignored", data[:100])
        elif kind == "stimulus":
            self._claim(page)
        elif page is not self.page:
            return  # a page that lost the role (or never had it)
        elif kind == "pong":
            self._pong(message)
        else:
            self._onset(message)

    def _claim(self, page: Page) -> None:
        if self.page is not None and self.page is not page:
            page.push(json.dumps({"type": "stimulus", "refused": "another page is the stimulus"}))
            if page not in self.waiting:
                self.waiting.append(page)
            return
        self.page, self.clock, self.pings = page, ClockSync(), {}
        page.push(json.dumps({"type": "stimulus", "settings": self.settings.for_page()}))
        log.info("a page is the stimulus")
        self.pinger = asyncio.ensure_future(self._ping(page))

    def leave(self, page: Page) -> None:
        """A page disconnected: if it was the stimulus page, the role goes to the page
        refused it first (or to the next one to claim it), which shows the move again."""
        if page in self.waiting:
            self.waiting.remove(page)
        if page is not self.page:
            return
        log.warning("the stimulus page disconnected")
        self.page = None
        if self.pinger is not None:
            self.pinger.cancel()
            self.pinger = None
        if self.waiting:
            self._claim(self.waiting.pop(0))

    async def _ping(self, page: Page) -> None:
        while True:
            self.ping_id += 1
            self.pings[self.ping_id] = pylsl.local_clock()
            page.push(json.dumps({"type": "ping", "id": self.ping_id}))
            await asyncio.sleep(PING_SLOW if self.clock.ready else PING_FAST)

    def _pong(self, message: dict[str, Any]) -> None:
        received = pylsl.local_clock()
        try:
            sent = self.pings.pop(int(message["id"]))
            self.clock.add(sent, float(message["page_ms"]) / 1e3, received)
        except (KeyError, TypeError, ValueError) as error:
            log.warning("bad pong %r: %s", message, error)
            return
        for old in [i for i in self.pings if i < int(message["id"])]:
            del self.pings[old]  # lost answers
        if not self.sent:
            self._show()

    def _onset(self, message: dict[str, Any]) -> None:
        try:
            show, frame_ms = int(message["show"]), float(message["frame_ms"])
            valid, reason = bool(message["valid"]), message.get("reason")
        except (KeyError, TypeError, ValueError) as error:
            log.warning("bad onset report %r: %s", message, error)
            return
        move, estimate = self.move, self.clock.estimate()
        if show != self.show_id or move is None or self.shown or estimate is None:
            log.info("onset report of show %d dropped: not the current show", show)
            return
        onset = frame_ms / 1e3 + estimate.offset
        now = pylsl.local_clock()
        step = move["step"]
        if valid:
            self.outlet.push_sample([f"onset {step}"], onset)
            self.shown = True
        else:
            reason = str(reason or "invalid").replace(" ", "-")
            self.outlet.push_sample([f"invalid-onset {step} {reason}"], onset)
        entry = {
            "step": step, "repeat": move["repeat"], "show": show, "onset": onset,
            "valid": valid, "reason": None if valid else reason,
            "uncertainty_ms": estimate.uncertainty * 1e3, "offset": estimate.offset,
            "report_ms": (now - onset) * 1e3,
            **{key: message.get(key) for key in ("period_ms", "before_ms", "after_ms")},
        }
        log.info("%s of step %d at t=%.4f s (+-%.2f ms)%s",
                 "onset" if valid else "invalid onset", step, onset,
                 entry["uncertainty_ms"], "" if valid else f": {reason}; shown again")
        if self.settings.onset_log is not None:
            with self.settings.onset_log.open("a") as file:
                file.write(json.dumps(entry) + "\n")
        if not valid:
            self._show()

