"""The deployment of docs/deployment.md, for real: a `cfbci router` process enforcing the
shipped policy (deploy/router.json5) over TLS with a certificate authority made here by
deploy/make-certs.sh, a `cfbci serve` process and a `cfbci source` process, all Zenoh
clients of the router, on loopback.

Absence is shown causally, never by waiting a while: after the messages that must be
dropped, the same client sends one that is allowed to the same receiver over the same
link (Zenoh delivers a link's reliable messages in order), and the check runs once that
one has arrived.
"""

from __future__ import annotations

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

from cfbci.router import READY
from replay.recording import read_recording
from replay.rerun import replay_check
from wire import protocol
from wire.transport import Outbox, Pump, Received, wait_for_subscribers
from wire.zenoh_config import build_config, merge, read_config_file

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
CLI = [sys.executable, "-m", "cfbci.cli"]
TIMEOUT = 60.0  # failure guard, seconds
STEPS = 30
FORGED_CELL = 777  # from_state of the forged moves: no cell of a 5 x 5 grid



@pytest.fixture(autouse=True)
def _openssl() -> None:
    """The certificates are made with openssl (Debian's package of that name)."""
    require("openssl", "openssl")


@dataclass
class Deployment:
    """The shipped deploy/ files in a scratch directory, with certificates made for it."""

    root: Path
    endpoint: str  # the router's, tls/127.0.0.1:<port>

    def client_config(self, name: str, **changes: Any) -> zenoh.Config:
        """A client configuration: deploy/<name>.json5 with ``changes`` merged over it, and
        the router's endpoint."""
        document = merge(read_config_file(self.root / f"{name}.json5"), changes)
        document = merge(document, {"connect": {"endpoints": [self.endpoint]}})
        return build_config(document)

    def as_user(self, user: str, **changes: Any) -> zenoh.Config:
        """A client logged in as ``user`` (its password from credentials.txt)."""
        password = self.password(user)
        auth = {"transport": {"auth": {"usrpwd": {"user": user, "password": password}}}}
        return self.client_config("source", **merge(auth, changes))

    def password(self, user: str) -> str:
        for line in (self.root / "credentials.txt").read_text().splitlines():
            name, _, password = line.partition(":")
            if name == user:
                return password
        raise KeyError(user)


def make_certs(directory: Path, *names: str) -> None:
    subprocess.run(
        ["sh", str(DEPLOY / "make-certs.sh"), str(directory), *names], check=True,
        capture_output=True, timeout=TIMEOUT,
    )


@pytest.fixture
def deployment(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Deployment:
    """The deployment's files in ``tmp_path``, which is also the working directory (the
    configurations' paths are relative to it)."""
    monkeypatch.chdir(tmp_path)
    for name in ("router.json5", "service.json5", "source.json5"):
        shutil.copy(DEPLOY / name, tmp_path / name)
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


def _decoded(inbox: queue.SimpleQueue[Received]) -> protocol.Message:
    received = inbox.get(timeout=TIMEOUT)
    return protocol.decode(received.data, key_expr=received.key_expr)


class Monitor:
    """What the ``monitor`` user receives: every event, truth, and one session's moves."""

    def __init__(self, session: zenoh.Session, watched: str) -> None:
        self.inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
        self.pumps = [
            Pump(session, "cfbci/*/event", "event", self.inbox),
            Pump(session, "cfbci/*/truth", "truth", self.inbox),
            Pump(session, protocol.key(watched, "move"), "move", self.inbox),
        ]
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

    def events(self, session: str) -> list[str]:
        return [m.fields["event"] for m in self.seen if m.kind == "event" and m.session == session]

    def close(self) -> None:
        for pump in self.pumps:
            pump.close()


def _event(session: str, event: str) -> Callable[[protocol.Message], bool]:
    return lambda m: m.kind == "event" and m.session == session and m.fields["event"] == event


def _config(seed: int, grid: int, steps: int) -> dict[str, Any]:
    return {"seed": seed, "world": "grid", "grid": grid, "frame": "feedback", "steps": steps,
            "learner": {},
            "dataset": {}, "signal": "features"}


def _matched(outbox: Outbox, session: str, kind: str) -> None:
    """Wait until the router lets this client see a subscriber of ``cfbci/<session>/<kind>``
    (so what it publishes there really leaves it)."""
    assert wait_for_subscribers(outbox.publisher(protocol.key(session, kind)), TIMEOUT)


def test_only_authenticated_sources_start_sessions_and_only_the_service_moves(
    deployment: Deployment,
) -> None:
    records = deployment.root / "records"
    with (
        router(deployment),
        cli_process(deployment, "service", "serve", "--zenoh-config", "service.json5",
                    "--connect", deployment.endpoint, "--record-dir", str(records)),
        zenoh.open(deployment.as_user("monitor")) as watcher,
    ):
        monitor = Monitor(watcher, "lab1-demo")

        # No credentials, or a wrong password: the router refuses the Zenoh session itself.
        no_auth = {"transport": {"auth": {"usrpwd": {"user": None, "password": None}}}}
        for refused in (
            deployment.client_config("source", **no_auth),
            deployment.client_config(
                "source", transport={"auth": {"usrpwd": {"user": "lab1", "password": "guess"}}}
            ),
        ):
            with pytest.raises(zenoh.ZError):
                zenoh.open(refused).close()

        # Another source user (lab2) runs its own sessions, but cannot start lab1's or
        # inject epochs into them.
        with zenoh.open(deployment.as_user("lab2")) as lab2_session:
            lab2 = Outbox(lab2_session)
            _matched(lab2, "lab2-probe", "config")  # the service is up and reachable
            lab2.send("config", "lab2-probe", _config(1, 3, 5))
            monitor.wait_for(_event("lab2-probe", "session_started"))
            _matched(lab2, "lab1-demo", "config")
            _matched(lab2, "lab1-demo", "epoch")
            lab2.send("config", "lab1-demo", _config(999, 3, 5))
            features = {"step": 1, "signal": "features"}
            lab2.send("epoch", "lab1-demo", features, np.ones(4))
            # Causal sentinel: an epoch of lab2's own session, sent after the attempts on
            # the same link, answered with an error (no move 6 was sent).
            lab2.send("epoch", "lab2-probe", {**features, "step": 6}, np.ones(4))
            monitor.wait_for(_event("lab2-probe", "error"))
            lab2.close()
        assert monitor.events("lab1-demo") == []  # the service saw nothing of lab2's

        # The real source (user lab1) runs lab1-demo; meanwhile another lab1 client forges
        # moves of that session.
        with cli_process(
            deployment, "source", "source", "--zenoh-config", "source.json5", "--connect",
            deployment.endpoint, "--session", "lab1-demo", "--steps", str(STEPS),
        ) as source, zenoh.open(deployment.as_user("lab1")) as forger_session:
            monitor.wait_for(lambda m: m.kind == "move" and m.session == "lab1-demo")
            forger = Outbox(forger_session)
            _matched(forger, "lab1-demo", "move")  # it sees the source's move subscriber
            for step in (2, 3, 4):
                forger.send("move", "lab1-demo", {
                    "step": step, "from_state": FORGED_CELL, "action": "up",
                    "to_state": FORGED_CELL, "target_reached": False,
                })
            _matched(forger, "lab1-sentinel", "truth")
            forger.send("truth", "lab1-sentinel", {"step": 1, "target": 0, "label": 0})
            monitor.wait_for(lambda m: m.kind == "truth" and m.session == "lab1-sentinel")
            forger.close()
            output, _ = source.communicate(timeout=TIMEOUT * 5)
        assert source.returncode == 0
        assert f"'lab1-demo': {STEPS} steps" in output
        monitor.wait_for(lambda m: m.kind == "move" and m.fields["step"] == STEPS)
        monitor.close()

    moves = [m for m in monitor.seen if m.kind == "move"]
    assert [m.fields["step"] for m in moves] == list(range(1, STEPS + 1))
    assert all(m.fields["from_state"] != FORGED_CELL for m in moves)
    assert monitor.events("lab1-demo").count("session_started") == 1
    assert "error" not in monitor.events("lab1-demo")
    assert sorted(p.name for p in records.glob("*.mcap")) == ["lab1-demo.mcap", "lab2-probe.mcap"]
    recording = read_recording(records / "lab1-demo.mcap")
    assert (recording.config["seed"], recording.config["grid"]) == (0, 5)  # not lab2's 999, 3
    result = replay_check(records / "lab1-demo.mcap")
    assert result.divergence is None
    assert result.moves == STEPS


def test_tls_client_certificates_from_another_authority_are_refused(
    deployment: Deployment,
) -> None:
    make_certs(deployment.root / "certs", "127.0.0.1", "--client", "lab1")
    make_certs(deployment.root / "other", "127.0.0.1", "--client", "lab1")
    mutual = {"transport": {"link": {"tls": {"enable_mtls": True}}}}
    shipped = read_config_file(deployment.root / "router.json5")
    (deployment.root / "router-mtls.json5").write_text(json.dumps(merge(shipped, mutual)))

    def client(directory: str | None, ca: str = "certs") -> zenoh.Config:
        tls: dict[str, Any] = {"root_ca_certificate": f"{ca}/ca.pem", "enable_mtls": True}
        if directory is not None:
            tls |= {"connect_certificate": f"{directory}/lab1.pem",
                    "connect_private_key": f"{directory}/lab1-key.pem"}
        return deployment.as_user("lab1", transport={"link": {"tls": tls}})

    with router(deployment, "router-mtls.json5", stop=signal.SIGINT):
        with zenoh.open(client("certs")) as accepted:  # a certificate of the CA
            assert str(accepted.info.zid())
        # A certificate of another CA, none, or a client that does not trust the router's.
        for refused in (client("other"), client(None), client("certs", ca="other")):
            with pytest.raises(zenoh.ZError):
                zenoh.open(refused).close()
