"""``cfbci view`` is safe by default: every request needs the view's token, and a request
for another host name (DNS rebinding) or from another site is refused; its model drops a
malformed message (naming what and where) and keeps updating the session, and every map it
keeps per session is bounded.

The HTTP tests run the real command (``python -m cfbci.cli view``) in a process of its own,
a real aiohttp server on loopback and a real Zenoh peer, and talk to it with urllib and
aiohttp's WebSocket client. The model tests feed `cfbci.view.model.SessionBook`
messages of every world (grid, line, pick-and-place, continuous, puddle), and
`cfbci.view.server.ViewServer` real wire bytes. The pages in a real Chromium are
tested in ``tests/test_view.py``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import queue
import re
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from email.message import Message as Headers
from typing import IO, Any

import aiohttp
import numpy as np
import pytest

from cfbci.view import TOKEN_ENV
from cfbci.view.checks import MAX_TASKS, PENDING_STEPS
from cfbci.view.model import (
    MAX_SESSIONS,
    SERIES_LENGTH,
    TARGETS_KEPT,
    TEXT_LENGTH,
    SessionBook,
)
from cfbci.view.server import ViewServer
from wire import protocol
from wire.transport import Received
from wire.zenoh_config import free_tcp_endpoint

CLI = [sys.executable, "-m", "cfbci.cli"]
TIMEOUT = 60.0  # failure guard, seconds
ALLOWED_HOST = "view.lab"  # --allow-host of the module's view (any port: its own)
ALLOWED_ORIGIN = "http://proxy.lab:9000"  # --allow-origin of the module's view


@dataclass(frozen=True)
class RunningView:
    """A ``cfbci view`` process: its HTTP port and the token it printed."""

    port: int
    token: str

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.port}"


def _lines(stream: IO[str], into: queue.SimpleQueue[str | None]) -> None:
    for line in stream:
        into.put(line)
    into.put(None)


@contextmanager
def view_command(*args: str, env_token: str | None = None) -> Iterator[RunningView]:
    """``cfbci view --listen <free endpoint> --port 0 *args`` until it prints its addresses;
    stopped with SIGTERM, which must end it cleanly. ``env_token``: the token in the
    environment (else none there)."""
    env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV} | {"PYTHONUNBUFFERED": "1"}
    if env_token is not None:
        env[TOKEN_ENV] = env_token
    process = subprocess.Popen(
        [*CLI, "view", "--listen", free_tcp_endpoint(), "--port", "0", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    try:
        lines: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        threading.Thread(target=_lines, args=(process.stdout, lines), daemon=True).start()
        line = lines.get(timeout=TIMEOUT)
        assert line is not None, f"cfbci view stopped: {process.communicate()[1][-2000:]}"
        found = re.match(r"operator view: http://127\.0\.0\.1:(\d+)/\?token=(\S+)$", line)
        assert found, line
        subject = lines.get(timeout=TIMEOUT)
        assert subject == (
            f"subject view: http://127.0.0.1:{found[1]}/subject?session=ID&token={found[2]}\n"
        )
        yield RunningView(int(found[1]), found[2])
    finally:
        process.terminate()
        try:
            process.wait(TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    assert process.returncode == 0, process.stderr.read() if process.stderr else ""


@pytest.fixture(scope="module")
def view() -> Iterator[RunningView]:
    """The module's view: a random token, one more host name and one more origin allowed."""
    with view_command("--allow-host", ALLOWED_HOST, "--allow-origin", ALLOWED_ORIGIN) as running:
        yield running


@dataclass
class Answer:
    status: int
    text: str
    headers: Headers


def _get(url: str, **headers: str) -> Answer:
    """GET ``url`` with these headers (``Host`` replaces urllib's own); the answer, errors
    included."""
    request = urllib.request.Request(url, headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=TIMEOUT) as response:
            return Answer(response.status, response.read().decode(), response.headers)
    except urllib.error.HTTPError as error:
        return Answer(error.code, error.read().decode(), error.headers)


def _websocket(url: str, origin: str | None = None, **headers: str) -> tuple[int, Any]:
    """Open the view's WebSocket: ``(101, first message)``, or ``(status, None)`` if the
    handshake is refused."""

    async def attempt() -> tuple[int, Any]:
        async with aiohttp.ClientSession() as client:
            try:
                async with client.ws_connect(url, origin=origin, headers=headers) as socket:
                    return 101, await socket.receive_json(timeout=TIMEOUT)
            except aiohttp.WSServerHandshakeError as error:
                return error.status, None

    return asyncio.run(asyncio.wait_for(attempt(), TIMEOUT))


def _follow(view: RunningView, session: str) -> dict[str, Any]:
    """The snapshot of ``session`` a page following it gets first."""

    async def follow() -> dict[str, Any]:
        async with aiohttp.ClientSession() as client:
            async with client.ws_connect(f"{view.base}/ws?token={view.token}") as socket:
                await socket.send_json({"follow": session})
                while True:
                    message = await socket.receive_json(timeout=TIMEOUT)
                    if message["type"] == "snapshot":
                        return message

    return asyncio.run(asyncio.wait_for(follow(), TIMEOUT))


PAGES = ("/", "/subject?session=s", "/static/common.js", "/static/view.css", "/ws")


def test_every_page_and_the_websocket_refuse_a_request_without_the_right_token(
    view: RunningView,
) -> None:
    wrong = view.token[:-1] + ("a" if view.token[-1] != "a" else "b")
    for path in PAGES:
        for query in ("", f"{'&' if '?' in path else '?'}token={wrong}"):
            answer = _get(view.base + path + query)
            assert answer.status == 403, (path, query, answer.status)
            assert "token" in answer.text and view.token not in answer.text, answer.text
            assert "Set-Cookie" not in answer.headers
        answer = _get(view.base + path, Cookie=f"cfbci-view-{view.port}={wrong}")
        assert answer.status == 403, path
    assert _websocket(f"{view.base}/ws")[0] == 403
    assert _websocket(f"{view.base}/ws?token={wrong}")[0] == 403


def test_the_token_opens_every_page_and_a_cookie_keeps_them_open(view: RunningView) -> None:
    answer = _get(f"{view.base}/?token={view.token}")
    assert answer.status == 200 and "operator view" in answer.text
    cookie = answer.headers["Set-Cookie"]
    assert cookie.startswith(f"cfbci-view-{view.port}={view.token};"), cookie
    assert {"HttpOnly", "SameSite=Strict", "Path=/"} <= {
        part.strip() for part in cookie.split(";")
    }, cookie
    assert answer.headers["Referrer-Policy"] == "no-referrer"
    assert answer.headers["X-Frame-Options"] == "DENY"
    with_cookie = {"Cookie": f"cfbci-view-{view.port}={view.token}"}
    for path in PAGES[:-1]:  # a reload, and the files a page loads, carry the cookie
        assert _get(view.base + path, **with_cookie).status == 200, path
    assert _websocket(f"{view.base}/ws?token={view.token}") == (
        101, {"type": "sessions", "sessions": []}
    )
    assert _websocket(f"{view.base}/ws", **with_cookie)[0] == 101


def test_a_websocket_or_page_requested_by_another_site_is_refused(view: RunningView) -> None:
    ws = f"{view.base}/ws?token={view.token}"
    for origin in (f"http://127.0.0.1:{view.port}", f"http://localhost:{view.port}",
                   f"http://[::1]:{view.port}", f"http://{ALLOWED_HOST}:{view.port}",
                   ALLOWED_ORIGIN):
        assert _websocket(ws, origin=origin)[0] == 101, origin
    for origin in ("http://evil.example", f"http://evil.example:{view.port}", "null",
                   f"http://127.0.0.1:{view.port + 1}", f"https://127.0.0.1:{view.port}",
                   "http://proxy.lab:9001"):
        assert _websocket(ws, origin=origin)[0] == 403, origin
    answer = _get(f"{view.base}/?token={view.token}", Origin="http://evil.example")
    assert answer.status == 403 and "'http://evil.example'" in answer.text
    assert "--allow-origin" in answer.text, answer.text


def test_a_request_for_another_host_name_is_refused(view: RunningView) -> None:
    """DNS rebinding: a name of the attacker's that resolves to 127.0.0.1 reaches the view
    with that name in ``Host``, and is refused (even with the token)."""
    page = f"{view.base}/?token={view.token}"
    for host in (f"localhost:{view.port}", f"127.0.0.1:{view.port}", f"[::1]:{view.port}",
                 f"{ALLOWED_HOST}:{view.port}", f"LOCALHOST:{view.port}"):
        assert _get(page, Host=host).status == 200, host
    for host in (f"evil.example:{view.port}", "evil.example", f"127.0.0.1:{view.port + 1}",
                 f"{ALLOWED_HOST}:{view.port + 1}", "127.0.0.1", f"127.0.0.1:{view.port}/x"):
        answer = _get(page, Host=host)
        assert answer.status == 403, host
        assert "--allow-host" in answer.text, answer.text
    assert _websocket(f"{view.base}/ws?token={view.token}",
                      Host=f"evil.example:{view.port}")[0] == 403


def test_the_token_is_random_unless_the_environment_or_an_option_gives_one(
    view: RunningView,
) -> None:
    assert re.fullmatch(r"[A-Za-z0-9_-]{43}", view.token), view.token  # 32 random bytes
    given = "lab-token-0123456789abcdef"
    with view_command("--hide-truth", env_token=given) as running:
        assert running.token == given
        assert _get(f"{running.base}/?token={given}").status == 200
        snapshot = _follow(running, "any")
        assert snapshot["truth_hidden"] is True and snapshot["user_target"] is None
    assert _follow(view, "any")["truth_hidden"] is False
    bad = (("short", "at least 16"), ("with space 0123456789", "only the characters"))
    for token, problem in bad:
        done = subprocess.run(
            [*CLI, "view", "--listen", free_tcp_endpoint(), "--port", "0", "--token", token],
            capture_output=True, text=True, timeout=TIMEOUT,
        )
        assert done.returncode == 2 and "--token" in done.stderr, done.stderr
        assert problem in done.stderr and "Traceback" not in done.stderr, done.stderr


# --- the model: malformed messages of every world, bounds -------------------------------

STEPS = 50
CONFIGS: dict[str, dict[str, Any]] = {
    "grid": {"world": "grid", "grid": 5, "frame": "feedback"},
    "line": {"world": "line", "frame": "feedback"},
    "pick-and-place": {"world": "pick-and-place", "frame": "guidance"},
    "continuous": {"world": "continuous", "frame": "cardinal"},
    "puddle": {"world": "puddle", "frame": "mixed"},
}
#: Per world: the number of states (None: points of the unit square), of tasks (None:
#: truth targets are points), an action of the world and one of another world.
WORLDS: dict[str, tuple[int | None, int | None, str, str]] = {
    "grid": (25, 25, "up", "probe"),
    "line": (5, 2, "no-move", "up"),
    "pick-and-place": (624, 624, "grasp", "north"),
    "continuous": (None, None, "probe", "up"),
    "puddle": (None, 660, "north", "grasp"),
}
SID = "s"


def _wire(kind: str, t_ns: int = 0, payload: Any = None, **fields: Any) -> protocol.Message:
    """A valid message of session ``s``, through the wire encoding and back."""
    message = protocol.Message(kind, SID, 0, t_ns, fields, payload)
    return protocol.decode(protocol.encode(message), key_expr=protocol.key(SID, kind))


def _state_value(world: str, index: int) -> Any:
    return [0.5, 0.1 * index] if WORLDS[world][0] is None else index


def _move(world: str, step: int) -> protocol.Message:
    return _wire("move", step=step, from_state=_state_value(world, 1), action=WORLDS[world][2],
                 to_state=_state_value(world, 2), target_reached=False)


def _state(n_signals: int, n: int = 4) -> protocol.Message:
    return _wire("state", payload=np.full(n, 1 / n, np.float32), best_task=0, confident=False,
                 n_signals=n_signals, class_counts=[1.0, 2.0], balanced_accuracy=0.5,
                 points=[])


def _truth_target(world: str) -> Any:
    return [0.25, 0.75] if WORLDS[world][1] is None else 1


def _opening(world: str) -> list[protocol.Message]:
    """The first messages of session ``s`` of ``world``: its config, a move, a state and a
    truth."""
    config = {"seed": 0, "steps": STEPS, "learner": {}, "dataset": {}, "signal": "features"}
    return [_wire("config", t_ns=1, **config, **CONFIGS[world]), _move(world, 1), _state(1),
            _wire("truth", step=1, target=_truth_target(world), label=0)]


def _started(world: str) -> SessionBook:
    """A book with session ``s`` of ``world`` (`_opening`)."""
    book = SessionBook()
    for message in _opening(world):
        book.update(message, 0)
    return book


def _received(message: protocol.Message) -> Received:
    """A message as the view's Zenoh subscriber hands it over."""
    key = protocol.key(message.session, message.kind)
    return Received(message.kind, key, protocol.encode(message), 0)


def _forged(kind: str, payload: Any = None, drop: str | None = None,
            **fields: Any) -> protocol.Message:
    """A message of session ``s`` as a forger may hand it over: not checked by the encoding."""
    return protocol.Message(kind, SID, 7, 2, {k: v for k, v in fields.items() if k != drop},
                            payload)


def _malformed(world: str) -> list[tuple[protocol.Message, str]]:
    """Malformed messages of a session of ``world``, each with the field its problem names."""
    n_states, n_tasks, action, foreign = WORLDS[world]
    move = _move(world, 2).fields
    state = dict(_state(2).fields)
    truth = {"step": 2, "target": _truth_target(world), "label": 0}
    ones = np.full(4, 0.25, np.float32)
    nan = float("nan")
    cases: list[tuple[protocol.Message, str]] = []
    for step in (0, -1, STEPS + 1, 2**62, 2**70, "3", True, 2.0, nan, None):
        cases += [(_forged("move", **(move | {"step": step})), "'step'"),
                  (_forged("epoch", np.zeros(2, np.float32), step=step, signal="features"),
                   "'step'"),
                  (_forged("truth", **(truth | {"step": step})), "'step'")]
    if n_states is None:  # points of the unit square
        states: list[Any] = [[1.5, 0.5], [-0.1, 0.5], [nan, 0.5], [0.5], [0.5, 0.5, 0.5], 3,
                             [2**62, 0], ["0.5", 0.5], "x", None]
    else:
        states = [n_states, -1, 2**62, 2**70, 1.5, nan, [0.5, 0.5], "3", True, None]
    for value in states:
        cases += [(_forged("move", **(move | {name: value})), f"'{name}'")
                  for name in ("from_state", "to_state")]
    if n_tasks is None:  # the continuous world's goal points
        targets: list[Any] = [[1.5, 0.5], [nan, nan], [0.5], 3, "x", None]
    else:
        targets = [n_tasks, -1, 2**62, 2**70, nan, 0.5, [0.5, 0.5], "1", False, None]
    cases += [(_forged("truth", **(truth | {"target": value})), "'target'") for value in targets]
    cases += [(_forged("move", **(move | {"action": value})), "'action'")
              for value in ("jump", foreign, 3, None)]
    cases += [(_forged("move", **(move | {"target_reached": value})), "'target_reached'")
              for value in ("yes", 1, None)]
    if world in ("continuous", "puddle"):
        cases.append((_forged("move", **(move | {"target_reached": True})), "target"))
    cases += [(_forged("move", drop=name, **move), f"'{name}'") for name in move]
    assert action in protocol.ACTION_NAMES
    payloads = [np.array([0.5, nan, 0.2, 0.3], np.float32), np.array([1.5, 0, 0, 0], np.float32),
                np.array([-0.1, 0.5, 0.3, 0.3], np.float32), np.zeros(0, np.float32),
                np.full((2, 2), 0.25, np.float32), None, [0.25] * 4,
                np.full(MAX_TASKS + 1, 0.5, np.float32)]
    cases += [(_forged("state", payload, **state), "payload") for payload in payloads]
    for name, values in {
        "best_task": [4, -1, 2**62, "0", 0.0, None],
        "confident": ["no", 1, None],
        "n_signals": [-1, 2**70, "2", nan, None],
        "balanced_accuracy": [nan, 1.5, -0.5, "x", float("inf")],
        "class_counts": [[-1.0], [nan], "x", [1, "2"], None],
    }.items():
        cases += [(_forged("state", ones, **(state | {name: value})), f"'{name}'")
                  for value in values]
    cases += [(_forged("event", event=value, message="m", config_t_ns=None), "'event'")
              for value in ("nope", 3, None)]
    cases += [(_forged("event", event="info", message=value, config_t_ns=None), "'message'")
              for value in (5, None, ["m"])]
    config = {"seed": 0, "steps": STEPS, "learner": {}, "dataset": {}, "signal": "features",
              **CONFIGS[world]}
    for name, values in {
        "steps": [-1, "50", 2**70, None],
        "world": ["mars", 3, None],
        "frame": [3, None],
        "learner": ["x", [1], None],
    }.items():
        cases += [(_forged("config", **(config | {name: value})), f"'{name}'")
                  for value in values]
    if world == "grid":
        cases += [(_forged("config", **(config | {"grid": value})), "'grid'")
                  for value in ("5", -5, 2.5, None)]
    return cases


@pytest.mark.parametrize("world", list(CONFIGS))
def test_a_malformed_message_is_dropped_and_the_session_keeps_updating(world: str) -> None:
    book = _started(world)
    shown = json.dumps(book.sessions[SID].snapshot())
    assert book.sessions[SID].snapshot()["user_target"] == _truth_target(world)
    cases = _malformed(world)
    for message, names in cases:
        with pytest.raises(ValueError, match=re.escape(names)):
            book.update(message, 5)
        assert json.dumps(book.sessions[SID].snapshot()) == shown, (message.kind, message.fields)
    assert book.listing() == [{"session": SID, "status": "running", "steps": STEPS}]
    patch, _ = book.update(_move(world, 2), 6)  # the session goes on
    assert patch is not None and patch["set"]["step"] == 2
    assert book.sessions[SID].snapshot()["step"] == 2
    assert len(cases) >= 100  # the cases above, not an empty list


@pytest.mark.parametrize(("world", "target"), [("line", 2), ("line", 7),
                                               ("pick-and-place", 624), ("grid", 25)])
def test_an_out_of_range_truth_leaves_the_targets_updating(world: str, target: int) -> None:
    """The truth of a task the world does not have is dropped (it raised IndexError inside
    the view, which then stopped judging that session's targets)."""
    book = _started(world)
    cell = 4 if world == "line" else 1  # line: task 1 is state 4
    declared = _wire("move", step=2, from_state=cell, action=WORLDS[world][2], to_state=cell,
                     target_reached=True)
    book.update(declared, 0)
    with pytest.raises(ValueError, match=f"'target'.*{target}"):
        book.update(_wire("truth", step=2, target=target, label=0), 0)
    book.update(_wire("truth", step=2, target=1, label=0), 0)
    assert book.sessions[SID].snapshot()["targets"] == [
        {"step": 2, "cell": cell, "status": "correct"}
    ]


def test_a_truth_seen_before_the_config_that_the_world_lacks_is_forgotten() -> None:
    book = SessionBook()
    book.update(_wire("truth", step=3, target=9, label=0), 0)  # no config yet: kept
    config = {"seed": 0, "steps": STEPS, "learner": {}, "dataset": {}, "signal": "features"}
    book.update(_wire("config", t_ns=1, **config, **CONFIGS["line"]), 0)
    book.update(_wire("move", step=3, from_state=4, action="no-move", to_state=4,
                      target_reached=True), 0)
    assert book.sessions[SID].snapshot()["targets"] == [
        {"step": 3, "cell": 4, "status": "pending"}
    ]


def test_the_server_drops_bad_wire_bytes_with_a_warning_and_keeps_the_session(
    caplog: pytest.LogCaptureFixture,
) -> None:
    server = ViewServer()
    for message in _opening("line"):
        server.receive(_received(message))
    key = protocol.key(SID, "truth")
    out_of_range = protocol.encode(protocol.Message("truth", SID, 3, 0,
                                                    {"step": 2, "target": 7, "label": 0}))
    header = json.dumps({"v": protocol.VERSION, "kind": "truth", "session": SID, "seq": 4,
                         "t_ns": 0, "step": 2, "target": 1, "label": -1}).encode()
    negative = len(header).to_bytes(4, "little") + header
    with caplog.at_level(logging.WARNING, logger="cfbci.view"):
        server.receive(Received("truth", key, out_of_range, 0))
        server.receive(Received("truth", key, negative, 0))
    warnings = [r.getMessage() for r in caplog.records]
    assert warnings[0].startswith(f"dropped truth of session {SID!r} seq 3: field 'target'")
    assert "7" in warnings[0] and "line" in warnings[0], warnings[0]
    assert warnings[1].startswith(f"dropped a message: session {SID!r} seq 4: field 'label'")
    server.receive(_received(_move("line", 2)))
    assert server.book.sessions[SID].snapshot()["step"] == 2


def test_forged_epochs_moves_and_truths_leave_the_per_step_maps_bounded() -> None:
    """Epochs, truths and moves of steps that never pair up (a session without a config:
    any step goes) are remembered up to `PENDING_STEPS` each, the newest."""
    book = SessionBook()
    last = 7 * 20 * PENDING_STEPS
    for step in range(7, last + 1, 7):
        book.update(_wire("epoch", payload=np.zeros(2, np.float32), step=step,
                          signal="features"), step)
        book.update(_wire("truth", step=step + 1, target=3, label=0), 0)
        book.update(_wire("move", step=step + 2, from_state=1, action="up", to_state=1,
                          target_reached=False), step)
    view = book.sessions[SID]
    assert len(view.epoch_ns) == len(view.move_ns) == len(view.truths) == PENDING_STEPS
    # The newest are kept: the epoch of the last step pairs with the move after it.
    patch, _ = book.update(_wire("move", step=last + 1, from_state=1, action="up", to_state=1,
                                 target_reached=False), last + 10**6)
    assert patch is not None and patch["append"]["latency"] == [[last, 1.0]]


def test_the_series_targets_and_texts_of_a_session_are_bounded() -> None:
    book = SessionBook()
    for n in range(1, SERIES_LENGTH + 11):
        book.update(_state(n), 0)
    view = book.sessions[SID]
    assert len(view.series) == SERIES_LENGTH and view.series[0][0] == 11
    snapshot = view.snapshot()
    assert snapshot["series_length"] == SERIES_LENGTH and len(snapshot["series"]) == SERIES_LENGTH
    for step in range(1, TARGETS_KEPT + 6):
        book.update(_wire("move", step=step, from_state=2, action="goal", to_state=2,
                          target_reached=True), 0)
        book.update(_wire("truth", step=step, target=2 if step % 2 else 3, label=0), 0)
    snapshot = view.snapshot()
    assert len(snapshot["targets"]) == TARGETS_KEPT and snapshot["targets"][0]["step"] == 6
    assert (snapshot["correct"], snapshot["wrong"]) == ((TARGETS_KEPT + 6) // 2,
                                                        (TARGETS_KEPT + 5) // 2)
    for step in range(1, SERIES_LENGTH + 11):
        book.update(_wire("epoch", payload=np.zeros(2, np.float32), step=step,
                          signal="features"), 0)
        book.update(_wire("move", step=step + 1, from_state=2, action="up", to_state=2,
                          target_reached=False), 1000)
    assert len(view.latency) == SERIES_LENGTH and view.latency[0][0] == 11
    book.update(_wire("event", event="info", message="x" * 10**6, config_t_ns=None), 0)
    assert len(view.events[-1]["message"]) == TEXT_LENGTH


def test_the_number_of_sessions_kept_is_bounded_the_running_ones_first() -> None:
    book = SessionBook()
    for i in range(3):
        book.update(protocol.Message("move", f"run-{i}", 0, 0, _move("grid", 1).fields), 0)
    for i in range(10 * MAX_SESSIONS):
        book.update(protocol.Message("event", f"idle-{i}", 0, 0, {
            "event": "info", "message": "m", "config_t_ns": None}), 0)
    kept = [entry["session"] for entry in book.listing()]
    assert len(kept) == MAX_SESSIONS
    assert kept[:3] == ["run-0", "run-1", "run-2"] and kept[-1] == f"idle-{10 * MAX_SESSIONS - 1}"
