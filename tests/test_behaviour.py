"""The same command lines make the same decisions as the references (``tools/behaviour_check.py``).

The references in ``tests/behaviour/reference`` were written by the code at commit cd7b978,
before the session core was refactored (``tests/behaviour/README.md``). Each case runs
``cfbci simulate`` or ``cfbci session`` with this code: traces must be byte-identical, JSON
reports equal (timings dropped), and the reference recordings must replay identically. The
cases on ``../shared`` data are skipped where it is absent (a fresh clone). One case is a
few seconds of CPU (pick-and-place, its speech preset, the puddle world and the live
sessions 5 to 8 s); the whole file about 65 s of CPU, spread by ``pytest -n 2``.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]
SHARED = Path(__file__).resolve().parents[2] / "shared"


def _behaviour_check() -> ModuleType:
    """``tools/behaviour_check.py`` (a script, not a package) as a module."""
    path = REPOSITORY / "tools" / "behaviour_check.py"
    spec = importlib.util.spec_from_file_location("behaviour_check", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


check = _behaviour_check()
SYNTHETIC = [case for case in check.CASES if not case.shared_files]
REAL = [case for case in check.CASES if case.shared_files]


def _same_as_the_reference(case: check.Case, scratch: Path) -> None:
    """Run ``case`` with this code in ``scratch``; fail at its first difference."""
    try:
        check.check_case(case, check.Runner.create(), check.REFERENCE, scratch, SHARED)
    except check.Difference as difference:
        pytest.fail(str(difference), pytrace=False)


@pytest.mark.parametrize("case", SYNTHETIC, ids=lambda case: case.name)
def test_a_synthetic_case_decides_as_before(case: check.Case, tmp_path: Path) -> None:
    """Synthetic data and the committed speech features: runs everywhere."""
    _same_as_the_reference(case, tmp_path)


@pytest.mark.parametrize("case", REAL, ids=lambda case: case.name)
def test_a_real_data_case_decides_as_before(case: check.Case, tmp_path: Path) -> None:
    """``../shared/datasets`` (s4, finger moves): skipped where it is absent."""
    missing = check.missing_data(case, SHARED)
    if missing:
        pytest.skip(f"real data set {missing[0]} is absent (../shared is not in a fresh clone)")
    _same_as_the_reference(case, tmp_path)


def test_every_case_has_its_references() -> None:
    """A reference file for every output of every case (real-data ones included)."""
    for case in check.CASES:
        for name in case.outputs():
            assert (check.REFERENCE / name).is_file(), name


def test_a_changed_decision_is_reported_at_its_first_difference(tmp_path: Path) -> None:
    """The check names where outputs first differ: JSON path, trace line."""
    reference = [{"seed": 0, "step": 1, "action": "up"}, {"seed": 0, "step": 2, "action": "up"}]
    changed = [reference[0], {**reference[1], "action": "goal"}]
    found = check.first_json_difference(reference, changed)
    assert found == '[1].action: "up" in the reference, "goal" now'
    assert check.first_json_difference(reference, [reference[0]]) == (
        ": length 2 in the reference, 1 now"
    )
    old, new = tmp_path / "old.trace", tmp_path / "new.trace"
    old.write_text('{"step": 1}\n{"step": 2}\n')
    new.write_text('{"step": 1}\n{"step": 3}\n')
    assert check.first_trace_difference(old, new).startswith("line 2:")
    assert check.first_trace_difference(old, old) is None


def test_only_timings_are_dropped_from_the_json() -> None:
    """Timing keys go, nothing else; numbers compare exactly."""
    report = {"steps": 30, "time": 1.9, "moves": [{"update_ms": 3.0, "action": "up"}]}
    assert check.without_timings(report) == {"steps": 30, "moves": [{"action": "up"}]}
    # Floats compare exactly, and NaN equals NaN.
    assert check.first_json_difference([0.1 + 0.2], [0.3]) is not None
    assert check.first_json_difference([float("nan")], [float("nan")]) is None
