"""Zenoh configuration of the pipeline: peers on explicit TCP endpoints, no multicast.

Every process of a session (service, source, displays) is a Zenoh *peer* that listens
on, and connects to, explicit endpoints such as ``tcp/127.0.0.1:7447``; multicast
scouting is off, so nothing is discovered (or leaked) beyond the endpoints given.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence

import zenoh


def peer_config(listen: Sequence[str] = (), connect: Sequence[str] = ()) -> zenoh.Config:
    """A peer-mode Zenoh configuration with multicast scouting off.

    Parameters
    ----------
    listen : sequence of str
        Endpoints to accept connections on, e.g. ``["tcp/127.0.0.1:7447"]``.
    connect : sequence of str
        Endpoints of other peers to connect to (retried until they listen).

    Returns
    -------
    zenoh.Config
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("peer"))
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", "false")
    return config


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """``tcp/<host>:<port>`` with a TCP port that was free a moment ago (picked by the OS)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return f"tcp/{host}:{probe.getsockname()[1]}"
