"""The names a config and a move may use, as plain constants: what the wire protocol
validates against without building a world or loading a learner.

``tests/test_vocabulary.py`` checks that they are the names the worlds, frames and plane
sessions use.
"""

from __future__ import annotations

#: The discrete worlds (`calibration_free.worlds.WORLDS`).
WORLDS: tuple[str, ...] = ("grid", "line", "pick-and-place")
#: The discrete worlds' frames (`calibration_free.frames.FRAMES`).
FRAMES: tuple[str, ...] = ("feedback", "guidance")
#: The plane worlds the live path runs, and the frame each requires.
PLANE_FRAMES: dict[str, str] = {"continuous": "cardinal", "puddle": "mixed"}
#: The continuous world's only action: teleport to the probe point.
PROBE = "probe"
#: The puddle world's actions, in its order (`calibration_free.puddle.ACTIONS`).
PUDDLE_MOVES: tuple[str, ...] = ("north", "south", "east", "west")
#: The discrete worlds' action names, in world order then action order.
DISCRETE_ACTIONS: tuple[str, ...] = (
    "up", "down", "left", "right", "goal", "no-move", "grasp", "release",
)
