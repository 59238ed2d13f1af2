"""Zenoh configuration of the pipeline: the project's defaults, a user's file over them.

By default every process of a session (service, source, displays) is a Zenoh *peer* that
listens on, and connects to, explicit endpoints such as ``tcp/127.0.0.1:7447``; multicast
scouting is off, so nothing is discovered (or leaked) beyond the endpoints given.

``--zenoh-config FILE`` (``cfbci serve``, ``source``, ``session``, ``router``, ``replay
--publish``) names a Zenoh JSON5 configuration merged over these defaults, and the
endpoints of the command line over the file. Three layers, later ones winning:

1. the project's defaults: ``mode`` (``"peer"``; ``"router"`` for ``cfbci router``),
   multicast scouting off, no endpoints;
2. the file: objects are merged key by key (recursively), any other value (a string, a
   number, a list) replaces the default; so a file that sets ``mode: "client"``, TLS,
   credentials or an ``access_control`` section keeps multicast scouting off unless it
   turns it on itself;
3. ``--listen`` and ``--connect``: when given, they replace the file's
   ``listen/endpoints`` and ``connect/endpoints``.

Relative paths in the file (certificates, ``dictionary_file``) are Zenoh's business:
relative to the process's working directory. ``docs/deployment.md`` shows a router-
centred deployment with TLS, user/password authentication and access control.
"""

from __future__ import annotations

import json
import random
import socket
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import json5
import zenoh

#: Zenoh modes a configuration may ask for.
MODES = ("peer", "client", "router")


def project_defaults(mode: str = "peer") -> dict[str, Any]:
    """The project's defaults: ``mode``, multicast scouting off, no endpoints."""
    if mode not in MODES:
        raise ValueError(f"Zenoh mode must be one of {MODES}; got {mode!r}")
    return {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}},
        "listen": {"endpoints": []},
        "connect": {"endpoints": []},
    }


def read_config_file(path: Path) -> dict[str, Any]:
    """A Zenoh JSON5 configuration file as a dictionary.

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    ValueError
        If it is not JSON5, or not one JSON5 object; the message names the file.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"--zenoh-config {path}: no such file") from None
    except (IsADirectoryError, UnicodeDecodeError) as error:
        raise ValueError(f"--zenoh-config {path}: cannot be read as text: {error}") from None
    try:
        document = json5.loads(text)
    except ValueError as error:
        raise ValueError(f"--zenoh-config {path}: not valid JSON5: {error}") from None
    if not isinstance(document, dict):
        raise ValueError(
            f"--zenoh-config {path}: a Zenoh configuration is one JSON5 object; got "
            f"{type(document).__name__}"
        )
    return document


def merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``override`` over ``base``: objects merged key by key, recursively; other values
    (strings, numbers, lists, null) of ``override`` replace those of ``base``. Neither
    argument is modified."""
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def config_document(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zenoh_config: Path | None = None,
    mode: str = "peer",
) -> dict[str, Any]:
    """The merged configuration (defaults, file, command-line endpoints) as a dictionary.

    Parameters
    ----------
    listen, connect : sequence of str
        Endpoints of the command line, e.g. ``["tcp/127.0.0.1:7447"]``; when non-empty
        they replace the file's.
    zenoh_config : Path or None
        A Zenoh JSON5 configuration file (see the module docstring).
    mode : {"peer", "client", "router"}
        The default mode (the file may set another).
    """
    document = project_defaults(mode)
    if zenoh_config is not None:
        document = merge(document, read_config_file(zenoh_config))
    if listen:
        document = merge(document, {"listen": {"endpoints": list(listen)}})
    if connect:
        document = merge(document, {"connect": {"endpoints": list(connect)}})
    return document


def build_config(document: Mapping[str, Any], origin: Path | None = None) -> zenoh.Config:
    """A `zenoh.Config` from a configuration dictionary, checked by Zenoh.

    Raises
    ------
    ValueError
        If Zenoh rejects it (unknown key, wrong type, ...), naming ``origin`` if given.
    """
    try:
        return zenoh.Config.from_json5(json.dumps(document))
    except zenoh.ZError as error:
        where = f"--zenoh-config {origin}" if origin is not None else "Zenoh configuration"
        raise ValueError(f"{where}: rejected by Zenoh: {error}") from None


def peer_config(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zenoh_config: Path | None = None,
) -> zenoh.Config:
    """The configuration of a pipeline process: a peer with multicast scouting off, unless
    ``zenoh_config`` says otherwise (see the module docstring).

    Parameters
    ----------
    listen : sequence of str
        Endpoints to accept connections on, e.g. ``["tcp/127.0.0.1:7447"]``.
    connect : sequence of str
        Endpoints of other peers (or of a router) to connect to (retried until they
        listen).
    zenoh_config : Path or None
        A Zenoh JSON5 configuration file merged over the defaults.

    Returns
    -------
    zenoh.Config

    Raises
    ------
    FileNotFoundError, ValueError
        If the file is missing, not JSON5, or rejected by Zenoh (the message names it).
    """
    return build_config(config_document(listen, connect, zenoh_config), zenoh_config)


def router_config(
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    zenoh_config: Path | None = None,
) -> zenoh.Config:
    """As `peer_config`, for a Zenoh router (``cfbci router``).

    Raises
    ------
    ValueError
        Also if the result listens on no endpoint, or is not in router mode.
    """
    document = config_document(listen, connect, zenoh_config, mode="router")
    if document.get("mode") != "router":
        raise ValueError(
            f"--zenoh-config {zenoh_config}: sets mode {document.get('mode')!r}; "
            "cfbci router runs a Zenoh router (mode \"router\")"
        )
    if not document.get("listen", {}).get("endpoints"):
        raise ValueError(
            "a router must listen: give --listen EP or listen/endpoints in --zenoh-config"
        )
    return build_config(document, zenoh_config)


#: Where the kernel says its ephemeral ports are (Linux); the ports it hands to outgoing
#: connections and to ``bind(0)``.
EPHEMERAL_PORT_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
#: The lowest port `free_tcp_endpoint` picks below the ephemeral range.
LOWEST_LISTEN_PORT = 10000


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """``tcp/<host>:<port>`` with a TCP port that was free a moment ago.

    The endpoint is bound later by another process (a service started after it is
    chosen). A port the OS picks for ``bind(0)`` is an ephemeral port, one the OS may also
    give, in the meantime, to any outgoing connection (the session's other processes
    connecting to each other): the listener then fails with "Address already in use" (it
    did, once, in a ``make run``). So where the kernel's ephemeral range is known (Linux),
    the port is drawn at random below it, from ``LOWEST_LISTEN_PORT`` up, where only an
    explicit bind can take it; elsewhere the OS picks it.
    """
    low = _ephemeral_low()
    attempts = 100 if low is not None and low > LOWEST_LISTEN_PORT else 0
    draw = random.SystemRandom()
    for _ in range(attempts):
        port = draw.randrange(LOWEST_LISTEN_PORT, low)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
            try:
                probe.bind((host, port))
            except OSError:
                continue
            return f"tcp/{host}:{port}"
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return f"tcp/{host}:{probe.getsockname()[1]}"


def _ephemeral_low() -> int | None:
    """The first port of the kernel's ephemeral range, or None where it cannot be read."""
    try:
        return int(EPHEMERAL_PORT_RANGE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None
