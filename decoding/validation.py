"""One place for input checks, so every user-facing error reads the same way.

Each helper raises `ValueError` (or `TypeError`) with a message that says
*what* is wrong, *where* (the argument or file it came from) and what was expected.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np


def check_option(name: str, value: Any, allowed: Iterable[Any]) -> Any:
    """Return ``value`` if it is one of ``allowed``, else raise a readable ``ValueError``."""
    allowed = tuple(allowed)
    if value not in allowed:
        choices = ", ".join(repr(a) for a in allowed)
        raise ValueError(f"{name} must be one of {choices}; got {value!r}")
    return value


def check_range(
    name: str, value: float, low: float, high: float, *, inclusive: bool = True
) -> float:
    """Return ``value`` if it lies in [low, high] (or (low, high)), else raise ``ValueError``."""
    ok = low <= value <= high if inclusive else low < value < high
    if not ok:
        brackets = "[]" if inclusive else "()"
        raise ValueError(
            f"{name} must be in {brackets[0]}{low}, {high}{brackets[1]}; got {value!r}"
        )
    return value


def check_at_least(name: str, value: float, low: float, *, strict: bool = False) -> float:
    """Return ``value`` if it is at least ``low`` (above it if ``strict``), else raise a
    readable ``ValueError``."""
    if not (value > low if strict else value >= low):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {low}; got {value!r}")
    return value


def check_array(
    name: str,
    value: Any,
    *,
    ndim: int | None = None,
    shape: tuple[int | None, ...] | None = None,
    dtype: type | np.dtype | None = np.float64,
    finite: bool = True,
    where: str = "",
) -> np.ndarray:
    """Convert ``value`` to an ndarray and check its rank, shape and finiteness.

    ``shape`` may hold ``None`` for free dimensions. ``where`` (a file name, a message id)
    is prefixed to any error so the user knows which input was at fault.
    """
    prefix = f"{where}: " if where else ""
    try:
        array = np.asarray(value) if dtype is None else np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{prefix}{name} could not be read as numbers: {exc}") from exc
    if shape is not None:
        ndim = len(shape)
    if ndim is not None and array.ndim != ndim:
        raise ValueError(
            f"{prefix}{name} must have {ndim} dimensions; got shape {array.shape}"
        )
    if shape is not None:
        for axis, (want, got) in enumerate(zip(shape, array.shape, strict=True)):
            if want is not None and want != got:
                raise ValueError(
                    f"{prefix}{name} has size {got} on axis {axis}; expected {want} "
                    f"(shape {array.shape})"
                )
    if finite and array.dtype.kind in "fc" and not np.all(np.isfinite(array)):
        bad = np.argwhere(~np.isfinite(array))[0]
        raise ValueError(
            f"{prefix}{name} holds NaN or infinite values (first at index {tuple(bad.tolist())})"
        )
    return array
