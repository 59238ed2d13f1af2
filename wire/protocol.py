"""Wire protocol of the real-time pipeline: key expressions, message encoding, validation.

Pure encode/decode, no transport: the replay source and the pipeline service put these
bytes on Eclipse Zenoh. A message is::

    [uint32 little-endian: header length H][H bytes: UTF-8 JSON object][float32 LE payload]

The header always holds ``v``, ``kind``, ``session``, ``seq`` and ``t_ns`` (`COMMON`),
then the fields of its kind (`SPECS`); a message with a payload also holds ``shape``,
``dtype`` and ``units`` (`PAYLOAD_FIELDS`). `SPECS` is the one table that both
`decode` checks against and ``docs/protocol.md`` prints (`markdown_table`).
No pickle, no code evaluation: JSON and raw float32 only.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from session.vocabulary import DISCRETE_ACTIONS, FRAMES, PLANE_FRAMES, PROBE, PUDDLE_MOVES, WORLDS

VERSION: int = 8
PREFIX: str = "cfbci"
MAX_BYTES: int = 16 * 2**20
NO_SESSION: str = "_"  # key segment of the service's events about unusable session ids
SIGNALS: tuple[str, ...] = ("epochs", "features")
EVENTS: tuple[str, ...] = (
    "error", "target_reached", "session_started", "session_ended", "session_rejected", "info",
    "session_pending", "prior_received", "prior_rejected", "session_paused", "session_resumed",
    "target_marked",
)
#: The operator's commands (a ``control`` message's ``command``).
COMMANDS: tuple[str, ...] = ("pause", "resume", "end", "target")

#: Every world's action names, in world order then action order (a move's ``action``).
ACTION_NAMES: tuple[str, ...] = (*DISCRETE_ACTIONS, PROBE, *PUDDLE_MOVES)
#: The worlds of a config: the discrete ones, then those of the plane.
CONFIG_WORLDS: tuple[str, ...] = (*WORLDS, *PLANE_FRAMES)

_NAME = r"[A-Za-z0-9_-]{1,64}"
#: A session id: one key chunk, or two (``<user>/<name>``: the session in its user's space).
_SESSION = re.compile(rf"{_NAME}(/{_NAME})?")
_ONE_CHUNK = re.compile(_NAME)
_SHA256 = re.compile(r"[0-9a-f]{64}")
_INT64 = 2**63


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and -_INT64 <= x < _INT64


def _is_count(x: Any) -> bool:
    return _is_int(x) and x >= 0


def _is_float(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _list_of(check: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda x: isinstance(x, list) and all(check(item) for item in x)


def _is_sha256(x: Any) -> bool:
    return isinstance(x, str) and _SHA256.fullmatch(x) is not None


def _is_point(x: Any) -> bool:
    return isinstance(x, list) and len(x) == 2 and all(_is_float(v) for v in x)


# Field types: name used in SPECS and in the documentation -> (description, check).
TYPES: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "int": ("an integer in the int64 range", _is_int),
    "count": ("an integer >= 0 in the int64 range", _is_count),
    "float": ("a finite number", _is_float),
    "count/null": (
        "an integer >= 0 in the int64 range, or null", lambda x: x is None or _is_count(x)
    ),
    "float/null": ("a finite number or null", lambda x: x is None or _is_float(x)),
    "bool": ("true or false", lambda x: isinstance(x, bool)),
    "str": ("a string", lambda x: isinstance(x, str)),
    "str[]": ("a list of strings", _list_of(lambda x: isinstance(x, str))),
    "float[]": ("a list of finite numbers", _list_of(_is_float)),
    "state": (
        "a state index (an integer >= 0), or a point [x, y] of two finite numbers (the "
        "worlds in the plane)",
        lambda x: _is_count(x) or _is_point(x),
    ),
    "point[]": ("a list of points [x, y] of two finite numbers", _list_of(_is_point)),
    "shape": (
        "a non-empty list of integers >= 1",
        lambda x: _list_of(lambda n: _is_count(n) and n >= 1)(x) and len(x) > 0,
    ),
    "object": ("a JSON object", lambda x: isinstance(x, dict)),
    "session": (
        "a session id: a name, or `<user>/<name>` (a session in its user's key space); a name "
        "or user is 1 to 64 characters of A-Z, a-z, 0-9, '_' and '-'",
        lambda x: isinstance(x, str) and _SESSION.fullmatch(x) is not None,
    ),
    "name": (
        "1 to 64 characters of A-Z, a-z, 0-9, '_' and '-'",
        lambda x: isinstance(x, str) and _ONE_CHUNK.fullmatch(x) is not None,
    ),
    "sha256": ("a SHA-256 digest: 64 characters of 0-9 and a-f", _is_sha256),
    "sha256[]": (
        "a non-empty list of distinct SHA-256 digests",
        lambda x: _list_of(_is_sha256)(x) and 0 < len(x) == len(set(x)),
    ),
}


@dataclass(frozen=True)
class Field:
    """One header field: its `TYPES` name, its meaning, and its allowed values."""

    type: str
    meaning: str
    choices: tuple[Any, ...] = ()


@dataclass(frozen=True)
class Payload:
    """The float32 payload of a kind.

    Attributes
    ----------
    units : str
        Value of the header's ``units`` (``"uV"`` microvolts, ``"1"`` dimensionless).
    dims : mapping of str or None to tuple of str
        Dimension names per value of the header's ``signal`` field (key None for a kind
        without one); the payload's ``shape`` has as many entries.
    meaning : str
    """

    units: str
    dims: Mapping[str | None, tuple[str, ...]]
    meaning: str


@dataclass(frozen=True)
class KindSpec:
    """A message kind: who sends it, its header fields, its payload (None: never one).

    ``conditional`` maps ``(field, value)`` to fields required when the header's ``field``
    has that value and forbidden otherwise (``("signal", "epochs")``: the raw epochs'
    description; ``("world", "grid")``: the grid's side). ``optional`` fields may be
    absent.
    """

    sender: str
    meaning: str
    fields: Mapping[str, Field]
    payload: Payload | None = None
    conditional: Mapping[tuple[str, str], Mapping[str, Field]] = field(default_factory=dict)
    optional: Mapping[str, Field] = field(default_factory=dict)

    def fields_for(self, header: Mapping[str, Any]) -> dict[str, Field]:
        """The kind's fields a header with these values must hold (conditional ones
        included where their condition holds), and the optional ones it holds."""
        fields = dict(self.fields) | {k: v for k, v in self.optional.items() if k in header}
        for (name, value), extra in self.conditional.items():
            if header.get(name) == value:
                fields |= extra
        return fields

    def condition_of(self, name: str) -> tuple[str, str] | None:
        """The ``(field, value)`` under which a conditional field is allowed (None: not
        a conditional field)."""
        return next((c for c, extra in self.conditional.items() if name in extra), None)


COMMON: dict[str, Field] = {
    "v": Field("int", "protocol version", (VERSION,)),
    "kind": Field("str", "message kind, the last segment of the key expression"),
    "session": Field(
        "session", "session id, the key expression's segments between `cfbci` and the kind"
    ),
    "seq": Field("count", "sequence number of the sender on this key expression, from 0"),
    "t_ns": Field("count", "sender's monotonic clock at publication, in nanoseconds"),
}
PAYLOAD_FIELDS: dict[str, Field] = {
    "shape": Field("shape", "payload dimensions, row-major (C order)"),
    "dtype": Field("str", "payload element type, little-endian IEEE 754", ("float32",)),
    "units": Field("str", "physical units of the payload values (fixed per kind)"),
}
_STEP = Field("count", "device action, 1 to `steps`")
_SIGNAL = Field("str", "raw EEG epochs or feature vectors", SIGNALS)
_CH_NAMES = Field("str[]", "EEG channel names, in payload row order")
_EPOCHS = ("signal", "epochs")

SPECS: dict[str, KindSpec] = {
    "config": KindSpec(
        "source",
        "First message of a session: everything the service needs to run it.",
        {
            "seed": Field("int", "session seed (method's random streams)"),
            "world": Field(
                "str", "the world the device acts in (see \"Worlds\")", CONFIG_WORLDS
            ),
            "frame": Field(
                "str", "interaction frame (the continuous world's: cardinal; the puddle "
                "world's: mixed)",
                (*FRAMES, *PLANE_FRAMES.values()),
            ),
            "steps": Field("count", "device actions (epochs) in the session"),
            "learner": Field(
                "object", "learner settings, as `LearnerConfig` field: value (the likelihood "
                "is `learner.likelihood`); the continuous world's: `ContinuousConfig` fields; "
                "the puddle world's: `PuddleConfig` fields"
            ),
            "dataset": Field("object", "description of the data the source answers from"),
            "signal": _SIGNAL,
        },
        optional={
            "service": Field(
                "name", "id of the service chosen to run the session (see \"Several "
                "services\"); absent: every service that hears the config runs it"
            ),
            "prior": Field(
                "sha256[]", "earlier recordings of the user the learner starts from, by the "
                "SHA-256 of their files, each in the user's prior store (see \"Priors\"; "
                "grid, line and pick-and-place worlds); absent: none"
            ),
        },
        conditional={
            ("world", "grid"): {
                "grid": Field("count", "side of the grid; cells are `row * grid + col`"),
            },
            _EPOCHS: {
                "sfreq": Field("float", "sampling frequency, Hz"),
                "tmin": Field("float", "time of the first sample relative to action onset, s"),
                "ch_names": _CH_NAMES,
            },
        },
    ),
    "epoch": KindSpec(
        "source",
        "The user's signal answering the move of the same step.",
        {"step": _STEP, "signal": _SIGNAL},
        Payload(
            "uV",
            {"epochs": ("n_channels", "n_times"), "features": ("n_features",)},
            "raw EEG epoch or ErrP feature vector, microvolts",
        ),
        conditional={_EPOCHS: {"ch_names": _CH_NAMES}},
        optional={
            "reset": Field(
                "bool", "puddle world only: true when the move's `to_state` is in the user's "
                "goal cell, so the environment restarts the agent (the service draws the "
                "restart state before the next move; the learner never reads this field); "
                "absent: false"
            ),
        },
    ),
    "truth": KindSpec(
        "source",
        "Ground truth of an epoch, for recording and evaluation; the service never reads it.",
        {
            "step": _STEP,
            "target": Field(
                "state", "the user's target task when the epoch was produced (the continuous "
                "world's: the goal point; the puddle world's: the task index)"
            ),
            "label": Field(
                "count", "class of the epoch (feedback: 0 correct, 1 error; guidance: the "
                "guidance action's class; cardinal: the direction; mixed: 0 correct, "
                "1 incorrect, 2-5 north, south, east, west)"
            ),
        },
    ),
    "ready": KindSpec(
        "source",
        "The source's answer to its session's `session_pending` event: it listens to the "
        "session's events (a session starts only then; see \"Starting a session\").",
        {
            "config_t_ns": Field("count", "the `t_ns` of the config it confirms"),
            "challenge": Field("str", "the `challenge` of the `session_pending` event"),
        },
    ),
    "prior": KindSpec(
        "source",
        "A chunk of a prior's upload into the user's prior store (see \"Priors\"); "
        "answered by a `prior_received` or `prior_rejected` event.",
        {
            "sha256": Field("sha256", "SHA-256 of the whole file"),
            "size": Field("count", "the whole file's size, bytes"),
            "offset": Field("count", "where the chunk's bytes start in the file"),
            "data": Field(
                "str", "the chunk's bytes, base64 (RFC 4648); empty: asks how many bytes "
                "of the file the service holds"
            ),
        },
    ),
    "move": KindSpec(
        "service",
        "The device's next action.",
        {
            "step": _STEP,
            "from_state": Field(
                "state", "state before the action (continuous: the probe; puddle: the agent's "
                "point)"
            ),
            "action": Field("str", "the action, one of its world's", ACTION_NAMES),
            "to_state": Field(
                "state", "state after the action (continuous: the probe; puddle: the point "
                "the move reached, drawn by the service)"
            ),
            "target_reached": Field(
                "bool", "the action is the world's declaration action performed while confident"
            ),
        },
    ),
    "state": KindSpec(
        "service",
        "The learner's beliefs after its latest epoch, which chose the accompanying move.",
        {
            "best_task": Field("count", "most likely task"),
            "confident": Field(
                "bool",
                "best task's confidence exceeds what a target needs (beta; more before the "
                "first target on a short history)",
            ),
            "n_signals": Field("count", "epochs the learner has observed"),
            "class_counts": Field(
                "float[]", "signals per class under the best task's labels (may be weighted)"
            ),
            "balanced_accuracy": Field(
                "float/null", "best task's cross-validated balanced accuracy; null if unknown"
            ),
            "points": Field(
                "point[]", "the continuous world's particles, in payload order (tasks are "
                "particles); empty in the other worlds"
            ),
        },
        Payload("1", {None: ("n_tasks",)}, "confidence of every task, in [0, 1]"),
    ),
    "event": KindSpec(
        "service",
        "Something happened on the session.",
        {
            "event": Field("str", "what happened", EVENTS),
            "message": Field("str", "human-readable explanation"),
            "config_t_ns": Field(
                "count/null",
                "`session_pending`, `session_started`, `session_rejected`: the `t_ns` of the "
                "config they answer (the running session's for a rejection after the start); "
                "null otherwise",
            ),
        },
        optional={
            "challenge": Field(
                "str", "`session_pending` only: what the source's `ready` message repeats"
            ),
            "prior": Field(
                "sha256", "`prior_received`, `prior_rejected`: the prior uploaded"
            ),
            "received": Field(
                "count", "`prior_received` only: bytes of the prior the service holds, "
                "from the start (its size: stored)"
            ),
            "step": Field(
                "count", "`session_paused`, `session_resumed`, `target_marked`, and "
                "`session_ended` when the operator ended the session: the last move's step "
                "then (see \"Operator controls\")"
            ),
            "target": Field("state", "`target_marked` only: the target the operator marked"),
        },
    ),
    "control": KindSpec(
        "operator",
        "The operator's command on a running session (see \"Operator controls\"); answered "
        "by an `event` (`session_paused`, `session_resumed`, `session_ended`, "
        "`target_marked`) or an `error`.",
        {"command": Field("str", "what the operator does", COMMANDS)},
        conditional={
            ("command", "target"): {
                "target": Field(
                    "state", "the target the subject chose, a task of the session's world "
                    "(the continuous world's: its goal point): the session's truth from the "
                    "next epoch on; the learner never reads it"
                ),
            },
        },
    ),
}
KINDS: tuple[str, ...] = tuple(SPECS)


def markdown_table() -> str:
    """The field types and every kind's header fields as Markdown (``docs/protocol.md``)."""

    def table(fields: Mapping[str, Field], note: str = "") -> list[str]:
        rows = ["| field | type | meaning |", "|---|---|---|"]
        for name, spec in fields.items():
            choices = " in " + ", ".join(f"`{_show(c)}`" for c in spec.choices)
            rows.append(
                f"| `{name}` | `{spec.type}`{choices if spec.choices else ''} "
                f"| {spec.meaning}{note} |"
            )
        return rows

    lines = ["### Field types", "", "| type | JSON value |", "|---|---|"]
    lines += [f"| `{name}` | {description} |" for name, (description, _) in TYPES.items()]
    lines += ["", "### Every message", "", *table(COMMON)]
    lines += ["", "### Every message with a payload", "", *table(PAYLOAD_FIELDS)]
    for kind, spec in SPECS.items():
        lines += ["", f"### `{kind}`: {PREFIX}/<session>/{kind}, sent by the {spec.sender}", ""]
        lines += [spec.meaning, ""]
        lines += table(spec.fields)
        for (name, value), extra in spec.conditional.items():
            lines += table(extra, f" (only when `{name}` is {_show(value)})")[2:]
        lines += table(spec.optional, " (optional)")[2:]
        if spec.payload is None:
            lines += ["", "Payload: none."]
            continue
        shapes = " or ".join(
            f"`[{', '.join(dims)}]`" + (f' when `signal` is "{signal}"' if signal else "")
            for signal, dims in spec.payload.dims.items()
        )
        lines += [
            "",
            f'Payload: float32, units `"{spec.payload.units}"`, shape {shapes}: '
            f"{spec.payload.meaning}.",
        ]
    return "\n".join(lines) + "\n"


class ProtocolError(ValueError):
    """A message or key expression that breaks the protocol.

    Attributes
    ----------
    problem : str
        What is wrong.
    session : str or None
        A valid session id the problem belongs to (where to report it), if known.
    seq : int or None
        The offending message's sequence number, if known.
    """

    def __init__(self, problem: str, session: str | None = None, seq: int | None = None):
        self.problem, self.session, self.seq = problem, session, seq
        where = [f"session {session!r}"] if session is not None else []
        where += [f"seq {seq}"] if seq is not None else []
        super().__init__(f"{' '.join(where)}: {problem}" if where else problem)


@dataclass(eq=False)
class Message:
    """One protocol message.

    Parameters
    ----------
    kind : str
        One of `KINDS`.
    session : str
        Session id (see `key`).
    seq : int
        Sender's sequence number on this key expression, >= 0.
    t_ns : int
        Sender's monotonic clock at publication (``time.monotonic_ns()``), nanoseconds.
    fields : dict
        The kind's header fields (`SPECS`), e.g. ``{"step": 3, "signal": "features"}``.
    payload : ndarray or None
        float32 values: epoch ``(n_channels, n_times)`` or ``(n_features,)`` in microvolts;
        state ``(n_tasks,)`` confidences. None for kinds without a payload.
    """

    kind: str
    session: str
    seq: int
    t_ns: int
    fields: dict[str, Any] = field(default_factory=dict)
    payload: np.ndarray | None = None


def _show(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, str | int | float | bool | None) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _check_value(name: str, spec: Field, value: Any, context: dict[str, Any]) -> None:
    description, check = TYPES[spec.type]
    if not check(value):
        raise ProtocolError(f"field {name!r} must be {description}; got {_show(value)}", **context)
    if spec.choices and value not in spec.choices:
        choices = ", ".join(_show(c) for c in spec.choices)
        raise ProtocolError(
            f"field {name!r} must be one of {choices}; got {_show(value)}", **context
        )


def _check_reserved(session: str, kind: str, context: dict[str, Any]) -> None:
    if session == NO_SESSION and kind != "event":
        raise ProtocolError(
            f"session id {NO_SESSION!r} is reserved for the service's events about unusable "
            "session ids",
            **context,
        )


def key(session: str, kind: str) -> str:
    """The key expression ``cfbci/<session>/<kind>``.

    Parameters
    ----------
    session : str
        A name (1 to 64 characters of ``[A-Za-z0-9_-]``) or ``<user>/<name>``; ``"_"``
        (`NO_SESSION`) only for ``kind="event"``.
    kind : str
        One of `KINDS`.

    Raises
    ------
    ProtocolError
        If the kind is unknown or the session id is invalid.
    """
    if kind not in SPECS:
        raise ProtocolError(f"unknown kind {_show(kind)}; expected one of {', '.join(KINDS)}")
    _check_value("session", COMMON["session"], session, {})
    _check_reserved(session, kind, {})
    return f"{PREFIX}/{session}/{kind}"


def user_of(session: str) -> str | None:
    """The user of a session id ``<user>/<name>``; None for a one-chunk id."""
    user, sep, _ = session.partition("/")
    return user if sep else None


def split_key(key_expr: str) -> tuple[str, str]:
    """The ``(session, kind)`` of a key expression built by `key`.

    Raises
    ------
    ProtocolError
        If ``key_expr`` is not ``cfbci/<session>/<kind>`` with a valid session and kind.
    """
    parts = key_expr.split("/")
    if len(parts) not in (3, 4) or parts[0] != PREFIX:
        raise ProtocolError(f"key expression {key_expr!r} is not {PREFIX}/<session>/<kind>")
    session, kind = "/".join(parts[1:-1]), parts[-1]
    key(session, kind)
    return session, kind


def _context(session: Any, seq: Any) -> dict[str, Any]:
    """Where to report a problem: the session and seq, when they are usable."""
    return {
        "session": session if TYPES["session"][1](session) else None,
        "seq": seq if _is_count(seq) else None,
    }


def _json_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    names = [name for name, _ in pairs]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"field(s) {', '.join(map(repr, repeated))} appear more than once")
    return dict(pairs)


def _json_constant(name: str) -> None:
    raise ValueError(f"{name} is not a JSON number")


def _split(data: bytes, max_bytes: int, context: dict[str, Any]) -> tuple[Any, bytes]:
    """The parsed JSON header and the payload bytes of a message."""
    if len(data) > max_bytes:
        raise ProtocolError(
            f"message is {len(data)} bytes, more than the limit of {max_bytes}", **context
        )
    if len(data) < 4:
        raise ProtocolError(
            f"message is {len(data)} bytes: empty or truncated (the header length alone is 4)",
            **context,
        )
    size = int.from_bytes(data[:4], "little")
    if size > len(data) - 4:
        raise ProtocolError(
            f"header length {size} exceeds the {len(data) - 4} bytes that follow: "
            "truncated message",
            **context,
        )
    try:
        text = data[4 : 4 + size].decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"header is not UTF-8: {exc}", **context) from None
    try:
        header = json.loads(text, object_pairs_hook=_json_object, parse_constant=_json_constant)
    except ValueError as exc:
        raise ProtocolError(f"header is not valid JSON: {exc}", **context) from None
    except RecursionError:
        raise ProtocolError("header is not valid JSON: nested too deeply", **context) from None
    if not isinstance(header, dict):
        raise ProtocolError(f"header must be a JSON object; got {type(header).__name__}", **context)
    return header, data[4 + size :]


def _check_fields(
    header: dict[str, Any], fields: Mapping[str, Field], kind: str, context: dict[str, Any]
) -> None:
    missing = [name for name in fields if name not in header]
    if missing:
        raise ProtocolError(
            f"kind {kind!r} misses field(s) {', '.join(map(repr, missing))}", **context
        )
    for name, spec in fields.items():
        _check_value(name, spec, header[name], context)


def _validate(
    header: dict[str, Any], body: bytes, context: dict[str, Any], key_expr: str | None
) -> Message:
    """Check a parsed header and its payload bytes against `SPECS`."""
    for name, value in _context(header.get("session"), header.get("seq")).items():
        context[name] = context[name] if context[name] is not None else value
    if "v" not in header:
        raise ProtocolError("missing field 'v' (protocol version)", **context)
    if not _is_int(header["v"]) or header["v"] != VERSION:
        raise ProtocolError(
            f"unknown protocol version {_show(header['v'])}; this implementation speaks "
            f"version {VERSION}",
            **context,
        )
    kind = header.get("kind")
    if not isinstance(kind, str) or kind not in SPECS:
        raise ProtocolError(
            f"unknown kind {_show(kind)}; expected one of {', '.join(KINDS)}", **context
        )
    spec = SPECS[kind]
    if spec.payload is None and (body or PAYLOAD_FIELDS.keys() & header.keys()):
        raise ProtocolError(
            f"kind {kind!r} carries no payload; got {len(body)} payload bytes and header "
            f"fields {sorted(PAYLOAD_FIELDS.keys() & header.keys())}",
            **context,
        )
    if spec.payload is not None and not body:
        raise ProtocolError(f"kind {kind!r} requires a float32 payload; got none", **context)
    fields = COMMON | spec.fields | (PAYLOAD_FIELDS if spec.payload is not None else {})
    _check_fields(header, fields, kind, context)
    # The conditions' fields are valid by now: the conditional fields due are known.
    conditional = {k: v for k, v in spec.fields_for(header).items() if k not in spec.fields}
    _check_fields(header, conditional, kind, context)
    fields |= conditional
    unknown = [name for name in header if name not in fields]
    if unknown:
        conditions = [spec.condition_of(name) for name in unknown]
        allowed = "".join(
            f"; {name!r} is allowed only when {c[0]!r} is {_show(c[1])}"
            for name, c in zip(unknown, conditions, strict=True)
            if c is not None
        )
        raise ProtocolError(
            f"unknown header field(s) {', '.join(map(repr, unknown))} for kind {kind!r}"
            f"{allowed}",
            **context,
        )
    _check_reserved(header["session"], kind, context)
    if key_expr is not None and key(header["session"], kind) != key_expr:
        raise ProtocolError(
            f"header kind {kind!r} and session {header['session']!r} do not match key "
            f"expression {key_expr!r}",
            **context,
        )
    payload = None
    if spec.payload is not None:
        payload = _read_payload(header, body, spec.payload, context)
    own = {name: header[name] for name in header if name in spec.fields_for(header)}
    return Message(kind, header["session"], header["seq"], header["t_ns"], own, payload)


def _read_payload(
    header: dict[str, Any], body: bytes, spec: Payload, context: dict[str, Any]
) -> np.ndarray:
    shape, dims = header["shape"], spec.dims[header.get("signal")]
    if header["units"] != spec.units:
        raise ProtocolError(
            f"field 'units' must be {spec.units!r} for kind {header['kind']!r}; got "
            f"{_show(header['units'])}",
            **context,
        )
    if len(shape) != len(dims):
        raise ProtocolError(
            f"shape {shape} must have {len(dims)} dimension(s) ({', '.join(dims)})", **context
        )
    if math.prod(shape) * 4 != len(body):
        raise ProtocolError(
            f"shape {shape} of float32 needs {math.prod(shape) * 4} payload bytes; got {len(body)}",
            **context,
        )
    if "ch_names" in header and len(header["ch_names"]) != shape[0]:
        raise ProtocolError(
            f"{len(header['ch_names'])} ch_names for {shape[0]} payload rows (n_channels)",
            **context,
        )
    payload = np.frombuffer(body, dtype="<f4").reshape(shape).copy()
    finite = np.isfinite(payload)
    if not finite.all():
        first = tuple(np.argwhere(~finite)[0].tolist())
        raise ProtocolError(
            f"payload holds NaN or infinite values (first at index {first})", **context
        )
    return payload


def decode(data: bytes, *, max_bytes: int = MAX_BYTES, key_expr: str | None = None) -> Message:
    """Parse and validate one message.

    Parameters
    ----------
    data : bytes-like
        ``[uint32 LE header length][UTF-8 JSON header][float32 LE payload]``.
    max_bytes : int, default 16 MiB
        Longer messages are rejected before parsing.
    key_expr : str, optional
        The key expression the message arrived on; its kind and session must match the
        header's, and its session is where a problem is reported if the header is unusable.

    Returns
    -------
    Message
        ``fields`` holds the kind's fields (no common or payload-description field);
        ``payload`` is a writable float32 array of the header's ``shape``, or None.

    Raises
    ------
    ProtocolError
        Naming the problem; its ``session`` and ``seq`` say where it belongs when known.
    """
    context: dict[str, Any] = {"session": None, "seq": None}
    if key_expr is not None:
        context["session"] = split_key(key_expr)[0]
    header, body = _split(bytes(data), max_bytes, context)
    return _validate(header, body, context, key_expr)


def encode(message: Message) -> bytes:
    """Serialise a message, after checking it against `SPECS` as `decode` does.

    The payload is cast to little-endian float32 (bit-exact for float32 input); ``shape``,
    ``dtype`` and ``units`` are filled in from it and the kind.

    Raises
    ------
    ProtocolError
        If the message would be rejected by `decode`.
    """
    context = _context(message.session, message.seq)
    own = sorted((COMMON.keys() | PAYLOAD_FIELDS.keys()) & message.fields.keys())
    if own:
        raise ProtocolError(f"fields may not set the header's own field(s) {own}", **context)
    header = {
        "v": VERSION,
        "kind": message.kind,
        "session": message.session,
        "seq": message.seq,
        "t_ns": message.t_ns,
        **message.fields,
    }
    body = b""
    if message.payload is not None:
        try:
            payload = np.ascontiguousarray(message.payload, dtype="<f4")
        except (TypeError, ValueError) as exc:
            raise ProtocolError(f"payload is not numeric: {exc}", **context) from None
        spec = SPECS.get(message.kind)
        units = spec.payload.units if spec is not None and spec.payload is not None else None
        header |= {"shape": list(payload.shape), "dtype": "float32", "units": units}
        body = payload.tobytes()
    try:
        text = json.dumps(
            header, ensure_ascii=False, allow_nan=False, separators=(",", ":")
        ).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"header is not JSON-serialisable: {exc}", **context) from None
    data = len(text).to_bytes(4, "little") + text + body
    _validate(*_split(data, len(data), context), context, None)
    return data


class SequenceTracker:
    """Checks the sequence numbers of one sender on one key expression (session, kind).

    Attributes
    ----------
    expected : int
        The next sequence number in order.
    lost : int
        Messages skipped by gaps that have not arrived since.

    Examples
    --------
    >>> tracker = SequenceTracker()
    >>> [tracker.check(seq) for seq in (0, 1, 4, 2, 2)]  # doctest: +NORMALIZE_WHITESPACE
    [None, None, 'gap: expected 2, got 4 (2 messages lost)',
     'out of order: seq 2 arrived after 4 (it had been counted lost)',
     'duplicate: seq 2 was already received (expected 5)']
    """

    def __init__(self) -> None:
        self.expected = 0
        self._missing: list[range] = []

    @property
    def lost(self) -> int:
        """Messages skipped by gaps that have not arrived since."""
        return sum(len(missing) for missing in self._missing)

    def check(self, seq: int) -> str | None:
        """None if ``seq`` is the expected one, else what is wrong with it.

        A gap counts the skipped messages as lost and moves on; a duplicate or a late
        message leaves `expected` unchanged (a late one is no longer lost).
        """
        if not _is_count(seq):
            raise ValueError(f"seq must be {TYPES['count'][0]}; got {seq!r}")
        expected = self.expected
        if seq == expected:
            self.expected += 1
            return None
        if seq > expected:
            self._missing.append(range(expected, seq))
            self.expected = seq + 1
            lost = seq - expected
            return f"gap: expected {expected}, got {seq} ({lost} message{'s' * (lost > 1)} lost)"
        for i, missing in enumerate(self._missing):
            if seq in missing:
                parts = (range(missing.start, seq), range(seq + 1, missing.stop))
                self._missing[i : i + 1] = [part for part in parts if part]
                return (
                    f"out of order: seq {seq} arrived after {expected - 1} "
                    "(it had been counted lost)"
                )
        return f"duplicate: seq {seq} was already received (expected {expected})"
