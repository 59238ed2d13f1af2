"""Decisions between values that are equal up to rounding.

Values equal in exact arithmetic (two tasks a symmetric history cannot tell apart, two
moves of equal expected information) differ in their last bits by the order a BLAS kernel
sums in, which depends on the CPU and the thread count. A decision between them must not
turn on that: values within a relative `TIE_TOLERANCE` of the best count as tied,
and the caller breaks the tie by a rule (the lowest index, or a draw from its seeded
stream).
"""

from __future__ import annotations

import numpy as np

#: Relative tolerance under which two values count as tied (rounding is ~1e-16 relative
#: per operation; a decision's inputs pass through thousands of them).
TIE_TOLERANCE = 1e-9


def near_best(values: np.ndarray, axis: int = -1) -> np.ndarray:
    """Where ``values`` are within `TIE_TOLERANCE` (relative, at least absolute) of
    their maximum along ``axis``: a boolean array of ``values``' shape."""
    best = np.max(values, axis=axis, keepdims=True)
    return values >= best - TIE_TOLERANCE * np.maximum(1.0, np.abs(best))


def first_best(values: np.ndarray) -> int:
    """The lowest index among the values tied with the maximum of ``values`` (n,)."""
    return int(np.argmax(near_best(values)))
