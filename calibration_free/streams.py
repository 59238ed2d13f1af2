"""Session seeding: the random streams of a session seed, and the record of one step.

The session seed ``s`` is expanded with ``numpy.random.SeedSequence(s).spawn(3)`` into, in
order, the *data* stream (the synthetic generator's draws), the *user* stream (start cell,
targets, labels, pool shuffles; see `acquisition.user`) and the *learner* stream
(planner choices). Any process that spawns the same way reproduces the session exactly:
offline simulation, the live service and replay all take their streams from here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StepRecord:
    """One step of a session, as written to a trace.

    ``confident`` and ``best_task`` are the learner's beliefs when it chose the action.
    """

    seed: int
    step: int
    state: int
    action: str
    next_state: int
    confident: bool
    best_task: int
    event: str | None


def session_streams(seed: int) -> tuple[np.random.Generator, ...]:
    """The (data, user, learner) generators of a session seed."""
    return tuple(np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))


def start_cell(seed: int, n_states: int) -> int:
    """The agent's start cell: the first draw of the session's user stream.

    Parameters
    ----------
    seed : int
        Session seed.
    n_states : int
        Cells of the grid (``grid ** 2``).
    """
    return int(session_streams(seed)[1].integers(n_states))




#: Index of the world stream among a session seed's spawned streams.
WORLD_STREAM = 3


def world_stream(seed: int) -> np.random.Generator:
    """The world stream of a session seed, ``SeedSequence(seed).spawn(4)[3]``: consumed only
    by stochastic transitions, so that the data, user and learner streams (the first three
    spawned, `session_streams`) are those of a deterministic world."""
    child = np.random.SeedSequence(seed).spawn(WORLD_STREAM + 1)[WORLD_STREAM]
    return np.random.default_rng(child)
