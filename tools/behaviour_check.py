"""Before-and-after behaviour check: the same ``cfbci`` command lines, the same decisions.

A table of cases (`CASES`), each one ``cfbci simulate`` or ``cfbci session`` command
line, small enough to take a few seconds. ``--write DIR`` runs every case and stores its
outputs in DIR as reference files (``NAME.trace``, ``NAME.json``, ``NAME.mcap``);
``--check DIR`` runs them again and compares:

* ``--trace`` files byte for byte;
* ``--json`` files as parsed JSON, after dropping timing keys (`without_timings`: the
  present outputs hold none; keys named as wall-clock times are dropped should a later
  version add some), floats exactly;
* a live session's recording: ``cfbci replay NAME.mcap`` on the *reference* recording must
  print ``identical`` and exit 0 (the session's ``--json`` summary is compared as above).

The first difference is printed and the exit status is 1. Cases whose data
(``../shared/datasets``, beside the repository) is absent are skipped, with a message.

Every case runs in its own directory of a scratch directory holding a ``shared`` link to
the data, so that the command lines (and the dataset paths the JSON reports) read
``../shared/datasets/...`` as in the README, wherever the repository is. Files of
``tests/behaviour/data`` a case names are copied beside it.

Usage::

    python tools/behaviour_check.py --check tests/behaviour/reference        # this code
    python tools/behaviour_check.py --check tests/behaviour/reference --only synthetic
    python tools/behaviour_check.py --write DIR --python-path /path/to/old/checkout
    python tools/behaviour_check.py --check DIR --cfbci '.venv/bin/cfbci' --case puddle

``--python-path`` puts an old checkout first on the ``PYTHONPATH`` of the ``cfbci``
processes (the references of ``tests/behaviour/reference`` were written so, from commit
cd7b978); ``--cfbci`` replaces the command (default: this interpreter's
``python -m cfbci.cli``).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

REPOSITORY = Path(__file__).resolve().parents[1]
#: The real data sets, beside the repository (not in a fresh clone).
SHARED = REPOSITORY.parent / "shared"
#: Small data files the cases use (committed).
DATA = REPOSITORY / "tests" / "behaviour" / "data"
REFERENCE = REPOSITORY / "tests" / "behaviour" / "reference"
#: What a command line may take before the check gives up on it.
TIMEOUT_S = 600

S4 = "../shared/datasets/errp-features-s4/s4.mat"
FINGER = "../shared/datasets/finger-moves/move_finger.mat"

#: Keys that are timings (wall clock), dropped before JSON outputs are compared; a key ending
#: in one of `TIMING_SUFFIXES` is one too.
TIMING_KEYS = frozenset({"time", "elapsed", "duration", "wall_time", "seconds"})
TIMING_SUFFIXES = ("_ms", "_seconds", "_elapsed", "_duration")


@dataclass(frozen=True)
class Case:
    """One command line and what it writes.

    Attributes
    ----------
    name : str
        Also the stem of its reference files.
    command : str
        ``simulate`` (writes ``--trace`` and ``--json``, or ``--json`` only where ``trace``
        is False: frame hypotheses and the plane worlds write no trace) or ``session`` (a
        live session: ``--record`` and ``--json``).
    args : tuple of str
        The command's other options.
    trace : bool
        Whether the command writes a ``--trace``.
    data : tuple of str
        Files of `DATA` copied into the case's directory.
    """

    name: str
    command: str
    args: tuple[str, ...]
    trace: bool = True
    data: tuple[str, ...] = ()

    @property
    def shared_files(self) -> tuple[str, ...]:
        """The ``../shared`` files the case reads (none: a synthetic case)."""
        return tuple(arg for arg in self.args if arg.startswith("../shared/"))

    def output_args(self) -> list[str]:
        """The output options, files named after the case in its directory."""
        if self.command == "session":
            return ["--record", f"{self.name}.mcap", "--json", f"{self.name}.json"]
        trace = ["--trace", f"{self.name}.trace"] if self.trace else []
        return [*trace, "--json", f"{self.name}.json"]

    def outputs(self) -> tuple[str, ...]:
        """The names of the files the case writes (its reference files)."""
        if self.command == "session":
            return (f"{self.name}.mcap", f"{self.name}.json")  # the replay's step first
        trace = (f"{self.name}.trace",) if self.trace else ()
        return (*trace, f"{self.name}.json")


def _simulate(name: str, *args: str, trace: bool = True, data: tuple[str, ...] = ()) -> Case:
    """A ``cfbci simulate`` case."""
    return Case(name, "simulate", args, trace, data)


CASES: tuple[Case, ...] = (
    # Real data (skipped when ../shared is absent).
    _simulate("s4-feedback", "--dataset", S4, "--seeds", "3", "--steps", "200", "--jobs", "1"),
    _simulate(
        "finger-guidance", "--dataset", FINGER, "--frame", "guidance", "--seeds", "3",
        "--steps", "150", "--jobs", "1",
    ),
    _simulate(
        "preset-frame-hypotheses", "--preset", "frame-hypotheses", "--dataset", FINGER,
        "--seeds", "2", "--steps", "100", "--jobs", "1", trace=False,
    ),
    _simulate(
        "continuous-finger", "--world", "continuous", "--dataset", FINGER, "--seeds", "2",
        "--steps", "60", "--jobs", "1", trace=False,
    ),
    # Synthetic.
    _simulate(  # two Dask workers: the parallel path
        "synthetic-feedback", "--synthetic", "errp", "--synthetic-accuracy", "0.78",
        "--seeds", "3", "--steps", "150", "--jobs", "2",
    ),
    _simulate(
        "calibrated-baseline", "--synthetic-accuracy", "0.78", "--baseline", "calibrated",
        "--calibration-trials", "100", "--seeds", "2", "--steps", "200", "--jobs", "1",
    ),
    _simulate(
        "line-guidance", "--world", "line", "--frame", "guidance", "--synthetic", "gaussian",
        "--seeds", "2", "--steps", "100", "--jobs", "1",
    ),
    _simulate(
        "pick-and-place-feedback", "--world", "pick-and-place", "--seeds", "2", "--steps",
        "110", "--jobs", "1",
    ),
    _simulate(
        "preset-world-properties", "--preset", "world-properties", "--seeds", "2", "--jobs",
        "1",
    ),
    _simulate(
        "preset-simple-vs-matching", "--preset", "simple-vs-matching", "--seeds", "2",
        "--steps", "200", "--jobs", "1",
    ),
    _simulate(  # spoken yes/no (espeak-ng features, committed: see tests/behaviour/README.md)
        "preset-pick-and-place-speech", "--preset", "pick-and-place-speech", "--dataset",
        "speech-yes-no.npz", "--seeds", "2", "--steps", "60", "--jobs", "1",
        data=("speech-yes-no.npz",),
    ),
    _simulate(
        "frame-hypotheses-synthetic", "--world", "line", "--frame", "hypotheses",
        "--synthetic", "gaussian", "--planner", "random", "--seeds", "2", "--steps", "100",
        "--jobs", "1", trace=False,
    ),
    _simulate(
        "continuous-synthetic", "--world", "continuous", "--synthetic", "gaussian", "--seeds",
        "2", "--steps", "60", "--jobs", "1", trace=False,
    ),
    _simulate(
        "puddle", "--world", "puddle", "--seeds", "2", "--steps", "90", "--jobs", "1",
        trace=False,
    ),
    # Live sessions (Zenoh on loopback), synthetic; seeds and lengths chosen to reach a target
    # (grid) and keep the recordings small.
    Case("session-grid", "session", ("--seed", "6", "--steps", "30")),  # raw ErrP epochs
    Case(  # feature vectors: a longer session in as many bytes
        "session-grid-guidance", "session",
        ("--frame", "guidance", "--synthetic", "gaussian", "--seed", "4", "--steps", "80"),
    ),
    Case(
        "session-continuous", "session",
        ("--world", "continuous", "--frame", "cardinal", "--synthetic", "gaussian", "--seed",
         "1", "--steps", "25"),
    ),
)


class Difference(Exception):
    """A case's outputs differ from its reference (the message says where first)."""


@dataclass(frozen=True)
class Runner:
    """How to run ``cfbci``: the command's first words and its environment."""

    command: tuple[str, ...]
    env: dict[str, str]

    @classmethod
    def create(cls, cfbci: str | None = None, python_path: str | None = None) -> Runner:
        """``cfbci`` (a shell-quoted command) or this interpreter's ``python -m cfbci.cli``;
        ``python_path`` first on ``PYTHONPATH``."""
        command = tuple(shlex.split(cfbci)) if cfbci else (sys.executable, "-m", "cfbci.cli")
        env = dict(os.environ)
        if python_path:
            env["PYTHONPATH"] = os.pathsep.join(
                part for part in (python_path, env.get("PYTHONPATH")) if part
            )
        return cls(command, env)

    def run(self, args: Sequence[str], cwd: Path) -> subprocess.CompletedProcess[str]:
        """``cfbci ARGS`` in ``cwd``, output captured."""
        return subprocess.run(
            [*self.command, *args], cwd=cwd, env=self.env, capture_output=True, text=True,
            timeout=TIMEOUT_S, check=False,
        )


def missing_data(case: Case, shared: Path = SHARED) -> list[Path]:
    """The data files ``case`` needs that are absent."""
    paths = [shared / arg.removeprefix("../shared/") for arg in case.shared_files]
    return [path for path in paths if not path.is_file()]


def run_case(case: Case, runner: Runner, scratch: Path, shared: Path = SHARED) -> Path:
    """Run ``case`` in ``scratch/NAME`` (``scratch/shared`` linked to ``shared``); the
    directory holding its outputs.

    Raises
    ------
    Difference
        When the command fails or does not write its outputs.
    """
    link = scratch / "shared"
    if not link.exists() and shared.is_dir():
        link.symlink_to(shared.resolve(), target_is_directory=True)
    directory = scratch / case.name
    directory.mkdir(parents=True)
    for name in case.data:
        shutil.copyfile(DATA / name, directory / name)
    args = [case.command, *case.args, *case.output_args()]
    done = runner.run(args, directory)
    if done.returncode != 0:
        raise Difference(
            f"{case.name}: `cfbci {shlex.join(args)}` exited {done.returncode}:\n"
            f"{done.stdout[-2000:]}{done.stderr[-3000:]}"
        )
    for name in case.outputs():
        if not (directory / name).is_file():
            raise Difference(f"{case.name}: `cfbci {shlex.join(args)}` wrote no {name}")
    return directory


def without_timings(value: Any) -> Any:
    """``value`` (parsed JSON) without the keys that are timings, at any depth."""
    if isinstance(value, dict):
        return {
            key: without_timings(item) for key, item in value.items()
            if key not in TIMING_KEYS and not key.endswith(TIMING_SUFFIXES)
        }
    if isinstance(value, list):
        return [without_timings(item) for item in value]
    return value


def first_json_difference(reference: Any, actual: Any, where: str = "") -> str | None:
    """Where ``actual`` first differs from ``reference`` (parsed JSON; floats exactly, NaN
    equal to NaN), or None."""
    if isinstance(reference, dict) and isinstance(actual, dict):
        for key in [*reference, *(key for key in actual if key not in reference)]:
            if key not in actual or key not in reference:
                side = "new" if key not in reference else "missing"
                return f"{where}.{key}: {side} key"
            found = first_json_difference(reference[key], actual[key], f"{where}.{key}")
            if found:
                return found
        return None
    if isinstance(reference, list) and isinstance(actual, list):
        for index, (ref, act) in enumerate(zip(reference, actual, strict=False)):
            found = first_json_difference(ref, act, f"{where}[{index}]")
            if found:
                return found
        if len(reference) != len(actual):
            return f"{where}: length {len(reference)} in the reference, {len(actual)} now"
        return None
    if json.dumps(reference) != json.dumps(actual):  # exact, types included (1 vs 1.0)
        return f"{where or '.'}: {json.dumps(reference)} in the reference, {json.dumps(actual)} now"
    return None


def first_trace_difference(reference: Path, actual: Path) -> str | None:
    """The first line where two trace files differ (they must be byte-identical), or None."""
    expected, got = reference.read_bytes(), actual.read_bytes()
    if expected == got:
        return None
    old, new = expected.splitlines(keepends=True), got.splitlines(keepends=True)
    for number, (a, b) in enumerate(zip(old, new, strict=False), start=1):
        if a != b:
            return f"line {number}:\n  reference {a!r}\n  now       {b!r}"
    return f"{len(old)} lines in the reference, {len(new)} now (one is a prefix of the other)"


def replay(runner: Runner, recording: Path, cwd: Path) -> str | None:
    """Why ``cfbci replay RECORDING`` does not say ``identical`` with exit 0, or None."""
    done = runner.run(["replay", str(recording.resolve())], cwd)
    if done.returncode == 0 and "identical" in done.stdout:
        return None
    return f"`cfbci replay {recording}` exited {done.returncode}:\n{done.stdout}{done.stderr}"


def write_case(
    case: Case, runner: Runner, reference: Path, scratch: Path, shared: Path = SHARED
) -> None:
    """Run ``case`` (in ``scratch``, data from ``shared``) and store its outputs in
    ``reference``; a recording must replay identically with the same code."""
    directory = run_case(case, runner, scratch, shared)
    if case.command == "session":
        problem = replay(runner, directory / f"{case.name}.mcap", directory)
        if problem:
            raise Difference(f"{case.name}: its own recording does not replay: {problem}")
    reference.mkdir(parents=True, exist_ok=True)
    for name in case.outputs():
        shutil.copyfile(directory / name, reference / name)


def check_case(
    case: Case, runner: Runner, reference: Path, scratch: Path, shared: Path = SHARED
) -> None:
    """Run ``case`` (in ``scratch``, data from ``shared``) and compare with its reference
    files.

    Raises
    ------
    Difference
        At the first difference (or a missing reference file).
    """
    for name in case.outputs():
        if not (reference / name).is_file():
            raise Difference(f"{case.name}: no reference file {reference / name}")
    directory = run_case(case, runner, scratch, shared)
    for name in case.outputs():
        ours, theirs = reference / name, directory / name
        if name.endswith(".trace"):
            found = first_trace_difference(ours, theirs)
        elif name.endswith(".json"):
            found = first_json_difference(
                without_timings(json.loads(ours.read_text())),
                without_timings(json.loads(theirs.read_text())),
            )
        else:  # the reference recording, re-run by this code
            found = replay(runner, ours, directory)
        if found:
            raise Difference(f"{case.name}: {name} differs: {found}")


def select(only: str, names: Sequence[str]) -> list[Case]:
    """The cases ``--only`` (all, synthetic, real) and ``--case`` keep, in table order."""
    known = {case.name for case in CASES}
    unknown = [name for name in names if name not in known]
    if unknown:
        raise SystemExit(f"unknown case(s) {', '.join(unknown)}; known: {', '.join(known)}")
    return [
        case for case in CASES
        if (not names or case.name in names)
        and (only == "all" or (only == "real") == bool(case.shared_files))
    ]


def code_location(runner: Runner, cwd: Path) -> Path | None:
    """The ``cfbci`` package the runner imports when run in ``cwd`` (where the cases run),
    or None when the command is not this check's ``python -m cfbci.cli`` form."""
    if runner.command[1:] != ("-m", "cfbci.cli"):
        return None
    done = subprocess.run(
        [runner.command[0], "-c", "import cfbci; print(cfbci.__file__)"], cwd=cwd,
        env=runner.env, capture_output=True, text=True, check=True,
    )
    return Path(done.stdout.strip()).parent


def main(argv: Sequence[str] | None = None) -> int:
    """The command line; exit status 0 when every case that ran matches (or was written)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", type=Path, metavar="DIR", help="write the references here")
    mode.add_argument("--check", type=Path, metavar="DIR", help="compare with the references")
    mode.add_argument("--list", action="store_true", help="print the cases and exit")
    parser.add_argument(
        "--only", choices=("all", "synthetic", "real"), default="all",
        help="synthetic: only the cases that need no ../shared data (default all)",
    )
    parser.add_argument("--case", action="append", default=[], metavar="NAME",
                        help="run only this case (repeatable)")
    parser.add_argument("--cfbci", help="the command that runs cfbci (default: "
                        "this interpreter's `python -m cfbci.cli`)")
    parser.add_argument("--python-path", help="put this checkout first on PYTHONPATH "
                        "(to run another version's code)")
    args = parser.parse_args(argv)
    cases = select(args.only, args.case)
    if args.list:
        for case in cases:
            print(f"{case.name}: cfbci {shlex.join([case.command, *case.args])}")
        return 0
    runner = Runner.create(args.cfbci, args.python_path)
    scratch = Path(tempfile.mkdtemp(prefix="behaviour-"))
    location = code_location(runner, scratch)
    print(f"running {shlex.join(runner.command)}: cfbci from {location or 'its command'}",
          flush=True)
    if args.python_path and location and not location.is_relative_to(
        Path(args.python_path).resolve()
    ):
        print(f"error: cfbci is imported from {location}, not from {args.python_path}")
        return 2
    for case in cases:
        missing = missing_data(case)
        if missing:
            print(f"skipped {case.name}: {', '.join(map(str, missing))} absent", flush=True)
            continue
        try:
            if args.write:
                write_case(case, runner, args.write, scratch)
            else:
                check_case(case, runner, args.check, scratch)
        except (Difference, subprocess.TimeoutExpired) as error:
            # The first difference is the one to look at: stop there.
            print(f"DIFFERENT {error}\noutputs kept in {scratch}", flush=True)
            return 1
        print(f"{'written' if args.write else 'same'} {case.name}", flush=True)
    shutil.rmtree(scratch)
    return 0


if __name__ == "__main__":
    sys.exit(main())
