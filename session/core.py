"""The interface every session implements: a session config in, one record per step out.

A `Session` holds a world, a learner and the session's random streams, built from
a session config (`session.sessions.open_session`, or a caller's own objects for
offline simulation). Its life is a sequence of steps:

1. `Session.start` chooses the move of step 1;
2. `Session.observe` takes the signal answering the last move (the feature vector
   the learner sees, float32, shape (d,)) and chooses the next move, or none once every
   step's signal has been observed.

Each returns a `Step`: the ``move`` message's fields, the ``target_reached``
events' texts, and (when asked for) the beliefs the move was chosen with.
`Session.state` gives the ``state`` message's fields and payload at that point.
Nothing else in the project calls a learner's ``propose`` or ``observe``: the service, the
re-run and resume of a recording, the offline simulation, the benches, the memory probe
and the soak test all step a `Session`, so that live, replay and simulation take
the same decisions by construction.

`SignalPath` turns an epoch's payload into the learner's signal (raw epochs through
the ErrP feature extractor fitted on the session's first epoch; feature vectors as they
are), for the service and the re-run alike.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from decoding.features import ErrPFeatures

#: ``on_observe(n_signals, learner)``: called after the learner has observed a signal,
#: before it proposes the next move; it must not change the learner.
Observer = Callable[[int, Any], None]


@dataclass(frozen=True)
class Step:
    """What one step of a session produced.

    Attributes
    ----------
    move : dict or None
        The fields of the next ``move`` message (docs/protocol.md); None once the session's
        last signal has been observed.
    events : tuple of str
        The texts of the ``target_reached`` events the move declares (none or one).
    decision : object or None
        The learner's beliefs when it chose the move, if the session was asked to keep
        them (offline simulation's traces and metrics); None otherwise.
    """

    move: dict[str, Any] | None
    events: tuple[str, ...] = ()
    decision: Any = None


@dataclass(frozen=True)
class State:
    """The ``state`` message of a session at a point of its life.

    Attributes
    ----------
    fields : dict
        The message's fields (``best_task``, ``confident``, ``n_signals``,
        ``class_counts``, ``balanced_accuracy``, ``points``).
    confidence : ndarray, float32, shape (n_tasks,) or (n_hypotheses,)
        The message's payload.
    rule, threshold : str or None, float or None
        The decision rule in force and its threshold (not in the message; the report's
        calibration per rule); None in the plane worlds.
    """

    fields: dict[str, Any]
    confidence: np.ndarray
    rule: str | None = None
    threshold: float | None = None


class Session(ABC):
    """One session's steps (the learner's side: it never sees a label or the target).

    Attributes
    ----------
    steps : int
        Steps of the session.
    moves : list of dict
        The ``move`` fields so far, in order.
    """

    steps: int
    moves: list[dict[str, Any]]

    @property
    def step(self) -> int:
        """The last move's step (1-based; 0 before `start`)."""
        return len(self.moves)

    @property
    @abstractmethod
    def n_signals(self) -> int:
        """Signals observed so far."""

    @property
    def finished(self) -> bool:
        """Every step's signal has been observed."""
        return self.n_signals >= self.steps

    @abstractmethod
    def start(self) -> Step:
        """Choose the move of step 1."""

    @abstractmethod
    def observe(
        self, signal: np.ndarray, reset: bool = False, on_observe: Observer | None = None
    ) -> Step:
        """Observe the signal answering the last move and choose the next move.

        Parameters
        ----------
        signal : ndarray, float32, shape (d,)
            The learner's input (a feature vector).
        reset : bool
            The epoch's ``reset`` flag (only the puddle world's epochs may say it).
        on_observe : callable, optional
            ``on_observe(n_signals, learner)`` after the observation, before the next
            proposal.

        Raises
        ------
        ValueError
            On a signal of the wrong size or with non-finite values, or a ``reset`` the
            world does not allow.
        """

    @abstractmethod
    def state(self) -> State:
        """The ``state`` message that accompanies the last move (or ends the session)."""


class SignalPath:
    """The learner's signal of an epoch's payload, as the session's config says.

    A session of raw epochs (config ``signal`` "epochs", with ``sfreq``, ``tmin`` and
    ``ch_names``) passes each epoch (channels x samples, microvolts) through
    `decoding.features.ErrPFeatures` fitted on its first epoch; a session of
    feature vectors takes them as they are.
    """

    def __init__(self, config: dict[str, Any]) -> None:
        self.config = config
        self.raw = config.get("signal") == "epochs"
        self.extractor: ErrPFeatures | None = None

    def __call__(self, payload: np.ndarray) -> np.ndarray:
        """The float32 feature vector (d,) of one epoch's payload.

        Raises
        ------
        ValueError
            When the feature extractor cannot take the epoch (its shape or values).
        """
        if not self.raw:
            return np.asarray(payload, dtype=np.float32)
        extractor = self.extractor or ErrPFeatures(
            self.config["sfreq"], self.config["tmin"], self.config["ch_names"]
        ).fit(payload[None])
        signal = extractor.transform(payload[None])[0].astype(np.float32)
        self.extractor = extractor
        return signal
