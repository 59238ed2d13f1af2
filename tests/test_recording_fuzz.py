"""Fuzz: a real recording, mutated (bit flips, cuts, garbage, zeroed blocks; seeded), through
``cfbci replay``, ``report``, ``recover`` and ``export``.

Each case must give no traceback, finish within `CASE_SECONDS` (a timer that fails
the test, not a sleep), exit with a status ``docs/recordings.md`` documents for the mutant
(`cfbci.bench.fuzz.ALLOWED`; an error said as ``error: ...``), leave its input
unmodified and, recovered, give a copy that reads back complete. The commands run in this
process (``cfbci.cli.main``); two mutants also as ``cfbci`` processes, whose stderr must
hold no traceback. The long version: ``cfbci bench fuzz-recordings``.
"""

from __future__ import annotations

import contextlib
import hashlib
import random
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from cfbci.bench.fuzz import KINDS, allowed_statuses, command_lines, mutate, run_command
from cfbci.cli import main
from replay.recording import read_recording

ROOT = Path(__file__).resolve().parents[1]
SEED = 11
PER_KIND = 5  # 30 mutants
CASE_SECONDS = 30.0
REPORT_EVERY = 5  # the report (figures) of every 5th mutant: the slow command


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A live ``cfbci session``: 20 steps on a 3 x 3 grid, synthetic raw epochs."""
    path = tmp_path_factory.mktemp("fuzz") / "session.mcap"
    done = subprocess.run(
        [sys.executable, "-m", "cfbci.cli", "session", "--steps", "20", "--seed", "2",
         "--grid", "3", "--record", str(path)],
        capture_output=True, text=True, cwd=ROOT, timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return path


class Hang(Exception):
    """A case ran past its time."""


@contextlib.contextmanager
def time_limit(seconds: float, what: str) -> Iterator[None]:
    """Fail the case (raise `Hang`) if it runs longer than ``seconds``."""
    def expired(signum: int, frame: object) -> None:
        raise Hang(f"{what}: no result in {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def mutants(data: bytes) -> list[tuple[str, str, bytes]]:
    rng = random.Random(SEED)
    cases = []
    for k in range(PER_KIND):
        for kind in KINDS:
            mutant, what = mutate(data, kind, rng)
            cases.append((f"{kind} #{k}", what, mutant))
    return cases


def test_mutated_recordings_give_documented_statuses_never_a_traceback(
    source: Path, tmp_path: Path
) -> None:
    data = source.read_bytes()
    seen: dict[str, set[int | None]] = {name: set() for name in ("replay", "report",
                                                                   "recover", "export")}
    for index, (name, what, mutant) in enumerate(mutants(data)):
        directory = tmp_path / f"{index:02d}"
        directory.mkdir()
        path = directory / "mutant.mcap"
        path.write_bytes(mutant)
        before = hashlib.sha256(mutant).hexdigest()
        allowed = allowed_statuses(data, mutant)
        case = f"{name} ({what})"
        for command, argv in command_lines(path, directory).items():
            if command == "report" and index % REPORT_EVERY:
                continue
            with time_limit(CASE_SECONDS, f"{case}: {command}"):
                result = run_command(main, argv)
            assert not result["traceback"], f"{case}: {command}:\n{result['exception']}"
            status = result["status"]
            assert status in allowed[command], (
                f"{case}: {command} exited {status}, not one of {sorted(allowed[command])}:\n"
                f"{result['stdout']}{result['stderr']}")
            if status == 2:
                assert "error:" in result["stderr"], f"{case}: {command}: {result['stderr']}"
            seen[command].add(status)
            assert hashlib.sha256(path.read_bytes()).hexdigest() == before, (
                f"{case}: {command} modified its input")
        if (directory / "recovered.mcap").exists():
            recovered = read_recording(directory / "recovered.mcap")
            assert recovered.complete, case
    # The mutants reach the damaged and the cut statuses of every command.
    assert {3} <= seen["replay"] and {0, 3} <= seen["recover"] and {0, 3} <= seen["export"]
    assert 3 in seen["report"]


@pytest.mark.parametrize("kind", ["truncate+garbage", "bitflip"])
def test_no_traceback_reaches_the_stderr_of_a_cfbci_process(
    source: Path, tmp_path: Path, kind: str
) -> None:
    mutant, what = mutate(source.read_bytes(), kind, random.Random(f"{SEED}:{kind}"))
    path = tmp_path / "mutant.mcap"
    path.write_bytes(mutant)
    allowed = allowed_statuses(source.read_bytes(), mutant)
    for command, argv in command_lines(path, tmp_path).items():
        done = subprocess.run([sys.executable, "-m", "cfbci.cli", *argv], capture_output=True,
                              text=True, cwd=ROOT, timeout=120)
        assert "Traceback" not in done.stderr, f"{what}: {command}:\n{done.stderr}"
        assert done.returncode in allowed[command], (what, command, done.stdout, done.stderr)
    assert hashlib.sha256(path.read_bytes()).digest() == hashlib.sha256(mutant).digest()
