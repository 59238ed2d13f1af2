"""The wire protocol: round trips of every kind, every rejected message, sequence checks."""

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wire.protocol import (
    COMMON,
    KINDS,
    MAX_BYTES,
    SPECS,
    TYPES,
    VERSION,
    Message,
    ProtocolError,
    SequenceTracker,
    decode,
    encode,
    key,
    markdown_table,
    split_key,
)

DOCS = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"
CH_NAMES = ["Fz", "FCz", "Cz"]
# Bit patterns a lossy path would change: -0.0, the smallest subnormal, float32 extremes.
SPECIAL = np.array([-0.0, 1e-45, 3.4028235e38, -1.1754944e-38, 1 / 3, 12.5], dtype=np.float32)


def rng_floats(*shape: int) -> np.ndarray:
    return np.random.default_rng(0).normal(0.0, 20.0, size=shape).astype(np.float32)


EXAMPLES: dict[str, Message] = {
    "config_epochs": Message(
        "config", "s-01", 0, 17,
        {
            "seed": -3, "world": "grid", "grid": 5, "frame": "feedback", "steps": 500,
            "learner": {"eps": 0.1, "decoder": "lda"},
            "dataset": {"name": "synthetic", "accuracy": 0.78},
            "signal": "epochs", "sfreq": 256.0, "tmin": -0.2, "ch_names": CH_NAMES,
        },
    ),
    "config_features": Message(
        "config", "s_02", 0, 0,
        {
            "seed": 7, "world": "pick-and-place", "frame": "guidance", "steps": 10, "learner": {},
            "dataset": {"path": "move_finger.mat"}, "signal": "features",
        },
    ),
    "epoch_epochs": Message(
        "epoch", "s-01", 4, 2**62 + 12345,
        {"step": 5, "signal": "epochs", "ch_names": CH_NAMES},
        np.concatenate([SPECIAL, rng_floats(3 * 308 - SPECIAL.size)]).reshape(3, 308),
    ),
    "epoch_features": Message(
        "epoch", "s-01", 0, 1, {"step": 1, "signal": "features"}, rng_floats(57)
    ),
    "truth": Message("truth", "s-01", 9, 55, {"step": 10, "target": 24, "label": 1}),
    "ready": Message("ready", "lab/s-01", 0, 18, {"config_t_ns": 17, "challenge": "9f3a"}),
    "event_pending": Message(  # version 7: the challenge a source answers with `ready`
        "event", "lab/s-01", 0, 2,
        {"event": "session_pending", "message": "waits for its source",
         "config_t_ns": 17, "challenge": "9f3a"},
    ),
    "move": Message(
        "move", "s-01", 3, 999,
        {"step": 4, "from_state": 6, "action": "goal", "to_state": 6, "target_reached": True},
    ),
    "state": Message(
        "state", "s-01", 2, 1000,
        {
            "best_task": 6, "confident": False, "n_signals": 12,
            "class_counts": [9.5, 2.5], "balanced_accuracy": 0.71, "points": [],
        },
        np.linspace(0, 1, 25, dtype=np.float32),
    ),
    "state_first": Message(
        "state", "s-01", 0, 5,
        {
            "best_task": 0, "confident": False, "n_signals": 0,
            "class_counts": [], "balanced_accuracy": None, "points": [],
        },
        np.full(25, 0.5, dtype=np.float32),
    ),
    "move_probe": Message(  # the continuous world (version 4)
        "move", "s-01", 5, 1001,
        {"step": 6, "from_state": [0.25, 0.5], "action": "probe", "to_state": [0.25, 0.5],
         "target_reached": False},
    ),
    "state_particles": Message(
        "state", "s-01", 5, 1002,
        {
            "best_task": 1, "confident": False, "n_signals": 13, "class_counts": [],
            "balanced_accuracy": None, "points": [[0.1, 0.2], [0.3, 0.4], [1.0, 0.0]],
        },
        np.array([0.2, 0.7, 0.4], dtype=np.float32),
    ),
    "truth_goal": Message("truth", "s-01", 12, 56, {"step": 13, "target": [0.3, 0.4],
                                                    "label": 2}),
    "move_puddle": Message(  # the puddle world (version 6)
        "move", "s-01", 6, 1003,
        {"step": 7, "from_state": [0.25, 0.5], "action": "north", "to_state": [0.25, 0.61],
         "target_reached": False},
    ),
    "epoch_reset": Message(
        "epoch", "s-01", 6, 1004, {"step": 7, "signal": "features", "reset": True},
        np.zeros(20, dtype=np.float32),
    ),
    "event": Message(
        "event", "s-01", 1, 3,
        {"event": "session_started", "message": "grid 5, 500 steps", "config_t_ns": 1},
    ),
    "config_prior": Message(  # version 8: a prior named by its files' SHA-256
        "config", "lab/s-03", 0, 19,
        {
            "seed": 1, "world": "line", "frame": "feedback", "steps": 10, "learner": {},
            "dataset": {}, "signal": "features", "prior": ["0f" * 32, "a1" * 32],
        },
    ),
    "prior": Message(
        "prior", "lab/s-03", 2, 20,
        {"sha256": "0f" * 32, "size": 9, "offset": 6, "data": "AAEC"},
    ),
    "event_prior": Message(
        "event", "lab/s-03", 1, 21,
        {"event": "prior_received", "message": "9 of 9 bytes", "config_t_ns": None,
         "prior": "0f" * 32, "received": 9},
    ),
    "control_pause": Message(  # version 8: the operator's commands
        "control", "lab/s-03", 0, 22, {"command": "pause"},
    ),
    "control_target": Message(
        "control", "lab/s-03", 1, 23, {"command": "target", "target": 7},
    ),
    "event_target_marked": Message(
        "event", "lab/s-03", 2, 24,
        {"event": "target_marked", "message": "target 7 from step 5", "config_t_ns": None,
         "step": 5, "target": 7},
    ),
    "event_unusable_session": Message(
        "event", "_", 0, 3,
        {"event": "error", "message": "session id 'a b' is invalid — é", "config_t_ns": None},
    ),
}  # fmt: skip


def split(data: bytes) -> tuple[dict[str, Any], bytes]:
    """A message's header (as a dict) and payload bytes, read by hand."""
    size = int.from_bytes(data[:4], "little")
    return json.loads(data[4 : 4 + size]), data[4 + size :]


def frame(header: dict[str, Any] | bytes, body: bytes = b"") -> bytes:
    text = header if isinstance(header, bytes) else json.dumps(header).encode()
    return len(text).to_bytes(4, "little") + text + body


def tampered(name: str, body: bytes | None = None, drop: tuple[str, ...] = (), **changes) -> bytes:
    """An example message with header fields dropped or changed, and maybe another payload."""
    header, payload = split(encode(EXAMPLES[name]))
    header = {k: v for k, v in header.items() if k not in drop} | changes
    return frame(header, payload if body is None else body)


def rejects(data: bytes, problem: str, **kwargs: Any) -> ProtocolError:
    with pytest.raises(ProtocolError, match=problem) as caught:
        decode(data, **kwargs)
    assert isinstance(caught.value, ValueError)
    return caught.value


# Round trips ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", EXAMPLES)
def test_every_kind_round_trips_bit_exactly(name):
    message = EXAMPLES[name]
    back = decode(encode(message), key_expr=key(message.session, message.kind))
    assert (back.kind, back.session, back.seq, back.t_ns) == (
        message.kind, message.session, message.seq, message.t_ns,
    )  # fmt: skip
    assert back.fields == message.fields
    if message.payload is None:
        assert back.payload is None
    else:
        assert back.payload.dtype == np.float32 and back.payload.shape == message.payload.shape
        assert back.payload.tobytes() == message.payload.astype("<f4").tobytes()
        assert back.payload.flags.writeable
        back.payload[...] = 0  # a copy, not a view of the received bytes


def test_the_examples_cover_every_kind():
    assert {message.kind for message in EXAMPLES.values()} == set(KINDS)


def test_byte_layout_is_length_json_header_then_little_endian_float32():
    data = encode(EXAMPLES["epoch_features"])
    header, body = split(data)
    assert header == {
        "v": VERSION, "kind": "epoch", "session": "s-01", "seq": 0, "t_ns": 1,
        "step": 1, "signal": "features", "shape": [57], "dtype": "float32", "units": "uV",
    }  # fmt: skip
    assert body == EXAMPLES["epoch_features"].payload.astype("<f4").tobytes()
    assert len(data) == 4 + int.from_bytes(data[:4], "little") + 57 * 4
    assert split(encode(EXAMPLES["state"]))[0]["units"] == "1"


def test_encode_casts_a_float64_payload_to_float32():
    message = Message("epoch", "s", 0, 0, {"step": 1, "signal": "features"}, np.arange(4.0))
    assert decode(encode(message)).payload.dtype == np.float32


def test_docs_print_the_specification_table():
    assert markdown_table() in DOCS.read_text(encoding="utf-8")


# Rejected messages ---------------------------------------------------------------------

BAD_VALUES = {
    "int": "1", "count": -1, "count/null": -2, "float": "250", "float/null": "x", "bool": 1,
    "str": 3,
    "str[]": ["Fz", 1], "float[]": [1.0, "2"], "object": [], "shape": [0], "session": "a b",
    "name": "a/b", "state": [0.5, 0.5, 0.5], "point[]": [[0.1, 0.2], [0.3]],
    "sha256": "0F" * 32, "sha256[]": ["0f" * 32, "0f" * 32],
}  # fmt: skip


def test_every_type_has_a_bad_value():
    assert BAD_VALUES.keys() == TYPES.keys()


def framing_cases() -> list[tuple[bytes, str]]:
    header = split(encode(EXAMPLES["move"]))[0]
    return [
        (b"", "0 bytes: empty or truncated"),
        (b"\x05\x00\x00", "3 bytes: empty or truncated"),
        (frame(header)[:-1], "header length .* exceeds .*: truncated"),
        (frame(b'{"v": "\xff"}'), "header is not UTF-8"),
        (frame(b'{"v": 1,'), "header is not valid JSON"),
        (frame(b""), "header is not valid JSON"),
        (frame(b'{"v": NaN}'), "header is not valid JSON: NaN is not a JSON number"),
        (frame(b'{"v": 1, "v": 1}'), "header is not valid JSON: field.*'v'.* more than once"),
        (frame(b"[1, 2]"), "header must be a JSON object; got list"),
        (frame(b"[" * 100_000), "header is not valid JSON"),
        (frame({k: v for k, v in header.items() if k != "v"}), "missing field 'v'"),
        (frame(header | {"v": 2}), f"unknown protocol version 2; .* speaks version {VERSION}"),
        (frame(header | {"v": True}), "unknown protocol version true"),
        (frame(header | {"kind": "moves"}), 'unknown kind "moves"'),
        (frame(header | {"kind": ["move"]}), "unknown kind"),
    ]


@pytest.mark.parametrize(("data", "problem"), framing_cases())
def test_broken_framing_header_version_and_kind_are_rejected(data, problem):
    rejects(data, problem)


def test_oversized_messages_are_rejected_before_parsing():
    data = encode(EXAMPLES["epoch_epochs"])
    rejects(data, f"{len(data)} bytes, more than the limit of 1000", max_bytes=1000)
    rejects(b"x" * (MAX_BYTES + 1), "more than the limit")


REQUIRED = [
    (name, field)
    for name, message in EXAMPLES.items()
    for field in [*COMMON, *message.fields]
    if field not in ("v", "kind") and field not in SPECS[message.kind].optional
]


def test_the_puddle_epochs_optional_reset_is_a_bool_or_absent():
    """``reset`` (version 6) may be left out; present, it must be true or false."""
    without = decode(tampered("epoch_reset", drop=("reset",)))
    assert "reset" not in without.fields
    assert decode(encode(EXAMPLES["epoch_reset"])).fields["reset"] is True
    for value in ("yes", 1, None):
        rejects(tampered("epoch_reset", reset=value), "field 'reset' must be true or false")


@pytest.mark.parametrize(("name", "field"), REQUIRED)
def test_a_missing_required_field_is_named(name, field):
    rejects(tampered(name, drop=(field,)), f"misses field\\(s\\) '{field}'")


@pytest.mark.parametrize(("name", "field"), REQUIRED)
def test_a_wrongly_typed_field_is_named(name, field):
    spec = COMMON | SPECS[EXAMPLES[name].kind].fields_for(EXAMPLES[name].fields)
    value = BAD_VALUES[spec[field].type]
    rejects(tampered(name, **{field: value}), f"field '{field}' must be")


@pytest.mark.parametrize(
    ("name", "field", "value"),
    [
        ("move", "action", "jump"),
        ("event", "event", "warning"),
        ("config_epochs", "frame", "FEEDBACK"),
        ("config_epochs", "world", "maze"),
        ("epoch_epochs", "signal", "raw"),
    ],
)
def test_a_value_outside_its_choices_is_named(name, field, value):
    rejects(tampered(name, **{field: value}), f"field '{field}' must be one of .*got \"{value}\"")


def overflowing_sfreq() -> bytes:
    """A JSON number too large for a float64, which parsers read as infinity."""
    header = split(encode(EXAMPLES["config_epochs"]))[0] | {"sfreq": 12345.5}
    return frame(json.dumps(header).replace("12345.5", "1e999").encode())


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        (tampered("move", extra=1), "unknown header field\\(s\\) 'extra' for kind 'move'"),
        (tampered("epoch_features", ch_names=["Cz"]), "unknown header field\\(s\\) 'ch_names'"),
        (tampered("config_features", sfreq=256.0), "unknown header field\\(s\\) 'sfreq'"),
        (
            tampered("config_features", grid=5),
            "unknown header field\\(s\\) 'grid' for kind 'config'; 'grid' is allowed only "
            "when 'world' is \"grid\"",
        ),
        (overflowing_sfreq(), "field 'sfreq' must be a finite number"),
        (tampered("move", t_ns=2**63), "field 't_ns' must be .*int64"),
        (tampered("move", seq=-1), "field 'seq' must be an integer >= 0"),
        (tampered("move", seq=1.0), "field 'seq' must be an integer"),
        (tampered("move", step=True), "field 'step' must be an integer"),
        (tampered("state", balanced_accuracy=True), "field 'balanced_accuracy' must be"),
    ],
)
def test_unknown_fields_and_out_of_range_values_are_rejected(data, problem):
    rejects(data, problem)


@pytest.mark.parametrize(
    "session", ["", "a b", "x" * 65, "café", "a/b/c", "/a", "a/", "*", "s\n", 12, None]
)
def test_an_invalid_session_id_is_rejected_without_a_session_to_report_to(session):
    error = rejects(tampered("move", session=session), "field 'session' must be a session id")
    assert error.session is None and error.seq == 3


def test_the_unusable_session_id_is_reserved_for_events():
    error = rejects(tampered("epoch_features", session="_"), "'_' is reserved")
    assert error.session == "_"  # the service reports it on cfbci/_/event


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        (tampered("epoch_features", body=b"\x00" * 20), "needs 228 payload bytes; got 20"),
        (tampered("epoch_epochs", shape=[3, 307]), "needs 3684 payload bytes; got 3696"),
        (tampered("epoch_epochs", shape=[924]), "must have 2 dimension\\(s\\) \\(n_channels, n_t"),
        (tampered("epoch_features", shape=[3, 19]), "must have 1 dimension\\(s\\) \\(n_features"),
        (tampered("state", shape=[]), "field 'shape' must be a non-empty list"),
        (tampered("state", shape=[25.0]), "field 'shape' must be"),
        (tampered("epoch_features", dtype="float64"), "field 'dtype' must be one of \"float32\""),
        (tampered("epoch_features", units="V"), "field 'units' must be 'uV' for kind 'epoch'"),
        (tampered("state", units="%"), "field 'units' must be '1' for kind 'state'"),
        (tampered("epoch_epochs", ch_names=["Fz", "Cz"]), "2 ch_names for 3 payload rows"),
        (tampered("move", body=b"\x00" * 4), "kind 'move' carries no payload; got 4 payload"),
        (tampered("move", shape=[1]), "kind 'move' carries no payload; got 0 .*'shape'"),
        (tampered("state", body=b""), "kind 'state' requires a float32 payload; got none"),
        (tampered("epoch_epochs", drop=("shape",)), "misses field\\(s\\) 'shape'"),
        (tampered("epoch_epochs", drop=("ch_names",)), "misses field\\(s\\) 'ch_names'"),
    ],
)
def test_payload_description_mismatches_are_rejected(data, problem):
    rejects(data, problem)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_payload_values_are_rejected(bad):
    values = rng_floats(57)
    values[7] = bad
    rejects(
        tampered("epoch_features", body=values.astype("<f4").tobytes()),
        "payload holds NaN or infinite values \\(first at index \\(7,\\)\\)",
    )


def test_errors_say_which_session_and_seq_they_belong_to():
    error = rejects(tampered("move", action="jump"), "^session 's-01' seq 3: field 'action'")
    assert (error.session, error.seq, error.problem[:14]) == ("s-01", 3, "field 'action'")
    error = rejects(b"", "^message is 0 bytes")
    assert error.session is None and error.seq is None
    # An unreadable header is reported on the session of the key it arrived on.
    error = rejects(b"garbage", "^session 'abc': header length", key_expr="cfbci/abc/epoch")
    assert error.session == "abc"


@pytest.mark.parametrize("key_expr", ["cfbci/s-01/epoch", "cfbci/other/move"])
def test_a_header_that_disagrees_with_its_key_expression_is_rejected(key_expr):
    error = rejects(encode(EXAMPLES["move"]), "do not match key expression", key_expr=key_expr)
    assert error.session == split_key(key_expr)[0]


def test_encode_rejects_what_decode_would():
    move, features = EXAMPLES["move"], EXAMPLES["epoch_features"]
    nan = np.array([1.0, np.nan], dtype=np.float32)
    cases = [
        (Message("move", "s", 0, 0, move.fields, np.zeros(2)), "kind 'move' carries no payload"),
        (Message("epoch", "s", 0, 0, features.fields, nan), "NaN or infinite"),
        (Message("epoch", "s", 0, 0, features.fields), "requires a float32 payload"),
        (Message("epoch", "s", 0, 0, features.fields, np.array(["a"])), "payload is not numeric"),
        (Message("move", "s", 0, 0, move.fields | {"seq": 4}), "header's own field\\(s\\)"),
        (Message("move", "s", 0, 0, move.fields | {"step": np.int64(1)}), "JSON-serialisable"),
        (Message("move", "s", 0, 0, move.fields | {"x": float("nan")}), "JSON-serialisable"),
        (Message("moves", "s", 0, 0, move.fields), "unknown kind"),
        (Message("move", "s", -1, 0, move.fields), "field 'seq' must be an integer >= 0"),
    ]
    for message, problem in cases:
        with pytest.raises(ProtocolError, match=problem):
            encode(message)


# Sequence numbers ----------------------------------------------------------------------


def test_sequence_tracker_accepts_the_expected_sequence():
    tracker = SequenceTracker()
    assert [tracker.check(seq) for seq in range(5)] == [None] * 5
    assert (tracker.expected, tracker.lost) == (5, 0)


def test_sequence_tracker_counts_a_gap_as_lost_and_moves_on():
    tracker = SequenceTracker()
    for seq in range(5):
        tracker.check(seq)
    assert tracker.check(8) == "gap: expected 5, got 8 (3 messages lost)"
    assert (tracker.expected, tracker.lost) == (9, 3)
    assert tracker.check(9) is None
    assert tracker.check(11) == "gap: expected 10, got 11 (1 message lost)"


def test_sequence_tracker_reports_duplicates_without_moving():
    tracker = SequenceTracker()
    tracker.check(0)
    tracker.check(1)
    assert tracker.check(1) == "duplicate: seq 1 was already received (expected 2)"
    assert tracker.check(0) == "duplicate: seq 0 was already received (expected 2)"
    assert tracker.check(2) is None


def test_sequence_tracker_reports_late_messages_once():
    tracker = SequenceTracker()
    tracker.check(0)
    tracker.check(4)  # 1, 2, 3 lost
    assert tracker.check(2) == "out of order: seq 2 arrived after 4 (it had been counted lost)"
    assert (tracker.expected, tracker.lost) == (5, 2)
    assert tracker.check(2).startswith("duplicate: seq 2")
    assert tracker.check(1).startswith("out of order: seq 1")
    assert tracker.check(3).startswith("out of order: seq 3")
    assert tracker.lost == 0 and tracker.check(5) is None


def test_sequence_tracker_first_message_may_be_late():
    tracker = SequenceTracker()
    assert tracker.check(2) == "gap: expected 0, got 2 (2 messages lost)"


@pytest.mark.parametrize("seq", [-1, 1.5, True])
def test_sequence_tracker_rejects_impossible_sequence_numbers(seq):
    with pytest.raises(ValueError, match="seq must be an integer >= 0"):
        SequenceTracker().check(seq)


# Key expressions -----------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_key_expressions_round_trip(kind):
    session = "Ab_9-" + "x" * 59
    assert key(session, kind) == f"cfbci/{session}/{kind}"
    assert split_key(key(session, kind)) == (session, kind)


def test_key_of_the_unusable_session_exists_for_events_only():
    assert key("_", "event") == "cfbci/_/event"
    with pytest.raises(ProtocolError, match="reserved"):
        key("_", "epoch")


@pytest.mark.parametrize(
    "session", ["", "a b", "x" * 65, "a/b/c", "a//b", "a/*", "*", "**", "é", "s$"]
)
def test_key_rejects_invalid_session_ids(session):
    with pytest.raises(ProtocolError, match=re.escape("1 to 64 characters of A-Z, a-z, 0-9")):
        key(session, "epoch")


def test_key_rejects_unknown_kinds():
    with pytest.raises(ProtocolError, match='unknown kind "epochs"; expected one of config'):
        key("s", "epochs")


@pytest.mark.parametrize(
    "key_expr", ["cfbci/s", "cfbci/s/epoch/x", "other/s/epoch", "cfbci/*/epoch", "cfbci/s/x"]
)
def test_split_key_rejects_foreign_key_expressions(key_expr):
    with pytest.raises(ProtocolError):
        split_key(key_expr)
