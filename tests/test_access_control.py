"""The deployment of docs/deployment.md, for real: a `cfbci router` process enforcing the
shipped policy (deploy/router.json5) over TLS with a certificate authority made here by
deploy/make-certs.sh, a `cfbci serve` process and `cfbci source` processes, all Zenoh
clients of the router, on loopback, with the shipped client files (deploy/*.json5) and the
example credentials. The two source users, ``lab`` and ``lab-x``, have names that share a
prefix: each owns the key chunk of its name (``cfbci/lab/*/...``, ``cfbci/lab-x/*/...``).

Absence is shown causally, never by waiting a while. After the messages that must be
dropped, the same client sends allowed messages of the same kinds, which travel the same
links in order (Zenoh delivers a link's reliable messages in order, and the router
forwards a link's messages in the order they came), and the check runs once their answers
have arrived: the service files the configs, ready messages and epochs of sessions it does
not run in one queue, in order (``wire/intake.py``), so the dropped message, had it come
through, would have been answered first.
"""

from __future__ import annotations

import itertools
import json
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
import pytest
import zenoh
from system_deps import require

from cfbci.service.router import READY
from replay.recording import read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.operator import send_command
from wire.transport import Outbox, Pump, Received, wait_for_subscribers
from wire.zenoh_config import build_config, merge, read_config_file

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
CLI = [sys.executable, "-m", "cfbci.cli"]
TIMEOUT = 60.0  # failure guard, seconds
STEPS = 30
FORGED_CELL = 777  # from_state of the forged moves, target of the forged truth: no cell of 5 x 5
#: The client file of each user (deploy/).
CLIENT_FILES = {"service": "service", "lab": "source", "lab-x": "source-lab-x",
                "monitor": "monitor", "operator": "operator"}
#: What the monitor may receive.
WATCHED = ("move", "state", "event", "truth")


@pytest.fixture(autouse=True)
def _openssl() -> None:
    """The certificates are made with openssl (Debian's package of that name)."""
    require("openssl", "openssl")


@dataclass
class Deployment:
    """The shipped deploy/ files in a scratch directory, with certificates made for it."""

    root: Path
    endpoint: str  # the router's, tls/127.0.0.1:<port>

    def client_config(self, user: str, **changes: Any) -> zenoh.Config:
        """The shipped client file of ``user`` with ``changes`` merged over it, and the
        router's endpoint."""
        document = read_config_file(self.root / f"{CLIENT_FILES[user]}.json5")
        document = merge(merge(document, changes), {"connect": {"endpoints": [self.endpoint]}})
        return build_config(document)

    def source_args(self, user: str, session: str, *more: str) -> list[str]:
        """``cfbci source`` of ``user`` with its client file, for ``session``."""
        return ["source", "--zenoh-config", f"{CLIENT_FILES[user]}.json5", "--connect",
                self.endpoint, "--session", session, *more]


def make_certs(directory: Path, *names: str) -> None:
    require("openssl", "openssl")  # for the other modules' tests that use the deployment
    subprocess.run(
        ["sh", str(DEPLOY / "make-certs.sh"), str(directory), *names], check=True,
        capture_output=True, timeout=TIMEOUT,
    )


@pytest.fixture
def deployment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Deployment:
    """The deployment's files in ``tmp_path``, which is also the working directory (the
    configurations' paths are relative to it)."""
    monkeypatch.chdir(tmp_path)
    for name in ("router", *CLIENT_FILES.values()):
        shutil.copy(DEPLOY / f"{name}.json5", tmp_path / f"{name}.json5")
    shutil.copy(DEPLOY / "credentials.example.txt", tmp_path / "credentials.txt")
    make_certs(tmp_path / "certs", "127.0.0.1", "localhost")
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    return Deployment(tmp_path, f"tls/127.0.0.1:{port}")


def _lines(stream: IO[str], into: queue.SimpleQueue[str]) -> None:
    for line in stream:
        into.put(line)


@contextmanager
def cli_process(
    deployment: Deployment, name: str, *args: str, stop: signal.Signals = signal.SIGTERM
) -> Iterator[subprocess.Popen[str]]:
    """``cfbci *args`` in the deployment's directory; stopped with ``stop``, which must end
    it cleanly (exit 0). Its standard error goes to ``<name>.log`` there."""
    log = (deployment.root / f"{name}.log").open("w")
    process = subprocess.Popen(
        [*CLI, *args], cwd=deployment.root, stdout=subprocess.PIPE, stderr=log, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        yield process
    finally:
        if process.poll() is None:
            process.send_signal(stop)
        try:
            process.wait(TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        log.close()
    assert process.returncode == 0, (deployment.root / f"{name}.log").read_text()[-3000:]


def cfbci(deployment: Deployment, *args: str) -> subprocess.CompletedProcess[str]:
    """``cfbci *args`` in the deployment's directory, to its end."""
    return subprocess.run(
        [*CLI, *args], cwd=deployment.root, capture_output=True, text=True,
        timeout=TIMEOUT * 3, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


@contextmanager
def router(deployment: Deployment, config: str = "router.json5",
           stop: signal.Signals = signal.SIGTERM) -> Iterator[None]:
    """``cfbci router`` on the deployment's endpoint, once it says it listens."""
    with cli_process(
        deployment, "router", "router", "--zenoh-config", config, "--listen",
        deployment.endpoint, stop=stop,
    ) as process:
        lines: queue.SimpleQueue[str] = queue.SimpleQueue()
        threading.Thread(target=_lines, args=(process.stdout, lines), daemon=True).start()
        line = lines.get(timeout=TIMEOUT)
        assert line.split() == [*READY.split(), deployment.endpoint]
        yield


@contextmanager
def service(deployment: Deployment, *limits: str) -> Iterator[Path]:
    """``cfbci serve`` with deploy/service.json5 and ``limits`` (flags), recording to the
    directory it yields."""
    records = deployment.root / "records"
    with cli_process(deployment, "service", "serve", "--zenoh-config", "service.json5",
                     "--connect", deployment.endpoint, "--record-dir", str(records), *limits):
        yield records


def _decoded(inbox: queue.SimpleQueue[Received]) -> protocol.Message:
    received = inbox.get(timeout=TIMEOUT)
    return protocol.decode(received.data, key_expr=received.key_expr)


class Monitor:
    """What the ``monitor`` user (deploy/monitor.json5) receives: the moves, states,
    events and truth of every session (``cfbci/**/<kind>``)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        self.pumps = [Pump(session, f"{protocol.PREFIX}/**/{kind}", kind, self.inbox)
                      for kind in WATCHED]
        self.seen: list[protocol.Message] = []

    def wait_for(self, wanted: Callable[[protocol.Message], bool]) -> protocol.Message:
        """The first message ``wanted`` received so far, or the next one to arrive
        (everything received is kept in ``seen``)."""
        for message in self.seen:
            if wanted(message):
                return message
        while True:
            message = _decoded(self.inbox)
            self.seen.append(message)
            if wanted(message):
                return message

    def of(self, session: str, kind: str) -> list[protocol.Message]:
        """The messages of ``kind`` of ``session`` received so far."""
        return [m for m in self.seen if m.kind == kind and m.session == session]

    def events(self, session: str) -> list[str]:
        return [m.fields["event"] for m in self.of(session, "event")]

    def close(self) -> None:
        for pump in self.pumps:
            pump.close()


def _event(session: str, event: str) -> Callable[[protocol.Message], bool]:
    return lambda m: m.kind == "event" and m.session == session and m.fields["event"] == event


def _config(seed: int, grid: int, steps: int) -> dict[str, Any]:
    return {"seed": seed, "world": "grid", "grid": grid, "frame": "feedback", "steps": steps,
            "learner": {}, "dataset": {}, "signal": "features"}


def _epoch(step: int) -> dict[str, Any]:
    return {"step": step, "signal": "features"}


FEATURES = np.ones(4)
FORGED_TRUTH = {"step": 1, "target": FORGED_CELL, "label": 0}


def _matched(outbox: Outbox, session: str, kind: str) -> None:
    """Wait until the router lets this client see a subscriber of ``cfbci/<session>/<kind>``
    (so what it publishes there really leaves it)."""
    assert wait_for_subscribers(outbox.publisher(protocol.key(session, kind)), TIMEOUT)


_probes = itertools.count()


def answered_in_turn(outbox: Outbox, monitor: Monitor, user: str) -> None:
    """Send, in ``user``'s own key space, one config, ready, epoch and truth of sessions
    that do not run, and wait until each is answered: the config with a
    ``session_pending`` event, the ready message and the epoch with ``error`` events, the
    truth by its arrival at the monitor. Every config, ready message and epoch that this
    client sent before, and that the router let through, was answered before them."""
    sessions = [f"{user}/probe-{next(_probes)}" for _ in range(4)]
    sends = [
        ("config", _config(1, 3, 5), None, _event(sessions[0], "session_pending")),
        ("ready", {"config_t_ns": 0, "challenge": "none"}, None, _event(sessions[1], "error")),
        ("epoch", _epoch(1), FEATURES, _event(sessions[2], "error")),
        ("truth", {"step": 1, "target": 0, "label": 0}, None,
         lambda m, s=sessions[3]: m.kind == "truth" and m.session == s),
    ]
    for sid, (kind, fields, payload, answer) in zip(sessions, sends, strict=True):
        _matched(outbox, sid, kind)
        outbox.send(kind, sid, fields, payload)
        monitor.wait_for(answer)


class Source:
    """A source started by hand, as wire/client.py does it (docs/protocol.md, "Starting a
    session"): its config, then a ``ready`` message repeating the ``session_pending``
    event's challenge; it answers moves only when told to (`answer`)."""

    def __init__(self, session: zenoh.Session, sid: str) -> None:
        self.sid, self.outbox = sid, Outbox(session)
        self.inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        self.pumps = [Pump(session, protocol.key(sid, kind), kind, self.inbox)
                      for kind in ("move", "event")]
        self.moves: list[protocol.Message] = []

    def start(self, fields: dict[str, Any]) -> protocol.Message:
        """Send the config and answer the challenge; the event that answers the config
        (``session_started`` or ``session_rejected``); the first move once started."""
        _matched(self.outbox, self.sid, "config")
        config = self.outbox.send("config", self.sid, fields)
        while True:
            message = self.next("event")
            if message.fields["config_t_ns"] != config.t_ns:
                continue
            if message.fields["event"] == "session_pending":
                ready = {"config_t_ns": config.t_ns, "challenge": message.fields["challenge"]}
                self.outbox.send("ready", self.sid, ready)
            elif message.fields["event"] in ("session_started", "session_rejected"):
                if message.fields["event"] == "session_started":
                    self.next("move")
                return message

    def next(self, kind: str) -> protocol.Message:
        """The next message of ``kind`` received (moves are kept in `moves`)."""
        while True:
            message = _decoded(self.inbox)
            if message.kind == "move":
                self.moves.append(message)
            if message.kind == kind:
                return message

    def close(self) -> None:
        for pump in self.pumps:
            pump.close()
        self.outbox.close()


def test_clients_without_valid_credentials_are_refused(deployment: Deployment) -> None:
    no_auth = {"transport": {"auth": {"usrpwd": {"user": None, "password": None}}}}
    wrong = {"transport": {"auth": {"usrpwd": {"user": "lab", "password": "guess"}}}}
    with router(deployment):
        with zenoh.open(deployment.client_config("lab")) as accepted:
            assert str(accepted.info.zid())
        for refused in (no_auth, wrong):
            with pytest.raises(zenoh.ZError):
                zenoh.open(deployment.client_config("lab", **refused)).close()


def test_users_whose_names_share_a_prefix_reach_only_their_own_sessions(
    deployment: Deployment,
) -> None:
    """``lab`` and ``lab-x`` each run a session, while each tries to start, run, answer
    and feed a session in the other's key space (``<other>/hijack``, ``<other>/run1``):
    nothing of it reaches the service or the monitor; the monitor receives both users'
    moves, states, events and truth."""
    users = ("lab", "lab-x")
    with (
        router(deployment),
        service(deployment) as records,
        zenoh.open(deployment.client_config("monitor")) as watcher,
        cli_process(deployment, "source-lab",
                    *deployment.source_args("lab", "lab/run1", "--steps", str(STEPS))) as lab,
        cli_process(deployment, "source-lab-x", *deployment.source_args(
            "lab-x", "lab-x/run1", "--steps", str(STEPS), "--seed", "1")) as lab_x,
    ):
        monitor = Monitor(watcher)
        for user in users:
            monitor.wait_for(lambda m, u=user: m.kind == "move" and m.session == f"{u}/run1")
        clients = {user: zenoh.open(deployment.client_config(user)) for user in users}
        try:
            outboxes = {user: Outbox(clients[user]) for user in users}
            for user, other in (users, users[::-1]):
                attacker = outboxes[user]
                hijack, running = f"{other}/hijack", f"{other}/run1"
                for sid in (hijack, running):
                    for kind in ("config", "ready", "epoch", "truth"):
                        _matched(attacker, sid, kind)  # it sees the service's subscribers
                attacker.send("config", hijack, _config(999, 3, 5))
                for sid in (hijack, running):
                    attacker.send("ready", sid, {"config_t_ns": 0, "challenge": "guess"})
                    attacker.send("epoch", sid, _epoch(STEPS + 5), FEATURES)
                    attacker.send("truth", sid, FORGED_TRUTH)
                answered_in_turn(attacker, monitor, user)
            for process in (lab, lab_x):
                output, _ = process.communicate(timeout=TIMEOUT * 3)
                assert process.returncode == 0
                assert f"{STEPS} steps" in output
            for user in users:  # the sessions' queues are emptied into the common one
                monitor.wait_for(_event(f"{user}/run1", "session_ended"))
            for user in users:
                answered_in_turn(outboxes[user], monitor, user)
            # Re-published as a source does, under the default id, in the user's space.
            published = cfbci(deployment, "replay", str(records / "lab" / "run1.mcap"),
                              "--publish", "--speed", "0", "--zenoh-config", "source.json5",
                              "--connect", deployment.endpoint)
            assert published.returncode == 0, published.stderr
            assert "published session 'lab/run1-replay'" in published.stdout
            assert f"moves equal the recorded moves: yes ({STEPS} moves)" in published.stdout
        finally:
            for client in clients.values():
                client.close()
        monitor.close()

    for user, other in (users, users[::-1]):
        assert monitor.events(f"{other}/hijack") == []  # neither started nor answered
        run = f"{user}/run1"  # the moves, states and truth of every step; no error
        assert {m.fields["step"] for m in monitor.of(run, "move")} == set(range(1, STEPS + 1))
        assert {m.fields["n_signals"] for m in monitor.of(run, "state")} == set(
            range(STEPS + 1))
        assert {m.fields["step"] for m in monitor.of(run, "truth")} == set(range(1, STEPS + 1))
        assert "session_ended" in monitor.events(run)
        assert not {"error", "session_rejected"} & set(monitor.events(run))
    assert all(m.fields["target"] != FORGED_CELL for m in monitor.seen if m.kind == "truth")
    recorded = sorted(str(p.relative_to(records)) for p in records.rglob("*.mcap"))
    assert recorded == ["lab-x/run1.mcap", "lab/run1-replay.mcap", "lab/run1.mcap"]
    for user, seed in zip(users, (0, 1), strict=True):
        path = records / user / "run1.mcap"
        recording = read_recording(path)
        assert recording.session == f"{user}/run1"
        assert (recording.config["seed"], recording.config["grid"]) == (seed, 5)  # not 999, 3
        result = replay_check(path)
        assert result.divergence is None
        assert result.moves == STEPS


def test_only_the_service_moves_and_the_monitor_only_watches(deployment: Deployment) -> None:
    """The monitor publishes a config and the epoch a session waits for; a ``lab`` client
    that sees the session's move subscriber forges moves of ``lab``'s own session: the
    router drops them all."""
    held = "lab/held"
    with (
        router(deployment),
        service(deployment) as records,
        zenoh.open(deployment.client_config("monitor")) as watcher,
        zenoh.open(deployment.client_config("lab")) as source_session,
        zenoh.open(deployment.client_config("lab")) as forger_session,
    ):
        monitor = Monitor(watcher)
        source = Source(source_session, held)
        assert source.start(_config(0, 5, 3)).fields["event"] == "session_started"
        forger = Outbox(forger_session)

        # The monitor: a config of a new session, and the epoch of step 1 of the held one.
        intruder = Outbox(watcher)
        intruder.send("config", "lab/from-monitor", _config(999, 3, 5))
        intruder.send("epoch", held, _epoch(1), np.full(4, 7.0))
        # After them on the monitor's link, a subscription, which the router passes on to
        # the lab clients: once the forger sees it, what it sends comes after the
        # monitor's messages (had the router let them through) on the service's link.
        spy = Pump(watcher, protocol.key("lab/from-monitor", "event"), "event",
                   queue.SimpleQueue())
        assert wait_for_subscribers(
            forger.publisher(protocol.key("lab/from-monitor", "event")), TIMEOUT)
        answered_in_turn(forger, monitor, "lab")

        _matched(forger, held, "move")  # it sees the source's move subscriber
        for step in (2, 3):
            forger.send("move", held, {
                "step": step, "from_state": FORGED_CELL, "action": "up",
                "to_state": FORGED_CELL, "target_reached": False,
            })
        # After the forged moves on the same link: the epoch of step 1, which the service
        # answers with the move of step 2.
        _matched(forger, held, "epoch")
        epoch = forger.send("epoch", held, _epoch(1), FEATURES)
        assert source.next("move").fields["step"] == 2
        monitor.wait_for(lambda m: m.kind == "move" and m.session == held
                         and m.fields["step"] == 2)
        spy.close()
        intruder.close()
        forger.close()
        source.close()
        monitor.close()

    moves = monitor.of(held, "move")
    assert [m.fields["step"] for m in moves] == [1, 2]
    assert [m.fields["step"] for m in source.moves] == [1, 2]
    assert all(m.fields["from_state"] != FORGED_CELL for m in moves + source.moves)
    assert monitor.events("lab/from-monitor") == []
    recording = read_recording(records / "lab" / "held.mcap")
    assert (recording.config["seed"], recording.config["grid"]) == (0, 5)
    # The epoch of step 1 taken is the forger's (the monitor's came first, had it come).
    assert [m["t_ns"] for _, m in recording.messages["/features"]] == [epoch.t_ns]
    assert sorted(p.name for p in records.rglob("*.mcap")) == ["held.mcap"]


def test_only_the_sessions_user_and_the_operator_send_its_commands(
    deployment: Deployment,
) -> None:
    """Operator commands (``control``) on sessions that do not run, which the service
    answers with an ``error`` event: ``lab-x``'s on ``lab``'s key chunk and the monitor's
    are dropped by the router (each followed on its link by an allowed message that is
    answered); ``lab``'s on its own chunk and the operator's on any are answered."""
    pause = {"command": "pause"}
    with (
        router(deployment),
        service(deployment),
        zenoh.open(deployment.client_config("monitor")) as watcher,
        zenoh.open(deployment.client_config("lab-x")) as other_session,
        zenoh.open(deployment.client_config("lab")) as own_session,
        zenoh.open(deployment.client_config("operator")) as operator_session,
    ):
        monitor = Monitor(watcher)
        other, own = Outbox(other_session), Outbox(own_session)
        _matched(other, "lab-x/ghost", "control")  # it sees the service's subscriber
        other.send("control", "lab/from-lab-x", pause)  # not its chunk: dropped
        other.send("control", "lab-x/ghost", pause)  # its own: answered, after it
        monitor.wait_for(_event("lab-x/ghost", "error"))
        intruder = Outbox(watcher)
        intruder.send("control", "lab/from-monitor", pause)
        # After it on the monitor's link, a subscription that the lab client sees: what
        # it sends then comes after the monitor's command on the service's link.
        spy = Pump(watcher, protocol.key("lab/from-monitor", "event"), "event",
                   queue.SimpleQueue())
        assert wait_for_subscribers(
            own.publisher(protocol.key("lab/from-monitor", "event")), TIMEOUT)
        _matched(own, "lab/own-ghost", "control")
        own.send("control", "lab/own-ghost", pause)
        answer = monitor.wait_for(_event("lab/own-ghost", "error"))
        assert "control 'pause' for a session that is not running" in answer.fields["message"]
        with pytest.raises(ValueError, match="not running"):  # the operator's, answered
            send_command(operator_session, "lab/op-ghost", "pause", timeout=TIMEOUT)
        spy.close()
        intruder.close()
        other.close()
        own.close()
        monitor.close()
    assert monitor.events("lab/from-lab-x") == monitor.events("lab/from-monitor") == []


def test_a_users_quota_leaves_the_other_users_sessions(deployment: Deployment) -> None:
    """With ``--user-sessions 1 --user-pending 1``: while ``lab`` runs a session, its
    second is rejected (``cfbci source`` says why, exit 1), and ``lab-x`` runs one; a user
    with a session waiting for its source has its next config rejected."""
    with (
        router(deployment),
        service(deployment, "--user-sessions", "1", "--user-pending", "1") as records,
        zenoh.open(deployment.client_config("monitor")) as watcher,
        zenoh.open(deployment.client_config("lab")) as lab_session,
        zenoh.open(deployment.client_config("lab-x")) as lab_x_session,
    ):
        monitor = Monitor(watcher)
        held = Source(lab_session, "lab/held")
        assert held.start(_config(0, 5, 10)).fields["event"] == "session_started"

        second = cfbci(deployment, *deployment.source_args("lab", "lab/second", "--steps", "5"))
        assert second.returncode == 1
        said = " ".join(second.stderr.split())
        assert "rejected session 'lab/second'" in said
        assert "user 'lab' runs its maximum of 1 sessions" in said

        other = cfbci(deployment, *deployment.source_args("lab-x", "lab-x/first", "--steps",
                                                          "5"))
        assert other.returncode == 0, other.stderr
        assert "'lab-x/first': 5 steps" in other.stdout

        waiting = Outbox(lab_x_session)  # lab-x: one config left unanswered, then another
        for sid in ("lab-x/waits", "lab-x/next"):
            _matched(waiting, sid, "config")
            waiting.send("config", sid, _config(0, 3, 5))
        monitor.wait_for(_event("lab-x/waits", "session_pending"))
        rejected = monitor.wait_for(_event("lab-x/next", "session_rejected"))
        assert "user 'lab-x' has its maximum of 1 sessions waiting" in rejected.fields["message"]
        waiting.close()
        held.close()
        monitor.close()

    assert set(monitor.events("lab/second")) == {"session_rejected"}
    recorded = sorted(str(p.relative_to(records)) for p in records.rglob("*.mcap"))
    assert recorded == ["lab-x/first.mcap", "lab/held.mcap"]


def test_tls_client_certificates_from_another_authority_are_refused(
    deployment: Deployment,
) -> None:
    make_certs(deployment.root / "certs", "127.0.0.1", "--client", "lab")
    make_certs(deployment.root / "other", "127.0.0.1", "--client", "lab")
    mutual = {"transport": {"link": {"tls": {"enable_mtls": True}}}}
    shipped = read_config_file(deployment.root / "router.json5")
    (deployment.root / "router-mtls.json5").write_text(json.dumps(merge(shipped, mutual)))

    def client(directory: str | None, ca: str = "certs") -> zenoh.Config:
        tls: dict[str, Any] = {"root_ca_certificate": f"{ca}/ca.pem", "enable_mtls": True}
        if directory is not None:
            tls |= {"connect_certificate": f"{directory}/lab.pem",
                    "connect_private_key": f"{directory}/lab-key.pem"}
        return deployment.client_config("lab", transport={"link": {"tls": tls}})

    with router(deployment, "router-mtls.json5", stop=signal.SIGINT):
        with zenoh.open(client("certs")) as accepted:  # a certificate of the CA
            assert str(accepted.info.zid())
        # A certificate of another CA, none, or a client that does not trust the router's.
        for refused in (client("other"), client(None), client("certs", ca="other")):
            with pytest.raises(zenoh.ZError):
                zenoh.open(refused).close()


def test_an_lsl_session_runs_behind_the_router_as_its_users(
    deployment: Deployment, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``cfbci lsl-bridge --zenoh-config source.json5``: the bridge logs in as ``lab`` and
    its session, ``lab/lsl1``, runs to its end through the router, recorded in ``lab``'s
    folder with every epoch the simulator (also logged in as ``lab``, for its truth)
    wrote."""
    pytest.importorskip("pylsl")
    from acquisition.lsl_streams import loopback_config

    (deployment.root / "lsl_api.cfg").write_text(loopback_config(f"cfbci-test-{os.getpid()}"))
    monkeypatch.setenv("LSLAPICFG", str(deployment.root / "lsl_api.cfg"))
    streams = [f"--{kind}" if i % 2 == 0 else f"{kind}-{os.getpid()}"
               for kind in ("eeg", "markers", "moves") for i in range(2)]
    session, steps = "lab/lsl1", 8
    with router(deployment), service(deployment) as records:
        with cli_process(deployment, "simulator", "lsl-simulator", "--session", session,
                         "--seed", "3", "--zenoh-config", "source.json5", "--connect",
                         deployment.endpoint, "--timeout", "60", "--written", "written.npz",
                         *streams) as simulator:
            bridged = cfbci(deployment, "lsl-bridge", "--session", session, "--seed", "3",
                            "--steps", str(steps), "--timeout", "60", "--zenoh-config",
                            "source.json5", "--connect", deployment.endpoint, *streams)
            assert bridged.returncode == 0, bridged.stderr
            assert f"{steps} epochs published" in bridged.stdout
            simulator.wait(TIMEOUT)  # it ends with the bridge's move stream
    path = records / "lab" / "lsl1.mcap"
    recording = read_recording(path)
    assert recording.session == session
    assert [m["step"] for _, m in recording.messages["/truth"]] == list(range(1, steps + 1))
    checked = cfbci(deployment, "lsl-check", "written.npz", str(path))
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert f"{steps} of {steps} recorded epochs equal" in checked.stdout
