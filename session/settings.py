"""The JSON kinds a learner setting takes: from its settings class's annotations.

A config's ``learner`` object names settings of a dataclass (``LearnerConfig`` in the
discrete worlds, ``ContinuousConfig`` or ``PuddleConfig`` in the plane); each value must
be of a kind its field's annotation allows (``float`` a number, ``int`` an integer,
``float | str`` a number or a string, ``float | None`` a number or null, ...).
"""

from __future__ import annotations

import functools
import typing
from collections.abc import Callable
from typing import Any

#: A JSON value's test for each kind an annotation may name.
_JSON_KINDS: dict[str, Callable[[Any], bool]] = {
    "a boolean": lambda value: isinstance(value, bool),
    "an integer": lambda value: isinstance(value, int) and not isinstance(value, bool),
    "a number": lambda value: isinstance(value, int | float) and not isinstance(value, bool),
    "a string": lambda value: isinstance(value, str),
    "null": lambda value: value is None,
}
_KIND_OF_TYPE = {
    bool: "a boolean", int: "an integer", float: "a number", str: "a string",
    type(None): "null",
}


@functools.cache
def setting_kinds(settings: type) -> dict[str, tuple[str, ...]]:
    """The JSON kinds of every field of the dataclass ``settings``, by name."""
    return {
        name: tuple(_KIND_OF_TYPE[t] for t in typing.get_args(hint) or (hint,))
        for name, hint in typing.get_type_hints(settings).items()
    }


def check_setting_kinds(values: dict[str, Any], settings: type) -> None:
    """Raise ValueError naming the first setting of ``values`` whose value is of a kind
    its field of ``settings`` does not allow (names ``settings`` lacks are not checked)."""
    kinds = setting_kinds(settings)
    for name, value in values.items():
        allowed = kinds.get(name)
        if allowed is not None and not any(_JSON_KINDS[kind](value) for kind in allowed):
            raise ValueError(
                f"learner setting {name!r} must be {' or '.join(allowed)}; got {value!r}"
            )
