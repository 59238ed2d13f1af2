"""``--zenoh-config``: a Zenoh JSON5 file merged over the project's defaults, the command
line's endpoints over the file; bad files named with their problem; the shipped
deployment files accepted by Zenoh and consistent with each other."""

from __future__ import annotations

import json
import queue
import re
from pathlib import Path

import pytest
import zenoh

from cfbci.cli import main
from wire.transport import wait_for_subscribers
from wire.zenoh_config import (
    EPHEMERAL_PORT_RANGE,
    LOWEST_LISTEN_PORT,
    build_config,
    free_tcp_endpoint,
    merge,
    peer_config,
    read_config_file,
    router_config,
)

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
TIMEOUT = 30.0  # failure guard, seconds


def _get(config: zenoh.Config, key: str) -> object:
    return json.loads(config.get_json(key))


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.skipif(
    not EPHEMERAL_PORT_RANGE.exists(), reason="the kernel's ephemeral port range is Linux's"
)
def test_a_free_endpoint_is_outside_the_ports_outgoing_connections_take() -> None:
    # Ports handed to outgoing connections cannot take a listener's port chosen in advance.
    low = int(EPHEMERAL_PORT_RANGE.read_text().split()[0])
    ports = set()
    for _ in range(20):
        host, port = free_tcp_endpoint().removeprefix("tcp/").rsplit(":", 1)
        ports.add(int(port))
        assert host == "127.0.0.1" and LOWEST_LISTEN_PORT <= int(port) < low
    assert len(ports) > 1  # drawn at random, not one fixed port
    with zenoh.open(peer_config([f"tcp/127.0.0.1:{min(ports)}"], ())):
        pass  # and Zenoh can listen there


def test_defaults_are_a_peer_on_the_given_endpoints_without_multicast() -> None:
    config = peer_config(["tcp/127.0.0.1:7001"], ["tcp/127.0.0.1:7002"])
    assert _get(config, "mode") == "peer"
    assert _get(config, "scouting/multicast/enabled") is False
    assert _get(config, "listen/endpoints") == ["tcp/127.0.0.1:7001"]
    assert _get(config, "connect/endpoints") == ["tcp/127.0.0.1:7002"]


def test_a_file_is_merged_over_the_defaults_and_the_command_line_over_the_file(
    tmp_path: Path,
) -> None:
    path = _write(tmp_path / "c.json5", """{
        // JSON5: comments, unquoted keys, trailing commas
        mode: "client",
        connect: {endpoints: ["tcp/127.0.0.1:7100"],},
        transport: {auth: {usrpwd: {user: "lab1", password: "pw"}}},
    }""")
    config = peer_config(zenoh_config=path)
    assert _get(config, "mode") == "client"
    assert _get(config, "connect/endpoints") == ["tcp/127.0.0.1:7100"]
    assert _get(config, "transport/auth/usrpwd/user") == "lab1"
    assert _get(config, "scouting/multicast/enabled") is False  # the default kept

    config = peer_config(["tcp/127.0.0.1:7201"], ["tcp/127.0.0.1:7200"], zenoh_config=path)
    assert _get(config, "connect/endpoints") == ["tcp/127.0.0.1:7200"]  # replaced, not added
    assert _get(config, "listen/endpoints") == ["tcp/127.0.0.1:7201"]

    on = _write(tmp_path / "on.json5", '{scouting: {multicast: {enabled: true}}}')
    assert _get(peer_config(zenoh_config=on), "scouting/multicast/enabled") is True


def test_merge_recurses_into_objects_and_replaces_everything_else() -> None:
    base = {"a": {"b": 1, "c": [1, 2]}, "d": "x"}
    assert merge(base, {"a": {"c": [3]}, "e": None}) == {"a": {"b": 1, "c": [3]}, "d": "x",
                                                         "e": None}
    assert merge(base, {"a": 5}) == {"a": 5, "d": "x"}
    assert base == {"a": {"b": 1, "c": [1, 2]}, "d": "x"}  # not modified


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("{mode: 'peer',, }", "not valid JSON5"),
        ("[1, 2]", "one JSON5 object; got list"),
        ("{colour: 'blue'}", "rejected by Zenoh: unknown field `colour`"),
        ("{mode: 'banana'}", "rejected by Zenoh: unknown variant `banana`"),
        ("{listen: {endpoints: ['nowhere']}}", "rejected by Zenoh: Endpoints must be"),
    ],
)
def test_a_bad_file_is_named_with_its_problem(tmp_path: Path, text: str, expected: str) -> None:
    path = _write(tmp_path / "bad.json5", text)
    with pytest.raises(ValueError, match=re.escape(expected)) as raised:
        peer_config(zenoh_config=path)
    assert str(path) in str(raised.value)


def test_a_missing_file_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "nope.json5"
    with pytest.raises(FileNotFoundError, match=re.escape("nope.json5: no such file")):
        peer_config(zenoh_config=missing)
    # The command line: an error naming the file, exit 2, before any network is opened.
    assert main(["serve", "--zenoh-config", str(missing)]) == 2
    assert "nope.json5: no such file" in capsys.readouterr().err.replace("\n", "")


def test_router_configuration_must_listen_and_stay_a_router(tmp_path: Path) -> None:
    config = router_config(["tcp/127.0.0.1:7300"])
    assert _get(config, "mode") == "router"
    assert _get(config, "scouting/multicast/enabled") is False
    with pytest.raises(ValueError, match="a router must listen"):
        router_config()
    client = _write(tmp_path / "client.json5", '{mode: "client"}')
    with pytest.raises(ValueError, match="sets mode 'client'"):
        router_config(["tcp/127.0.0.1:7300"], zenoh_config=client)


def test_the_file_configures_a_real_session(tmp_path: Path) -> None:
    """A peer that listens where its file says is reached by one that connects there."""
    endpoint = free_tcp_endpoint()
    listening = _write(tmp_path / "l.json5", json.dumps({"listen": {"endpoints": [endpoint]}}))
    received: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    with (
        zenoh.open(peer_config(zenoh_config=listening)) as listener,
        zenoh.open(peer_config((), [endpoint])) as talker,
    ):
        subscriber = listener.declare_subscriber(
            "cfbci/test/x", lambda sample: received.put(sample.payload.to_bytes())
        )
        publisher = talker.declare_publisher("cfbci/test/x")
        assert wait_for_subscribers(publisher, TIMEOUT)
        publisher.put(b"hello")
        assert received.get(timeout=TIMEOUT) == b"hello"
        subscriber.undeclare()


def test_the_shipped_deployment_files_are_accepted_and_consistent() -> None:
    documents = {name: read_config_file(DEPLOY / f"{name}.json5")
                 for name in ("router", "service", "source")}
    for document in documents.values():
        build_config(document)  # Zenoh accepts it
    router, service, source = documents["router"], documents["service"], documents["source"]
    assert router["mode"] == "router" and service["mode"] == source["mode"] == "client"
    assert all(e.startswith("tls/") for e in router["listen"]["endpoints"])
    for client in (service, source):
        assert all(e.startswith("tls/") for e in client["connect"]["endpoints"])

    credentials = dict(
        line.split(":", 1) for line in (DEPLOY / "credentials.example.txt").read_text().split()
    )
    acl = router["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    users = {name for subject in acl["subjects"] for name in subject["usernames"]}
    assert users == set(credentials)  # every user has a policy, every policy a user
    for client in (service, source):
        usrpwd = client["transport"]["auth"]["usrpwd"]
        assert credentials[usrpwd["user"]] == usrpwd["password"]
    rules = {rule["id"] for rule in acl["rules"]}
    subjects = {subject["id"] for subject in acl["subjects"]}
    for policy in acl["policies"]:
        assert set(policy["rules"]) <= rules and set(policy["subjects"]) <= subjects
