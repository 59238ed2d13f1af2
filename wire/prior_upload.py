"""A source's upload of a prior into the service's prior store (docs/protocol.md, "Priors").

A config names its prior by the SHA-256 of each file (`file_sha256`); the service
reads the files from the prior store of the session's user. `upload_priors` puts
them there first: for each file, a ``prior`` message without data asks how many bytes the
service holds (all of them: nothing to send), then chunks of `CHUNK_BYTES` follow,
each sent once the service has answered the previous one with a ``prior_received`` event
(re-sent unchanged until then, as a config or an epoch is). A ``prior_rejected`` event
ends the upload with the service's reason.
"""

from __future__ import annotations

import base64
import hashlib
import logging
import queue
import time
from collections.abc import Sequence
from pathlib import Path

import zenoh

from wire import protocol
from wire.transport import Outbox, Pump, Received, Resender, wait_for_subscribers

log = logging.getLogger("cfbci.source")

#: Bytes of a file per ``prior`` message (base64 in the header: 4/3 as many characters,
#: well under the service's default message limit of 1.06 MiB).
CHUNK_BYTES = 256 * 2**10


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, as 64 hexadecimal digits."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        while block := stream.read(2**20):
            digest.update(block)
    return digest.hexdigest()


def upload_priors(
    session: zenoh.Session,
    sid: str,
    paths: Sequence[Path],
    timeout: float,
    resend_interval: float,
) -> list[str]:
    """Upload prior files into the store of session ``sid``'s user, where the service
    lacks them; their digests, in order (the config's ``prior``).

    Raises
    ------
    TimeoutError
        When no service subscribes to uploads, or none answers for ``timeout`` seconds.
    RuntimeError
        When the service refuses a file (``prior_rejected``: its message).
    """
    files = [(str(path), path.read_bytes()) for path in paths]
    return upload_contents(session, sid, files, timeout, resend_interval)


def upload_contents(
    session: zenoh.Session,
    sid: str,
    files: Sequence[tuple[str, bytes]],
    timeout: float,
    resend_interval: float,
) -> list[str]:
    """`upload_priors` of files' contents, each with the name messages give it."""
    inbox: queue.SimpleQueue[Received] = queue.SimpleQueue()
    pump = Pump(session, protocol.key(sid, "event"), "event", inbox)
    outbox = Outbox(session)
    try:
        if not wait_for_subscribers(outbox.publisher(protocol.key(sid, "prior")), timeout):
            raise TimeoutError(f"no service subscribed to {protocol.key(sid, 'prior')} within "
                               f"{timeout:g} s")
        return [_upload(name, data, sid, inbox, Resender(outbox, resend_interval), timeout)
                for name, data in files]
    finally:
        pump.close()
        outbox.close()


def _upload(
    path: str,
    data: bytes,
    sid: str,
    inbox: queue.SimpleQueue[Received],
    resender: Resender,
    timeout: float,
) -> str:
    """Upload one file (see the module docstring); its digest."""
    sha256 = hashlib.sha256(data).hexdigest()

    def send(offset: int, ask: bool = False) -> None:
        chunk = b"" if ask else data[offset : offset + CHUNK_BYTES]
        fields = {"sha256": sha256, "size": len(data), "offset": offset,
                  "data": base64.b64encode(chunk).decode("ascii")}
        resender.send("prior", sid, fields)

    send(0, ask=True)
    heard = time.monotonic()
    while True:
        assert resender.pending is not None
        try:
            received = inbox.get(timeout=resender.wait(timeout))
        except queue.Empty:
            if time.monotonic() - heard > timeout:
                raise TimeoutError(f"session {sid!r}: no answer to the upload of prior {path} "
                                   f"for {timeout:g} s") from None
            resender.poll()
            continue
        try:
            fields = protocol.decode(received.data, key_expr=received.key_expr).fields
        except protocol.ProtocolError as error:
            log.warning("dropped a message of the service: %s", error)
            continue
        if fields.get("prior") != sha256:
            continue  # another event of the session's id
        heard = time.monotonic()
        if fields["event"] == "prior_rejected":
            raise RuntimeError(f"the service refused prior {path}: {fields['message']}")
        held = fields["received"]
        if held == len(data):
            resender.answered()
            log.info("prior %s (%s): %s", path, sha256[:12], fields["message"])
            return sha256
        pending = resender.pending.fields
        if pending["data"] == "" or pending["offset"] != held:  # else: a repeated answer
            send(held)
