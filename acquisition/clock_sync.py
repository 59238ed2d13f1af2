"""The offset between another clock and this machine's, from round trips (NTP's way).

A stimulus shown in a web page is timed by the page's clock (``performance.now()``, ms),
an onset marker by this machine's LSL clock (``pylsl.local_clock()``, s). `ClockSync`
maps one to the other from round trips that this side starts: it reads its own clock
when it sends a ping (``sent``) and when the answer comes back (``received``); the answer
carries the other clock's reading when it was made (``remote``). If the way out took as
long as the way back, the other clock read ``remote`` at the round trip's middle, so

    offset = (sent + received) / 2 - remote        (this clock minus the other's)

and whatever the two ways took, the true offset is within half the round trip of that.
A round trip slowed on one way (a busy event loop, a message queued behind another)
errs by up to half its extra time, so only the fastest round trips are trusted: the
estimate is the median offset of the ``best`` shortest round trips among the last
``window`` ones, and its uncertainty half the longest of those ``best`` round trips (a
bound on every one of them). The window follows a drifting clock; the median of several
fast round trips is less noisy than the fastest alone.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

#: Round trips kept, and how many of the shortest give the estimate.
WINDOW = 64
BEST = 8


@dataclass(frozen=True)
class Offset:
    """The estimated offset between two clocks.

    Attributes
    ----------
    offset : float
        This clock minus the other clock, s: a reading ``t`` of the other clock is
        ``t + offset`` on this one.
    uncertainty : float
        Half the longest round trip the estimate rests on, s: a bound on its error
        (whatever the two ways of a round trip took).
    round_trips : int
        Round trips in the window.
    """

    offset: float
    uncertainty: float
    round_trips: int


class ClockSync:
    """The offset of another clock to this one, from the round trips of a sliding window.

    Parameters
    ----------
    window : int
        Most recent round trips kept.
    best : int
        Shortest round trips of the window the estimate takes the median of.
    """

    def __init__(self, window: int = WINDOW, best: int = BEST) -> None:
        if not 1 <= best <= window:
            raise ValueError(f"best ({best}) must be in 1..window ({window})")
        self.best = best
        self._trips: deque[tuple[float, float]] = deque(maxlen=window)  # (round trip, offset)

    def add(self, sent: float, remote: float, received: float) -> None:
        """Take one round trip: this clock when the ping left and when its answer came
        back, and the other clock when it answered, all in s.

        Raises
        ------
        ValueError
            If ``received`` is before ``sent`` or a reading is not finite.
        """
        if not np.isfinite([sent, remote, received]).all():
            raise ValueError(f"clock readings must be finite; got {sent}, {remote}, {received}")
        if received < sent:
            raise ValueError(f"an answer received at {received} s before its ping was sent "
                             f"at {sent} s")
        self._trips.append((received - sent, (sent + received) / 2 - remote))

    @property
    def ready(self) -> bool:
        """Whether the window holds ``best`` round trips (an estimate can be made)."""
        return len(self._trips) >= self.best

    def estimate(self) -> Offset | None:
        """The offset from the window's shortest round trips; None until `ready`."""
        if not self.ready:
            return None
        trips = np.array(self._trips)
        fastest = trips[np.argsort(trips[:, 0], kind="stable")[: self.best]]
        return Offset(float(np.median(fastest[:, 1])), float(fastest[:, 0].max() / 2),
                      len(trips))
