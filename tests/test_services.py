"""Several services on one Zenoh network (real processes through a real `cfbci router` on
loopback): a source picks the least loaded service, exactly that one runs the session, and
a service refuses a session another one claims."""

from __future__ import annotations

import queue
import time
from collections.abc import Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import zenoh
from live import SPAWN, TIMEOUT, answering_challenges
from test_pipeline import GRID, STEPS, simulated

from acquisition.simulated_source import SourceSettings, SourceSummary, run_source
from cfbci.service import serve
from cfbci.service.limits import ServiceLimits
from cfbci.service.router import run_router
from replay.recording import read_recording
from wire import protocol
from wire.services import ask_for_offers, claim_key, claims_of, pick_service
from wire.transport import (
    Outbox,
    Pump,
    Received,
    reliable_publisher,
    wait_for_subscribers,
)
from wire.zenoh_config import free_tcp_endpoint, peer_config


@contextmanager
def processes(*targets: tuple) -> Iterator[None]:
    """Spawned processes ``(function, args, kwargs)``, stopped with SIGTERM (exit 0)."""
    started = [SPAWN.Process(target=f, args=a, kwargs=k) for f, a, k in targets]
    for process in started:
        process.start()
    try:
        yield
    finally:
        for process in reversed(started):
            process.terminate()
            process.join(TIMEOUT)
    assert [p.exitcode for p in started] == [0] * len(started)


@contextmanager
def client_source(
    settings: SourceSettings, router: str, client: Path
) -> Iterator[Future[SourceSummary]]:
    """``cfbci source`` in a spawned process, a Zenoh client of the router."""
    with ProcessPoolExecutor(1, mp_context=SPAWN) as pool:
        yield pool.submit(run_source, settings, [], [router], client)


def router_process(endpoint: str, ready: Any) -> None:
    """``cfbci router`` on ``endpoint``; sets ``ready`` (an Event) once it listens."""
    run_router([endpoint], on_ready=lambda _: ready.set())


def wait_for_offers(client: zenoh.Session, services: set[str]) -> None:
    """Query until every one of ``services`` answers the offers query."""
    deadline = time.monotonic() + TIMEOUT
    while {o.service for o in ask_for_offers(client)} != services:
        assert time.monotonic() < deadline, f"not every service of {services} answered"


def next_message(inbox: queue.SimpleQueue[Received]) -> protocol.Message:
    """The next message but ``session_pending`` challenges (answered by
    `live.answering_challenges` where a test needs its sessions started)."""
    while True:
        message = protocol.decode(inbox.get(timeout=TIMEOUT).data)
        if message.kind != "event" or message.fields["event"] != "session_pending":
            return message


def test_each_session_is_served_by_exactly_the_service_its_source_picked(
    tmp_path: Path,
) -> None:
    # Services and sources are Zenoh clients of the router, as in docs/deployment.md (peers
    # behind a router do not route queries and liveliness tokens to each other).
    router, client_file = free_tcp_endpoint(), tmp_path / "client.json5"
    client_file.write_text('{mode: "client"}')
    dirs = {name: tmp_path / name for name in ("svc-a", "svc-b")}
    services = [(serve, ([], [router], d), {"service_id": name, "zenoh_config": client_file})
                for name, d in dirs.items()]
    ready = SPAWN.Event()
    with processes((router_process, (router, ready), {})):
        assert ready.wait(TIMEOUT)  # clients cannot open before their router listens
        with processes(*services), zenoh.open(peer_config((), [router], client_file)) as client:
            wait_for_offers(client, set(dirs))
            summaries = run_two_sessions(client, router, client_file)
    for name, seed in (("first", 3), ("second", 5)):
        assert summaries[name].records == simulated(seed)[0]
        where = [d.name for d in dirs.values() if (d / f"{name}.mcap").exists()]
        assert len(where) == 1, (name, where)  # recorded by one service only
        recording = read_recording(dirs[where[0]] / f"{name}.mcap")
        assert not recording.truncated and len(recording.messages["/move"]) == STEPS
        assert recording.config["service"] == where[0]  # the one its source picked
    # "first" found both services idle: the smaller id. ("second" picks the less loaded
    # one, svc-b while "first" still runs, as asserted on the offers above; on a loaded
    # machine "first" may have ended by then, and the tie goes to svc-a.)
    assert (dirs["svc-a"] / "first.mcap").exists()


def run_two_sessions(
    client: zenoh.Session, router: str, client_file: Path
) -> dict[str, SourceSummary]:
    """"first" on the idle services (svc-a: the smaller id), a claim refused while it runs,
    then "second" (svc-b: the less loaded); the two sources' summaries."""
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    pumps = [Pump(client, protocol.key("first", kind), kind, inbox) for kind in ("move", "event")]
    first = SourceSettings("first", seed=3, steps=STEPS, grid=GRID, timeout=TIMEOUT,
                           interval=0.1, pick_service=True)
    second = SourceSettings("second", seed=5, steps=STEPS, grid=GRID, timeout=TIMEOUT,
                            pick_service=True)
    try:
        with client_source(first, router, client_file) as first_done:
            while next_message(inbox).kind != "move":
                pass
            offers = ask_for_offers(client)
            assert {o.service: o.sessions for o in offers} == {"svc-a": 1, "svc-b": 0}
            assert pick_service(offers).service == "svc-b"

            # Another source reusing the running id and naming svc-b is refused by svc-b,
            # which sees svc-a's claim; the running session is not disturbed.
            publisher = reliable_publisher(client, protocol.key("first", "config"))
            assert wait_for_subscribers(publisher, TIMEOUT)
            fields = {"seed": 0, "world": "grid", "grid": GRID, "frame": "feedback",
                      "steps": STEPS, "learner": {}, "dataset": {}, "signal": "features",
                      "service": "svc-b"}
            publisher.put(protocol.encode(protocol.Message("config", "first", 0, 7, fields)))
            while (message := next_message(inbox)).kind != "event" or (
                    message.fields["config_t_ns"] != 7):
                pass
            assert message.fields["event"] == "session_rejected"
            assert "already served by service 'svc-a'" in message.fields["message"]

            with client_source(second, router, client_file) as second_done:
                summaries = {"second": second_done.result(TIMEOUT)}
            summaries["first"] = first_done.result(TIMEOUT)
    finally:
        for pump in pumps:
            pump.close()
    return summaries


def test_a_session_whose_start_fails_leaves_no_claim(tmp_path: Path) -> None:
    # One service that runs one session at most. "x" names it and waits for its source
    # (claimed); "y" then takes the one slot; when x's source subscribes, x's start fails
    # (the service is full) and x is rejected: its claim must be gone by then, y's kept.
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    limits = ServiceLimits(max_sessions=1, subscriber_timeout=TIMEOUT, idle_timeout=TIMEOUT)
    service = (serve, ([endpoint], [client_endpoint], tmp_path),
               {"limits": limits, "service_id": "svc-a"})
    config = {"seed": 0, "world": "grid", "grid": GRID, "frame": "feedback", "steps": STEPS,
              "learner": {}, "dataset": {}, "signal": "features", "service": "svc-a"}
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    x_events: queue.SimpleQueue[Received] = queue.SimpleQueue()
    with zenoh.open(peer_config([client_endpoint], ())) as client, processes(service):
        outbox = Outbox(client)
        pumps = [Pump(client, protocol.key("x", "event"), "event", x_events)]
        assert wait_for_subscribers(outbox.publisher(protocol.key("x", "config")), TIMEOUT)
        x_config = outbox.send("config", "x", config)
        x_pending = protocol.decode(x_events.get(timeout=TIMEOUT).data)  # its challenge
        assert x_pending.fields["event"] == "session_pending"
        deadline = time.monotonic() + TIMEOUT
        while claims_of(client, "x") != ["svc-a"]:  # x waits for its source, claimed
            assert time.monotonic() < deadline, "the service never claimed x"
        pumps.append(Pump(client, protocol.key("y", "event"), "event", inbox))
        try:
            with answering_challenges(client):
                outbox.send("config", "y", config)
                assert next_message(inbox).fields["event"] == "session_started"
            # x's source answers its challenge now: x's start fails, the service is full.
            outbox.send("ready", "x", {"config_t_ns": x_config.t_ns,
                                       "challenge": x_pending.fields["challenge"]})
            rejected = next_message(x_events)
            assert (rejected.session, rejected.fields["event"]) == ("x", "session_rejected")
            assert "maximum of 1" in rejected.fields["message"]
            assert claims_of(client, "x") == []
            assert claims_of(client, "y") == ["svc-a"]
        finally:
            for pump in pumps:
                pump.close()
            outbox.close()


def test_of_two_services_claiming_one_session_the_smaller_id_keeps_it(tmp_path: Path) -> None:
    # svc-m runs "x" and "w"; then claims appear as if other services had claimed them at
    # the same moment as svc-m. svc-z's (a larger id) on "x" and "y", then svc-a's (a
    # smaller id) on "w": svc-m gives "w" up, naming svc-a. A service hears one peer's
    # claims in the order they were declared, so by then it has heard svc-z's too (a
    # config travels apart from the claims and may overtake them: it cannot be the
    # probe). svc-m keeps "x", and refuses a config for "y", claimed by svc-z. Then svc-a
    # claims "x": svc-m gives "x" up, naming svc-a, and withdraws its own claim.
    endpoint, client_endpoint = free_tcp_endpoint(), free_tcp_endpoint()
    service = (serve, ([endpoint], [client_endpoint], tmp_path), {"service_id": "svc-m"})
    config = {"seed": 0, "world": "grid", "grid": GRID, "frame": "feedback", "steps": STEPS,
              "learner": {}, "dataset": {}, "signal": "features", "service": "svc-m"}
    inboxes: dict[str, queue.SimpleQueue[Received]] = {sid: queue.SimpleQueue() for sid in "xyw"}
    with (
        zenoh.open(peer_config([client_endpoint], ())) as client,
        processes(service),
        answering_challenges(client),
    ):
        outbox = Outbox(client)
        pumps = [Pump(client, protocol.key(sid, "event"), "event", inboxes[sid])
                 for sid in "xyw"]
        tokens = []
        try:
            assert wait_for_subscribers(outbox.publisher(protocol.key("x", "config")), TIMEOUT)
            sent = outbox.send("config", "x", config)
            assert next_message(inboxes["x"]).fields["event"] == "session_started"
            outbox.send("config", "w", config)
            assert next_message(inboxes["w"]).fields["event"] == "session_started"
            tokens += [client.liveliness().declare_token(claim_key(sid, "svc-z"))
                       for sid in "xy"]
            tokens.append(client.liveliness().declare_token(claim_key("w", "svc-a")))
            probe = next_message(inboxes["w"])
            assert probe.fields["event"] == "session_rejected"
            assert "also claimed by service 'svc-a'" in probe.fields["message"]
            outbox.send("config", "y", config)
            refused = next_message(inboxes["y"])
            assert refused.fields["event"] == "session_rejected"
            assert "already served by service 'svc-z'" in refused.fields["message"]
            assert claims_of(client, "x") == ["svc-m", "svc-z"]  # svc-m keeps "x"
            tokens.append(client.liveliness().declare_token(claim_key("x", "svc-a")))
            rejected = next_message(inboxes["x"])
            assert rejected.fields["event"] == "session_rejected"
            assert rejected.fields["config_t_ns"] == sent.t_ns
            assert "also claimed by service 'svc-a'" in rejected.fields["message"]
            assert claims_of(client, "x") == ["svc-a", "svc-z"]  # svc-m's is withdrawn
        finally:
            for token in tokens:
                token.undeclare()
            for pump in pumps:
                pump.close()
            outbox.close()
    recording = read_recording(tmp_path / "x.mcap")
    assert not recording.truncated  # ended, and closed, by its service
