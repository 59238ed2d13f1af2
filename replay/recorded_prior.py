"""A session's prior in its recording: the files, so that a replay needs no prior store.

A config with a ``prior`` (protocol version 8) names earlier recordings by the SHA-256 of
their files. The service records each file whole when the session starts, as one
``/prior`` message ``{"seq", "t_ns", "sha256", "data"}`` (``data``: the file's bytes,
base64), in the config's order (`record_prior`). `recorded_prior` reads the
prior back from them, checking every digest, exactly as the service read it from its
store (`replay.prior.read_prior`), so that ``cfbci replay`` and a resumed service
re-run the session as it ran. A recording of version 7 or older has no ``prior``.
"""

from __future__ import annotations

import base64
import hashlib
import tempfile
import time
from pathlib import Path

from calibration_free.prior import Prior
from replay.prior import read_prior
from replay.recording import Recording, SessionRecorder


def record_prior(recorder: SessionRecorder, files: dict[str, bytes]) -> None:
    """Record a session's prior files (digest -> bytes, in the config's order) on
    ``/prior``, at the log time of their recording."""
    for seq, (sha256, data) in enumerate(files.items()):
        t_ns = time.time_ns()
        message = {"seq": seq, "t_ns": t_ns, "sha256": sha256,
                   "data": base64.b64encode(data).decode("ascii")}
        recorder.record("/prior", message, t_ns)


def prior_files(recording: Recording) -> dict[str, bytes]:
    """The files of the prior a recorded session started from, by digest in the config's
    order (none for a session without one).

    Raises
    ------
    ValueError
        When the recording names a prior it holds no intact copy of (the digest of a
        missing file, or of one whose bytes have another SHA-256).
    """
    held = {m["sha256"]: m["data"] for _, m in recording.messages.get("/prior", [])}
    files = {}
    for sha256 in recording.config.get("prior") or []:
        if sha256 not in held:
            raise ValueError(f"{recording.path}: the session's prior {sha256[:12]} is not in "
                             "the recording (no /prior message holds it)")
        files[sha256] = base64.b64decode(held[sha256])
        if hashlib.sha256(files[sha256]).hexdigest() != sha256:
            raise ValueError(f"{recording.path}: the recorded copy of prior {sha256[:12]} "
                             "has another SHA-256: damaged")
    return files


def recorded_prior(recording: Recording) -> Prior | None:
    """The prior a recorded session started from (None for a session without one), read
    from its files (`prior_files`) as the service read them from its store.

    Raises
    ------
    ValueError
        As `prior_files`.
    """
    files = prior_files(recording)
    if not files:
        return None
    with tempfile.TemporaryDirectory(prefix="cfbci-prior-") as folder:
        paths = [Path(folder) / f"{sha256}.mcap" for sha256 in files]
        for path, data in zip(paths, files.values(), strict=True):
            path.write_bytes(data)
        return read_prior(paths)
