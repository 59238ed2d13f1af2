"""The service's prior store: earlier recordings of a user, named by the SHA-256 of their files.

A config names the prior its learner starts from (`calibration_free.prior`) by the
SHA-256 digests of one or more recording files (its field ``prior``, protocol version 8),
since a config is small and a recording of raw epochs is not. The files are in the
store, one folder per user::

    <prior dir>/<user>/<sha256>.mcap          sessions <user>/<name>
    <prior dir>/.anonymous/<sha256>.mcap      one-chunk session ids (no user)

The access rule is the key space's: a session ``<user>/<name>`` uses only the priors of
``<prior dir>/<user>/``, and its source uploads only into that folder (over
``cfbci/<user>/<name>/prior``, a key chunk that access control grants that user alone).
A source uploads a file in chunks (``prior`` messages, `PriorStore.receive`),
each answered by a ``prior_received`` event saying how many bytes the service holds (the
file's size once it is stored, its hash checked), or by ``prior_rejected`` saying why.
An upload interrupted goes on where it stopped; a service restarted starts it over. The
store of a user holds at most ``user_prior_mb`` MiB (uploads in progress counted by
their declared size). ``cfbci priors`` lists, adds and deletes priors.

When a session starts, its recording receives the content of its prior (``/prior``,
`replay.recorded_prior`), so that ``cfbci replay`` re-runs it without the store.
"""

from __future__ import annotations

import base64
import binascii
import logging
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calibration_free.frames import Frame
from calibration_free.prior import Prior, ReturningLearner
from cfbci.service.admission import Reject, Rejection
from cfbci.service.limits import ServiceLimits
from replay.prior import read_prior, recording_space
from replay.recorded_prior import record_prior
from replay.recording import SessionRecorder
from session.config import config_world
from session.core import Session
from session.plane import is_plane
from session.sessions import open_session
from wire import protocol
from wire.prior_upload import file_sha256
from wire.transport import Received

log = logging.getLogger("cfbci.service")

#: The folder of the priors of sessions whose id has no user (not a valid user name).
ANONYMOUS = ".anonymous"
#: Suffix of an upload in progress.
PARTIAL = ".part"
#: Seconds an upload may wait for its next chunk before another upload may take its room.
UPLOAD_IDLE = 300.0
#: Priors read and kept for the sessions about to start (the most recent ones).
CACHED = 16

#: ``publish(session, event, text, extra=fields)``: an event answering an upload
#: (`cfbci.service.events.Events.publish`).
Answer = Callable[..., None]


def default_store(record_dir: Path | None) -> Path | None:
    """The prior store of a service without ``--prior-dir``: ``<record_dir>/priors`` (none
    without a record directory)."""
    return None if record_dir is None else record_dir / "priors"


def owner(session: str) -> str:
    """The store folder's name of a session id: its user, or `ANONYMOUS`."""
    user = protocol.user_of(session)
    return ANONYMOUS if user is None else user


def short(sha256: str) -> str:
    """A digest as messages name it: its first 12 digits."""
    return sha256[:12]


@dataclass(frozen=True)
class StoredPrior:
    """A file of the store: its user (or `ANONYMOUS`), digest, size (bytes) and
    path."""

    user: str
    sha256: str
    size: int
    path: Path


def stored_priors(directory: Path, user: str | None = None) -> list[StoredPrior]:
    """The priors in a store, of one user or all, by user then digest."""
    if user is not None:
        folders = [directory / user]
    else:
        folders = sorted(directory.iterdir()) if directory.is_dir() else []
    return [
        StoredPrior(folder.name, path.stem, path.stat().st_size, path)
        for folder in folders if folder.is_dir()
        for path in sorted(folder.glob("*.mcap"))
    ]


def add_prior(directory: Path, user: str, source: Path) -> StoredPrior:
    """Copy a recording into a user's store (``cfbci priors add``); an existing copy stays.

    Raises
    ------
    FileNotFoundError, ValueError
        On a missing file, a user name that is not one, or a file that is no prior
        (`replay.prior.read_prior`'s message).
    """
    if user != ANONYMOUS and not protocol.TYPES["name"][1](user):
        raise ValueError(f"user {user!r} is not a name: {protocol.TYPES['name'][0]}")
    read_prior([source])  # refuses a file that is no prior, naming what is wrong
    sha256 = file_sha256(source)
    target = directory / user / f"{sha256}.mcap"
    if not target.exists():
        target.parent.mkdir(parents=True, exist_ok=True)
        partial = target.with_suffix(PARTIAL)
        shutil.copyfile(source, partial)
        os.replace(partial, target)
    return StoredPrior(user, sha256, target.stat().st_size, target)


def delete_prior(directory: Path, user: str, sha256: str) -> Path:
    """Delete a prior from a user's store; the path it had.

    Raises
    ------
    FileNotFoundError
        When the user's store holds no such prior.
    """
    path = directory / user / f"{sha256}.mcap"
    if not protocol.TYPES["sha256"][1](sha256) or not path.is_file():
        raise FileNotFoundError(f"user {user!r}'s prior store ({directory / user}) holds no "
                                f"prior {sha256!r}")
    path.unlink()
    return path


@dataclass
class _Upload:
    """An upload in progress: its declared size, its partial file, the bytes received
    and when the last chunk came (monotonic ns)."""

    size: int
    path: Path
    received: int
    last_ns: int


class PriorStore:
    """The priors a service holds (see the module docstring).

    Parameters
    ----------
    directory : Path or None
        The store; None: the service keeps no priors (a config naming one is rejected).
    limits : ServiceLimits
        ``user_prior_mb``: most MiB of priors (stored and being uploaded) one user's store
        may hold; ``max_message_bytes``: the longest message taken in.
    """

    def __init__(self, directory: Path | None, limits: ServiceLimits) -> None:
        self.directory, self.user_mb = directory, limits.user_prior_mb
        self.max_bytes = limits.max_message_bytes
        self._uploads: dict[tuple[str, str], _Upload] = {}
        self._cache: dict[tuple[str, tuple[str, ...]], Prior] = {}
        if directory is not None and directory.is_dir():
            for partial in directory.glob(f"*/*{PARTIAL}"):  # a restart starts uploads over
                partial.unlink()

    # -- uploads ------------------------------------------------------------------------

    def receive(self, received: Received, answer: Answer) -> str:
        """Take one chunk of an upload and answer it (``prior_received`` with the bytes
        held, or ``prior_rejected`` naming the problem); the uploading session's id.

        Raises
        ------
        ProtocolError
            On a message that breaks the protocol (an ``error`` event).
        """
        message = protocol.decode(received.data, key_expr=received.key_expr,
                                  max_bytes=self.max_bytes)
        sid, fields = message.session, message.fields
        sha256 = fields["sha256"]
        extra: dict[str, Any] = {"prior": sha256}
        name = f"prior {short(sha256)}"
        if self.directory is None:
            answer(sid, "prior_rejected", f"{name}: this service keeps no prior store (start "
                   "it with --record-dir or --prior-dir)", extra=extra)
            return sid
        user = owner(sid)
        final = self.directory / user / f"{sha256}.mcap"
        if final.is_file():
            answer(sid, "prior_received", f"{name} is in user {user!r}'s prior store",
                   extra=extra | {"received": final.stat().st_size})
            return sid
        problem, upload = self._upload(user, sha256, fields["size"])
        if upload is None:
            answer(sid, "prior_rejected", f"{name}: {problem}", extra=extra)
            return sid
        if fields["data"] and fields["offset"] == upload.received:
            problem = self._append(upload, fields["data"], sha256)
            if problem is not None:
                self._discard(user, sha256)
                answer(sid, "prior_rejected", f"{name}: {problem}: upload discarded", extra=extra)
                return sid
        if upload.received == upload.size:
            os.replace(upload.path, final)
            del self._uploads[user, sha256]
            log.info("prior %s stored for user %r (%d bytes)", sha256, user, upload.size)
            answer(sid, "prior_received", f"{name} stored in user {user!r}'s prior store",
                   extra=extra | {"received": upload.size})
            return sid
        answer(sid, "prior_received", f"{name}: {upload.received} of {upload.size} bytes "
               "received", extra=extra | {"received": upload.received})
        return sid

    def _upload(self, user: str, sha256: str, size: int) -> tuple[str, _Upload | None]:
        """The upload of ``sha256`` into ``user``'s store, started if there is room; else
        the problem."""
        now = time.monotonic_ns()
        upload = self._uploads.get((user, sha256))
        if upload is not None and upload.size == size:
            upload.last_ns = now
            return "", upload
        for key, other in list(self._uploads.items()):  # stale ones make room
            if key[0] == user and now - other.last_ns > UPLOAD_IDLE * 1e9:
                self._discard(*key)
        self._discard(user, sha256)  # declared with another size: started over
        if size == 0:
            return "an empty file is no prior", None
        assert self.directory is not None
        held = sum(p.size for p in stored_priors(self.directory, user)) + sum(
            u.size for (owner_, _), u in self._uploads.items() if owner_ == user)
        limit = self.user_mb * 2**20
        if held + size > limit:
            return (f"a file of {size / 2**20:.1f} MiB would take user {user!r}'s prior store "
                    f"to {(held + size) / 2**20:.1f} MiB, over its limit of {self.user_mb:g} "
                    "MiB (--user-prior-mb; delete a prior first)"), None
        path = self.directory / user / f"{sha256}{PARTIAL}"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
        upload = self._uploads[user, sha256] = _Upload(size, path, 0, now)
        return "", upload

    @staticmethod
    def _append(upload: _Upload, data: str, sha256: str) -> str | None:
        """Append a chunk to the partial file; the problem, if any (then nothing is
        kept)."""
        try:
            chunk = base64.b64decode(data, validate=True)
        except binascii.Error as error:
            return f"field 'data' is not base64: {error}"
        if upload.received + len(chunk) > upload.size:
            return (f"the chunk at byte {upload.received} runs to byte "
                    f"{upload.received + len(chunk)}, past the declared size {upload.size}")
        with upload.path.open("ab") as stream:
            stream.write(chunk)
        upload.received += len(chunk)
        if upload.received == upload.size and (actual := file_sha256(upload.path)) != sha256:
            return f"the bytes received have SHA-256 {actual}, not the declared one"
        return None

    def _discard(self, user: str, sha256: str) -> None:
        upload = self._uploads.pop((user, sha256), None)
        if upload is not None:
            upload.path.unlink(missing_ok=True)

    # -- sessions -----------------------------------------------------------------------

    def prior(self, session: str, hashes: Sequence[str]) -> Prior:
        """The prior of a session's config's ``prior`` digests, read from its user's store
        (the last `CACHED` kept).

        Raises
        ------
        ValueError
            When the service keeps no store, a digest names no file of the user's store, or
            a file is no prior (naming it and why).
        """
        if self.directory is None:
            raise ValueError("this service keeps no prior store (start it with --record-dir "
                             "or --prior-dir)")
        user, key = owner(session), tuple(hashes)
        paths = self._paths(session, hashes)
        missing = [short(sha256) for sha256, path in zip(hashes, paths, strict=True)
                   if not path.is_file()]
        if missing:
            raise ValueError(f"prior {', '.join(missing)} is not in user {user!r}'s prior "
                             "store: upload it first (cfbci source --prior FILE does)")
        if (user, key) not in self._cache:
            self._cache[user, key] = read_prior(paths)
            while len(self._cache) > CACHED:
                del self._cache[next(iter(self._cache))]
        return self._cache[user, key]

    def check(self, session: str, config: dict[str, Any], reject: Reject) -> None:
        """Raise ``reject(problem)`` for a config whose ``prior`` the service cannot use:
        not in the store, no prior, a world in the plane, or another feature space than the
        config's (frame, classes, sampling, channels, feature settings; the size of the
        feature vectors is checked at the first epoch, `check_features`)."""
        if "prior" not in config:
            return
        if is_plane(config):
            raise reject(f"a prior starts the learner of the grid, line and pick-and-place "
                         f"worlds; this session's world is {config['world']!r}")
        try:
            check_space(self.prior(session, config["prior"]), config)
        except (ValueError, KeyError) as error:
            raise reject(f"prior refused: {error}") from None

    def _paths(self, session: str, hashes: Sequence[str]) -> list[Path]:
        """The files of a session's prior digests in its user's store."""
        assert self.directory is not None
        return [self.directory / owner(session) / f"{sha256}.mcap" for sha256 in hashes]

    def open(
        self,
        message: protocol.Message,
        config: dict[str, Any],
        record: Callable[[str, dict[str, Any]], SessionRecorder | None],
    ) -> tuple[Session, SessionRecorder | None]:
        """The session of an admitted config (`session.sessions.open_session`, ``config``
        resolved from ``message``'s) with its prior, and its recording: ``record(session,
        fields)`` (`cfbci.service.recordings.Recordings.open`), opened once the prior is
        read, which receives the prior's files (``/prior``).

        Raises
        ------
        Rejection
            When the prior is no longer in the store (deleted since the config was
            admitted) or cannot be read: no recording is opened.
        """
        sid = message.session
        fields = {"seq": message.seq, "t_ns": message.t_ns, **config}
        if "prior" not in config:
            return open_session(config), record(sid, fields)
        hashes, paths = config["prior"], self._paths(sid, config["prior"])
        gone = [short(h) for h, path in zip(hashes, paths, strict=True) if not path.is_file()]
        try:
            if gone:
                raise ValueError(f"prior {', '.join(gone)} is not in user {owner(sid)!r}'s "
                                 "prior store any more (deleted since the config was "
                                 "admitted)")
            prior = self.prior(sid, hashes)
            files = {h: path.read_bytes() for h, path in zip(hashes, paths, strict=True)}
        except (ValueError, OSError) as error:
            raise Rejection(f"prior refused: {error}: session not started", sid, message.seq,
                            message.t_ns) from None
        recorder = record(sid, fields)
        if recorder is not None:
            record_prior(recorder, files)
        return open_session(config, prior=prior), recorder


def check_space(prior: Prior, config: dict[str, Any]) -> None:
    """Raise a ``ValueError`` saying what differs when a config's feature space (frame,
    classes, and for raw epochs sampling, first sample time, channels and feature settings)
    is not the prior's; the size of the feature vectors is checked at the first epoch
    (`check_features`)."""
    frame = Frame(config_world(config), config["frame"])
    prior.check_space(recording_space(config, prior.space.n_features, frame.n_classes))


def check_features(core: Session, n_features: int, reject: Reject) -> None:
    """Raise ``reject(problem)`` when a session's prior has feature vectors of another
    size than its first epoch's (``n_features``)."""
    learner = getattr(core, "learner", None)
    if isinstance(learner, ReturningLearner) and learner.prior.space.n_features != n_features:
        raise reject(
            f"prior refused: its feature vectors have {learner.prior.space.n_features} values, "
            f"this session's {n_features}: session ended"
        )
