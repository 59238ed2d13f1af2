"""Which steps of a recording an analysis may use, when the file is cut or damaged.

The service writes a step's messages in one order (every world): the move of step ``k``,
its state (and the belief, ``/position`` in the puddle world, a target event and its log),
then, once the user answered, the epoch of step ``k`` and its features (the epoch
accepted); the truth of a step comes from the source at any time; after the last epoch, a
final state. So in an intact file, cut anywhere, the moves are steps ``1..M``, the states'
``n_signals`` ``0..S-1`` and the features' steps ``1..F`` with ``F <= M <= F + 1``,
``F <= S``, and ``S <= M`` except for the final state (``S = M + 1`` when ``F = M``); each
target move is followed, before the next move, by one ``target_reached`` event.

A damaged region (`replay.damage.Damage`) whose lost messages keep these rules
(a belief, a log, a truth, the metadata, a message index, the summary, or the ``/config``
message whose configuration the metadata also holds) is *harmless* to an analysis: the
messages after it are used too. The first region that breaks them (a lost move, state,
epoch, features or target event) ends the usable part there: the messages after it are
left out (``cfbci recover`` keeps them), as a cut file ends at its cut. Epochs recorded
without their features (the file cut before the service accepted the epoch, or an epoch it
rejected) are not the learner's inputs: they are left out too.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from replay.damage import Damage
from replay.recording import Recording


@dataclass(frozen=True)
class Extent:
    """The usable part of a recording (`usable_part`).

    Attributes
    ----------
    recording : Recording
        The messages an analysis may use (the file's ``damage`` and ``warning`` kept).
    stop : int or None
        Byte offset where damage ends the usable part early (None: nothing left out for
        damage; a cut file still ends at its cut).
    reason : str or None
        Why it ends there: the damaged region and what of the steps it broke.
    left_out : int
        Messages read after ``stop``, not used.
    unaccepted : int
        Epochs left out because they have no features (not accepted by the service).
    harmless : tuple of Damage
        Damaged regions before ``stop`` whose loss breaks no step (the analysis goes on
        past them).
    """

    recording: Recording
    stop: int | None
    reason: str | None
    left_out: int
    unaccepted: int
    harmless: tuple[Damage, ...]

    @property
    def whole(self) -> bool:
        """The file is closed and intact: the usable part is all of it."""
        return self.recording.complete

    def notes(self) -> list[str]:
        """What was left out and why, one sentence each (empty for an intact file)."""
        notes = []
        if self.stop is not None:
            notes.append(f"the usable steps end at byte {self.stop} ({self.reason}); "
                         f"{self.left_out} message{'s' * (self.left_out != 1)} after it not "
                         "used (`cfbci recover` keeps them)")
        for damage in self.harmless:
            notes.append(f"damaged {damage.describe()}: no move, state, epoch or target event "
                         "lost there, the steps go on past it")
        return notes

    def to_json(self) -> dict[str, Any]:
        return {"stop": self.stop, "reason": self.reason, "left_out": self.left_out,
                "unaccepted_epochs": self.unaccepted,
                "harmless_damage": [d.to_json() for d in self.harmless]}


def _entries(recording: Recording, topic: str) -> list[tuple[int, int, dict[str, Any]]]:
    """``(rank, offset, message)`` of a topic's messages."""
    messages = recording.messages.get(topic, [])
    order = recording.order.get(topic) or list(range(len(messages)))
    offsets = recording.offsets.get(topic) or [0] * len(messages)
    return [(r, o, m) for r, o, (_, m) in zip(order, offsets, messages, strict=True)]


def _integer(message: dict[str, Any], key: str) -> int | None:
    value = message.get(key)
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def step_break(recording: Recording, before: int | None = None) -> str | None:
    """The first way the messages before byte ``before`` (all if None) break the rules of
    the module docstring, or None if they keep them."""
    def kept(topic: str) -> list[tuple[int, int, dict[str, Any]]]:
        return [e for e in _entries(recording, topic) if before is None or e[1] < before]

    moves, states, features = kept("/move"), kept("/state"), kept("/features")
    for topic, entries, key, first in (("/move", moves, "step", 1),
                                       ("/state", states, "n_signals", 0),
                                       ("/features", features, "step", 1)):
        for k, (_, _, message) in enumerate(entries):
            if _integer(message, key) != k + first:
                return (f"{topic} #{k + 1} has {key} {message.get(key)!r} where {k + first} "
                        "follows: a message before it is lost")
    epochs = {m.get("seq") for _, _, m in kept("/epoch")}
    for _, _, message in features:
        if message.get("seq") not in epochs:
            return f"the epoch of step {message.get('step')} is lost (its features are there)"
    m, s, f = len(moves), len(states), len(features)
    if not (m - 1 <= f <= m and f <= s and (s <= m or (s == m + 1 and f == m))):
        return f"{m} moves, {s} states and {f} features do not fit: a move or state is lost"
    timeline = sorted(
        [(r, "move", bool(msg.get("target_reached"))) for r, _, msg in moves]
        + [(r, "event", True) for r, _, msg in kept("/event")
           if msg.get("event") == "target_reached"])
    pending: bool | None = None  # the last move declared a target and awaits its event
    for _, kind, target in timeline:
        if kind == "move":
            if pending:
                return "a target event is lost (a move declaring a target has none)"
            pending = target
        elif not pending:
            return "a move is lost (a target event follows a move declaring none)"
        else:
            pending = False
    return None


def usable_part(recording: Recording) -> Extent:
    """The part of ``recording`` an analysis may use (see the module docstring)."""
    stop = reason = None
    harmless: list[Damage] = []
    regions = recording.data_damage()
    for k, damage in enumerate(regions):
        until = regions[k + 1].start if k + 1 < len(regions) else None
        broken = step_break(recording, until)
        if broken is not None:
            stop, reason = damage.start, f"damaged {damage.describe()}: {broken}"
            break
        harmless.append(damage)
    left_out = 0
    messages, offsets, order = {}, {}, {}
    for topic, entries in recording.messages.items():
        kept = [k for k, at in enumerate(recording.offsets.get(topic) or [0] * len(entries))
                if stop is None or at < stop]
        left_out += len(entries) - len(kept)
        messages[topic] = [entries[k] for k in kept]
        offsets[topic] = [recording.offsets[topic][k] for k in kept] \
            if recording.offsets.get(topic) else []
        order[topic] = [recording.order[topic][k] for k in kept] \
            if recording.order.get(topic) else []
    unaccepted = 0
    if messages.get("/features"):
        accepted = {m["seq"] for _, m in messages["/features"]}
        kept = [k for k, (_, m) in enumerate(messages.get("/epoch", [])) if m["seq"] in accepted]
        unaccepted = len(messages.get("/epoch", [])) - len(kept)
        for table in (messages, offsets, order):
            if table.get("/epoch"):
                table["/epoch"] = [table["/epoch"][k] for k in kept]
    usable = replace(recording, messages=messages, offsets=offsets, order=order)
    return Extent(usable, stop, reason, left_out, unaccepted, tuple(harmless))
