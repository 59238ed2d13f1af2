"""The protocol's vocabulary (session.vocabulary) names what the worlds and sessions use."""

from calibration_free.frames import FRAMES
from calibration_free.puddle import ACTIONS
from calibration_free.worlds import WORLDS, make_world
from session import plane, vocabulary


def test_the_vocabulary_is_the_worlds_and_sessions_names() -> None:
    assert vocabulary.WORLDS == WORLDS
    assert vocabulary.FRAMES == FRAMES
    assert vocabulary.PUDDLE_MOVES == ACTIONS == plane.PUDDLE_MOVES
    assert vocabulary.PLANE_FRAMES == plane.PLANE_FRAMES
    assert vocabulary.PROBE == plane.PROBE
    names = dict.fromkeys(n for world in WORLDS for n in make_world(world).action_names)
    assert vocabulary.DISCRETE_ACTIONS == tuple(names)


def test_loading_the_protocol_loads_no_world_and_no_learner() -> None:
    """The wire protocol validates names against plain constants: importing it imports
    neither the worlds nor the learners (checked in a fresh interpreter)."""
    import subprocess
    import sys

    code = (
        "import sys, wire.protocol, wire.transport, wire.intake, wire.services;"
        "print(sorted(m for m in sys.modules if m.startswith(('calibration_free', 'decoding'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
