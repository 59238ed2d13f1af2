"""``cfbci bench fuzz-recordings``: damaged recordings through every command that reads them.

A real recording (``cfbci session``, synthetic raw epochs; or ``--recording FILE``) is
mutated, seeded: one flipped bit, several flipped bits, a cut, a cut with garbage appended,
garbage appended to the whole file, a zeroed block. Each mutant goes through ``cfbci
replay`` (with ``--json``), ``cfbci report``, ``cfbci recover`` and ``cfbci export`` in one
child process (`check_file`, the commands' ``main`` called in turn), killed after
``--timeout`` seconds (a hang), and is checked: no traceback (an exception escaping a
command), no hang, the input unmodified (its SHA-256 before and after), each command's exit
status one `ALLOWED` documents for the mutant (see ``docs/recordings.md``), an error
(status 2) said on stderr as ``error: ...`` and a recovered copy that reads back complete.
A few mutants (every ``--cli-every``-th) also run the four commands as ``cfbci``
processes, to see that no traceback reaches stderr there either.

Printed and written (``--json``): counts of tracebacks, hangs, inputs modified and
statuses not allowed, by mutation kind, and the outcomes (command: status) by kind.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from collections import Counter, defaultdict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

#: Mutation kinds, in the order they are drawn (round robin).
KINDS = ("bitflip", "bitflips", "truncate", "truncate+garbage", "append-garbage", "zero-block")
#: The commands each mutant goes through.
COMMANDS = ("replay", "report", "recover", "export")
#: Exit statuses each command may give a mutated recording: replay 3 (identical as far as
#: the cut or damaged file goes) or 2 (nothing to compare: no configuration left, not
#: MCAP); report 0 (cut only), 3 (damaged) or 1 (the file could not be reported: no
#: configuration left); recover 0 (cut only), 3 (damaged records dropped) or 2 (not MCAP);
#: export 0 (cut only), 3 (damaged) or 2 (nothing exportable: no configuration, no truth,
#: feature vectors). A divergence (replay 1) is never allowed: damage is never compared.
ALLOWED = {"replay": {2, 3}, "report": {0, 1, 3}, "recover": {0, 2, 3}, "export": {0, 2, 3}}
#: Statuses allowed for a file that is only cut (no byte changed): no damage said.
ALLOWED_CUT = {"replay": {2, 3}, "report": {0, 1}, "recover": {0, 2}, "export": {0, 2}}


def mutate(data: bytes, kind: str, rng: random.Random) -> tuple[bytes, str]:
    """A mutant of ``data`` of the given kind, and what was done (byte offsets)."""
    size = len(data)
    if kind == "bitflip":
        at, bit = rng.randrange(size), rng.randrange(8)
        mutant = bytearray(data)
        mutant[at] ^= 1 << bit
        return bytes(mutant), f"bit {bit} of byte {at} flipped"
    if kind == "bitflips":
        mutant = bytearray(data)
        spots = sorted(rng.randrange(size) for _ in range(rng.randint(2, 8)))
        for at in spots:
            mutant[at] ^= 1 << rng.randrange(8)
        return bytes(mutant), f"bits flipped at bytes {spots}"
    if kind == "truncate":
        at = rng.randrange(size)
        return data[:at], f"cut at byte {at} of {size}"
    if kind == "truncate+garbage":
        at, n = rng.randrange(size), rng.choice((1, 9, 100, 4096, 65536))
        return data[:at] + rng.randbytes(n), f"cut at byte {at} of {size}, {n} random bytes after"
    if kind == "append-garbage":
        n = rng.choice((1, 9, 100, 4096, 65536))
        return data + rng.randbytes(n), f"{n} random bytes appended"
    if kind == "zero-block":
        n = rng.choice((16, 512, 4096))
        at = rng.randrange(max(1, size - n))
        return data[:at] + bytes(min(n, size - at)) + data[at + n:], f"{n} bytes zeroed at {at}"
    raise ValueError(f"unknown mutation {kind!r}; the kinds are {', '.join(KINDS)}")


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def command_lines(path: Path, out: Path) -> dict[str, list[str]]:
    """The arguments of each of `COMMANDS` for a mutant, outputs under ``out``."""
    return {
        "replay": ["replay", str(path), "--json", str(out / "replay.json")],
        "report": ["report", str(path), "--out", str(out / "report"), "--jobs", "1"],
        "recover": ["recover", str(path), "--out", str(out / "recovered.mcap")],
        "export": ["export", str(path), "--out", str(out / "exported-epo.fif")],
    }


#: The command line's entry point, ``cfbci.cli.main`` (passed in: this module is below it).
Main = Callable[[list[str]], int]


def run_command(main: Main, argv: list[str]) -> dict[str, Any]:
    """Run ``cfbci ARGV`` in this process: its status, output and any exception escaping
    ``main`` (a traceback, which the command line would have printed)."""
    out, err = io.StringIO(), io.StringIO()
    escaped = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = main(argv)
        except SystemExit as exit_:  # a usage error
            status = exit_.code if isinstance(exit_.code, int) else 1
        except BaseException:  # an exception escaping a command is what is counted
            escaped = traceback.format_exc()
            status = None
    stderr = err.getvalue()
    return {"status": status, "stdout": out.getvalue()[-4000:], "stderr": stderr[-4000:],
            "traceback": escaped is not None or "Traceback (most recent call last)" in stderr,
            "exception": escaped}


def check_file(main: Main, path: Path, out: Path) -> dict[str, Any]:
    """Every command over one file, in this process; then whether the recovered copy reads
    back complete with the count recover printed. ``results.json`` in ``out`` holds them
    too (what `fuzz_one`'s child process hands back)."""
    from replay.recording import read_recording

    results = {name: run_command(main, argv) for name, argv in command_lines(path, out).items()}
    recovered = out / "recovered.mcap"
    if results["recover"]["status"] in (0, 3):
        try:
            clean = read_recording(recovered)
            said = f"recovered {clean.n_messages} messages"
            results["recover"]["copy_ok"] = clean.complete and said in results["recover"][
                "stdout"]
        except Exception as error:  # counted, not raised
            results["recover"]["copy_ok"] = False
            results["recover"]["copy_error"] = repr(error)
    (out / "results.json").write_text(json.dumps(results))
    return results


@dataclass
class Outcome:
    """One mutant's checks."""

    index: int
    kind: str
    what: str
    source: str
    statuses: dict[str, int | None] = field(default_factory=dict)
    tracebacks: list[str] = field(default_factory=list)
    hang: bool = False
    modified: bool = False
    not_allowed: list[str] = field(default_factory=list)
    unclear: list[str] = field(default_factory=list)
    bad_copy: bool = False
    seconds: float = 0.0
    cli: bool = False
    detail: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not (self.tracebacks or self.hang or self.modified or self.not_allowed
                    or self.unclear or self.bad_copy)


#: Statuses for a mutant equal to its source (a zeroed block over zeros): intact.
ALLOWED_INTACT = {name: {0} for name in COMMANDS}


def allowed_statuses(source: bytes, mutant: bytes) -> dict[str, set[int]]:
    """`ALLOWED` for a mutant of ``source``: `ALLOWED_INTACT` if unchanged,
    `ALLOWED_CUT` if only cut in the data section (a cut in the summary, after the
    data's DataEnd record, is summary damage: `ALLOWED`)."""
    from replay.damage import scan_mcap

    if mutant == source:
        return ALLOWED_INTACT
    if source.startswith(mutant) and len(mutant) < scan_mcap(source).data_end:
        return ALLOWED_CUT
    return ALLOWED


def judge(outcome: Outcome, results: dict[str, dict[str, Any]],
          allowed: dict[str, set[int]]) -> None:
    """Fill ``outcome`` from the commands' results (statuses against ``allowed``)."""
    for name, result in results.items():
        status = result["status"]
        outcome.statuses[name] = status
        if result["traceback"]:
            outcome.tracebacks.append(name)
            outcome.detail[name] = result.get("exception") or result["stderr"][-2000:]
        elif status not in allowed[name]:
            outcome.not_allowed.append(f"{name}: {status}")
            outcome.detail[name] = (result["stdout"] + result["stderr"])[-2000:]
        elif status == 2 and "error:" not in result["stderr"]:
            outcome.unclear.append(f"{name}: status 2 without 'error:' on stderr")
        if name == "recover" and result.get("copy_ok") is False:
            outcome.bad_copy = True
            outcome.detail["recover copy"] = result.get("copy_error", "not complete")


def _child(path: Path, out: Path, timeout: float) -> tuple[dict[str, Any] | None, str]:
    """`check_file` in a child process, killed after ``timeout`` s (None: a hang)."""
    report = out / "results.json"
    argv = [sys.executable, "-m", "cfbci.cli", "bench", "fuzz-recordings", "--check-file",
            str(path), str(out)]
    try:
        done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout,
                              env={**os.environ, "MPLBACKEND": "Agg"})
    except subprocess.TimeoutExpired:
        return None, "timeout"
    if done.returncode != 0 or not report.exists():
        return {name: {"status": None, "stdout": "", "stderr": done.stderr[-4000:],
                       "traceback": True, "exception": done.stderr[-4000:]}
                for name in COMMANDS}, "child failed"
    return json.loads(report.read_text()), ""


def _cli(path: Path, out: Path, timeout: float) -> dict[str, dict[str, Any]] | None:
    """The commands as ``cfbci`` processes (None if one hangs)."""
    results = {}
    cfbci = [sys.executable, "-m", "cfbci.cli"]
    for name, argv in command_lines(path, out / "cli").items():
        (out / "cli").mkdir(exist_ok=True)
        try:
            done = subprocess.run([*cfbci, *argv], capture_output=True, text=True,
                                  timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        results[name] = {"status": done.returncode, "stdout": done.stdout[-4000:],
                         "stderr": done.stderr[-4000:],
                         "traceback": "Traceback (most recent call last)" in done.stderr}
    return results


def fuzz_one(index: int, source: Path, data: bytes, kind: str, seed: int, work: Path,
             timeout: float, cli: bool) -> Outcome:
    """Mutate, run the commands, check."""
    rng = random.Random(f"{seed}:{index}")
    mutant, what = mutate(data, kind, rng)
    directory = work / f"{index:04d}"
    directory.mkdir(parents=True)
    path = directory / f"mutant-{index:04d}.mcap"
    path.write_bytes(mutant)
    before = sha256(path)
    outcome = Outcome(index, kind, what, source.name, cli=cli)
    started = time.perf_counter()
    results, problem = _child(path, directory, timeout)
    if results is None:
        outcome.hang = True
        outcome.detail["hang"] = f"no result in {timeout:g} s"
    else:
        judge(outcome, results, allowed_statuses(data, mutant))
        if problem:
            outcome.detail["child"] = problem
        if cli:
            processes = _cli(path, directory, timeout)
            if processes is None:
                outcome.hang = True
            else:
                for name, result in processes.items():
                    if result["traceback"]:
                        outcome.tracebacks.append(f"{name} (cfbci process)")
                        outcome.detail[f"{name} process"] = result["stderr"][-2000:]
                    elif result["status"] != outcome.statuses.get(name):
                        outcome.not_allowed.append(
                            f"{name} process: {result['status']} (in-process "
                            f"{outcome.statuses.get(name)})")
    outcome.modified = sha256(path) != before
    outcome.seconds = time.perf_counter() - started
    shutil.rmtree(directory, ignore_errors=True)
    return outcome


def make_recording(path: Path, steps: int, seed: int, timeout: float = 300) -> Path:
    """Record a ``cfbci session`` (synthetic raw epochs, 3 x 3 grid) to ``path``."""
    argv = [sys.executable, "-m", "cfbci.cli", "session", "--steps", str(steps), "--seed",
            str(seed), "--grid", "3", "--record", str(path)]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0 or not path.exists():
        raise RuntimeError(f"cfbci session failed ({done.returncode}): {done.stderr[-2000:]}")
    return path


def summarise(outcomes: list[Outcome]) -> dict[str, Any]:
    """Counts: overall, by kind, and the statuses of each command by kind."""
    def counts(group: list[Outcome]) -> dict[str, int]:
        return {
            "mutants": len(group),
            "tracebacks": sum(bool(o.tracebacks) for o in group),
            "hangs": sum(o.hang for o in group),
            "inputs_modified": sum(o.modified for o in group),
            "status_not_allowed": sum(bool(o.not_allowed) for o in group),
            "unclear_errors": sum(bool(o.unclear) for o in group),
            "bad_recovered_copies": sum(o.bad_copy for o in group),
            "ok": sum(o.ok for o in group),
            "via_cfbci_processes": sum(o.cli for o in group),
        }

    by_kind = defaultdict(list)
    for outcome in outcomes:
        by_kind[outcome.kind].append(outcome)
    statuses: dict[str, dict[str, dict[str, int]]] = {}
    for kind, group in by_kind.items():
        statuses[kind] = {
            name: dict(sorted(Counter(str(o.statuses.get(name)) for o in group).items()))
            for name in COMMANDS
        }
    seconds = [o.seconds for o in outcomes]
    return {
        "total": counts(outcomes),
        "by_kind": {kind: counts(group) for kind, group in by_kind.items()},
        "statuses_by_kind": statuses,
        "seconds_per_mutant": {"median": sorted(seconds)[len(seconds) // 2] if seconds else None,
                               "max": max(seconds, default=None)},
        "failures": [asdict(o) for o in outcomes if not o.ok],
    }


def run_fuzz(sources: list[Path], mutants: int, seed: int, jobs: int, timeout: float,
             cli_every: int, console: Console | None = None) -> dict[str, Any]:
    """Fuzz ``mutants`` mutants of ``sources`` (round robin over kinds and sources)."""
    datas = [(source, source.read_bytes()) for source in sources]
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="cfbci-fuzz-") as tmp:
        work = Path(tmp)
        jobs_ = [
            (k, *datas[k % len(datas)], KINDS[(k // len(datas)) % len(KINDS)])
            for k in range(mutants)
        ]
        outcomes: list[Outcome] = []
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(fuzz_one, k, source, data, kind, seed, work, timeout,
                                   cli_every > 0 and k % cli_every == 0)
                       for k, source, data, kind in jobs_]
            for future in futures:
                outcome = future.result()
                outcomes.append(outcome)
                if console is not None and not outcome.ok:
                    console.print(f"[red]mutant {outcome.index}[/] ({outcome.kind}: "
                                  f"{outcome.what}): {outcome.tracebacks or ''} "
                                  f"{'hang ' if outcome.hang else ''}"
                                  f"{'modified ' if outcome.modified else ''}"
                                  f"{outcome.not_allowed or ''} {outcome.unclear or ''}",
                                  soft_wrap=True)
    summary = summarise(outcomes)
    return {"sources": [{"file": str(s), "bytes": len(d)} for s, d in datas],
            "mutants": mutants, "seed": seed, "jobs": jobs, "timeout_s": timeout,
            "wall_s": round(time.perf_counter() - started, 1), **summary}


def print_fuzz(report: dict[str, Any], console: Console) -> None:
    """Counts by kind and the commands' statuses by kind."""
    table = Table(title=f"{report['mutants']} mutants of "
                  + ", ".join(f"{Path(s['file']).name} ({s['bytes']} bytes)"
                              for s in report["sources"]))
    names = ("mutants", "tracebacks", "hangs", "inputs_modified", "status_not_allowed",
             "unclear_errors", "bad_recovered_copies", "via_cfbci_processes")
    table.add_column("kind")
    for name in names:
        table.add_column(name.replace("_", " "), justify="right")
    for kind, counts in [*report["by_kind"].items(), ("all", report["total"])]:
        table.add_row(kind, *(str(counts[name]) for name in names))
    console.print(table)
    outcomes = Table(title="exit statuses by kind (status: mutants)")
    outcomes.add_column("kind")
    for name in COMMANDS:
        outcomes.add_column(name)
    for kind, statuses in report["statuses_by_kind"].items():
        outcomes.add_row(kind, *(", ".join(f"{s}: {n}" for s, n in statuses[name].items())
                                 for name in COMMANDS))
    console.print(outcomes)
    per = report["seconds_per_mutant"]
    console.print(f"wall {report['wall_s']} s on {report['jobs']} jobs; per mutant median "
                  f"{per['median']:.1f} s, max {per['max']:.1f} s (limit "
                  f"{report['timeout_s']:g} s)")


def fuzz_recordings(recordings: list[Path], mutants: int, seed: int, steps: int, jobs: int,
                    timeout: float, cli_every: int, json_out: Path | None,
                    console: Console) -> int:
    """``cfbci bench fuzz-recordings``: record a session unless given ``recordings``, fuzz,
    print, write ``json_out``; 0 if every mutant passed every check, else 1."""
    if mutants < 1 or jobs < 1 or timeout <= 0:
        raise ValueError("--mutants and --jobs must be at least 1, --timeout positive")
    with tempfile.TemporaryDirectory(prefix="cfbci-fuzz-source-") as tmp:
        sources = list(recordings)
        if not sources:
            console.print(f"recording a {steps}-step session ...")
            sources = [make_recording(Path(tmp) / "session.mcap", steps, seed)]
        report = run_fuzz(sources, mutants, seed, jobs, timeout, cli_every, console)
    print_fuzz(report, console)
    if json_out is not None:
        json_out.write_text(json.dumps(report, indent=1, default=str) + "\n")
    total = report["total"]
    return 0 if total["ok"] == total["mutants"] else 1
