"""``cfbci world check``: the task hypotheses of a world that no signal can tell apart."""

from __future__ import annotations

from calibration_free.frames import Frame
from calibration_free.identifiability import Confusable
from calibration_free.world import World


def describe(world: World, frame: Frame, pair: Confusable) -> str:
    """One line: the two tasks, how they are confused, and the class renaming if any."""
    names = frame.class_names()
    text = f"{world.task_name(pair.task)} / {world.task_name(pair.other)}: {pair.kind}"
    if pair.kind == "symmetric":
        renaming = ", ".join(
            f"{names[k]} -> {names[image]}"
            for k, image in enumerate(pair.permutation)
            if image != k
        )
        text += f" ({renaming})"
    return text


