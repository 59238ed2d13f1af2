"""The learner's inputs of a recording: its accepted epochs' signals and ``reset`` flags,
as the service computed them (shared by the re-run, `replay.rerun`, and the reader
of priors, `replay.prior`)."""

from __future__ import annotations

import numpy as np

from replay.recording import Recording, decode_array
from session.core import SignalPath


def recorded_signals(recording: Recording) -> list[np.ndarray]:
    """The learner's inputs, float32, from the accepted recorded epochs (raw or features),
    through the session's `session.core.SignalPath` as the service computed them."""
    path = SignalPath(recording.config)
    return [path(decode_array(message)) for message in recording.accepted_epochs()]


def recorded_resets(recording: Recording) -> list[bool]:
    """The ``reset`` flag of every accepted recorded epoch (False where it has none)."""
    return [bool(message.get("reset", False)) for message in recording.accepted_epochs()]
