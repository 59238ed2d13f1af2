"""The runnable examples of the documentation: find them, and run them as a reader would.

A page's examples are its fenced code blocks in ``sh``/``bash``, ``console`` and
``python``; other fences (``json5``, ``text``, none) are shown, never run. HTML comments
right above a block (``<!-- example: ... -->``, invisible once rendered) say how the test
runs it:

``skip: REASON``
    not run (it needs an amplifier, a person, the network...); listed with its reason.
``same-as: PAGE``
    the block is also on ``PAGE`` (a path from the repository's root), whose test runs it:
    the test checks that the other page holds it, with the same markers, and does not run it
    twice.
``test: COMMAND ARGS``
    its test-sized variant: ``ARGS`` appended to every ``cfbci COMMAND`` of the block, so
    that they override the block's own options (argparse keeps an option's last value),
    e.g. ``test: simulate --seeds 2 --steps 40``. Repeatable.
``replace: OLD => NEW``
    the test runs the block with ``OLD`` replaced by ``NEW``. Repeatable.
``background``
    the block runs on while the page's next blocks do (a terminal of its own); every
    process a page started is ended with SIGTERM once its last block is done.
``ready: TEXT``
    with ``background``: the next block starts once ``TEXT`` appears in its output.
``expect: TEXT``
    the block's output must contain ``TEXT``. Repeatable.
``timeout: SECONDS``
    how long the block may take (default `DEFAULT_TIMEOUT`).

A page's blocks run in order in one fresh folder, as one reader's terminal: a block sees the
files the blocks before it wrote, their shell variables and their working directory.
``HOME`` is a fresh folder in which ``~/cfbci`` is the repository (the reader's clone);
``CFBCI_DATA_DIR`` holds the real data sets where they are available, and a page that names
one that is not (``cfbci datasets path NAME`` or ``fetch NAME``) is skipped whole. The
literal ports 7447 (Zenoh) and 8080 (HTTP) get a free port of their own on each page, so
that pages run side by side. See docs/contributing/examples.md.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

#: Fence languages that are run, and how: a shell script, a console transcript, Python.
RUNNABLE = {"sh": "sh", "bash": "sh", "shell": "sh", "console": "console", "python": "python",
            "py": "python"}
#: Seconds a block may take unless it says otherwise.
DEFAULT_TIMEOUT = 120.0
#: Seconds a background block has to print its ``ready`` text.
READY_TIMEOUT = 60.0
#: Seconds the processes of a page have to exit after SIGTERM, before SIGKILL.
STOP_TIMEOUT = 20.0
#: The literal ports a page's blocks may use; each page gets free ones in their place.
PAGE_PORTS = ("7447", "8080")
#: Names of the real data sets a block asks for.
DATASET_USE = re.compile(r"cfbci datasets (?:path|fetch) ([a-z0-9_-]+)")

_FENCE = re.compile(r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`\n]*)$")
_MARKER = re.compile(r"^\s*<!--\s*example:\s*(?P<body>.*?)\s*-->\s*$")
_DIRECTIVES = ("skip:", "same-as:", "test:", "replace:", "background", "ready:", "expect:",
               "timeout:", "needs:")


class ExampleError(AssertionError):
    """A block failed, or its markers are malformed; the message names the page and line."""


@dataclass
class Block:
    """One fenced block of a page and what its markers say."""

    path: Path  #: the page
    line: int  #: 1-based line of the opening fence
    language: str  #: the fence's language (lower case, "" for none)
    code: str  #: the block's text, its indentation removed
    skip: str | None = None  #: why it is not run, or None
    same_as: str | None = None  #: the page (repository path) that runs this very block
    variants: list[tuple[str, str]] = field(default_factory=list)  #: (command, args) appended
    replacements: list[tuple[str, str]] = field(default_factory=list)  #: (old, new)
    background: bool = False
    ready: str | None = None
    expect: list[str] = field(default_factory=list)
    timeout: float = DEFAULT_TIMEOUT
    needs: list[tuple[str, str]] = field(default_factory=list)  #: (program, Debian package)

    @property
    def kind(self) -> str | None:
        """How it runs ("sh", "console", "python"), or None for a block only shown."""
        return RUNNABLE.get(self.language)

    @property
    def where(self) -> str:
        """``page:line``, for messages."""
        return f"{self.path}:{self.line}"

    @property
    def runs_here(self) -> bool:
        """Whether this page's test runs the block (runnable, not skipped, not run elsewhere)."""
        return self.kind is not None and self.skip is None and self.same_as is None

    def signature(self) -> tuple:
        """What must be equal for a block to be "the same" as another page's."""
        return (self.language, self.code, self.variants, self.replacements, self.background,
                self.ready, self.expect, self.timeout, self.needs)

    @property
    def datasets(self) -> set[str]:
        """The real data sets it names."""
        return set(DATASET_USE.findall(self.code))


def page_blocks(path: Path, text: str | None = None) -> list[Block]:
    """Every fenced block of a Markdown page, in order, with its markers applied.

    Raises
    ------
    ExampleError
        A marker that is not one of the directives, or one that is not right above a block.
    """
    lines = (path.read_text() if text is None else text).splitlines()
    blocks: list[Block] = []
    markers: list[tuple[int, str]] = []
    index = 0
    while index < len(lines):
        line = lines[index]
        marker = _MARKER.match(line)
        if marker:
            markers.append((index + 1, marker["body"]))
            index += 1
            continue
        opening = _FENCE.match(line)
        if not opening:
            if line.strip() and markers:
                raise ExampleError(f"{path}:{markers[0][0]}: an example marker must be right "
                                   "above a fenced block")
            index += 1
            continue
        indent, fence = opening["indent"], opening["fence"]
        body: list[str] = []
        index += 1
        while index < len(lines) and not (
            lines[index].strip().startswith(fence) and lines[index].strip(fence[0]).strip() == ""
        ):
            text_line = lines[index]
            body.append(text_line[len(indent):] if text_line.startswith(indent) else text_line)
            index += 1
        index += 1  # the closing fence
        language = opening["info"].strip().split(" ")[0].lower() if opening["info"] else ""
        block = Block(path, index - len(body) - 1, language.strip("{}."), "\n".join(body) + "\n")
        for line_number, body_text in markers:
            _apply_marker(block, body_text, f"{path}:{line_number}")
        if markers and block.kind is None:
            raise ExampleError(f"{path}:{markers[0][0]}: example markers above a block that "
                               f"is not run (language {language!r})")
        markers = []
        blocks.append(block)
    return blocks


def _apply_marker(block: Block, body: str, where: str) -> None:
    directive = next((d for d in _DIRECTIVES if body == d or body.startswith(d)), None)
    if directive is None:
        raise ExampleError(f"{where}: unknown example marker {body!r}; known: "
                           f"{', '.join(_DIRECTIVES)}")
    value = body[len(directive):].strip()
    if directive == "skip:":
        if not value:
            raise ExampleError(f"{where}: 'skip:' needs a reason")
        block.skip = value
    elif directive == "same-as:":
        if not value:
            raise ExampleError(f"{where}: 'same-as:' needs the page that runs the block")
        block.same_as = value
    elif directive == "test:":
        words = value.split()
        command = " ".join(w for w in _prefix_words(words))
        args = " ".join(words[len(command.split()):])
        if not command or not args:
            raise ExampleError(f"{where}: 'test:' needs a command and options, e.g. "
                               "'test: simulate --seeds 2'")
        block.variants.append((command, args))
    elif directive == "replace:":
        old, arrow, new = value.partition(" => ")
        if not arrow or not old:
            raise ExampleError(f"{where}: 'replace:' needs 'OLD => NEW'")
        block.replacements.append((old, new))
    elif directive == "background":
        block.background = True
    elif directive == "ready:":
        block.ready = value
    elif directive == "expect:":
        block.expect.append(value)
    elif directive == "needs:":
        words = value.split()
        if len(words) not in (1, 2):
            raise ExampleError(f"{where}: 'needs:' takes a program and, if its Debian package "
                               "is named otherwise, the package: 'needs: openssl'")
        block.needs.append((words[0], words[-1]))
    else:
        try:
            block.timeout = float(value)
        except ValueError:
            raise ExampleError(f"{where}: 'timeout:' needs seconds; got {value!r}") from None


def _prefix_words(words: list[str]) -> Iterator[str]:
    for word in words:
        if word.startswith("-"):
            return
        yield word


def check_same_as(block: Block, repository: Path) -> None:
    """Raise `ExampleError` unless the page a ``same-as`` block names runs that very
    block (the same code and markers)."""
    other = page_blocks(repository / block.same_as)
    if not any(b.runs_here and b.signature() == block.signature() for b in other):
        raise ExampleError(f"{block.where}: not run on {block.same_as}: the block or its "
                           "markers differ there")


def variant_code(block: Block) -> str:
    """The code the test runs: the block's, with its replacements and test options."""
    code = block.code
    for old, new in block.replacements:
        if old not in code:
            raise ExampleError(f"{block.where}: 'replace:' text {old!r} is not in the block")
        code = code.replace(old, new)
    for command, args in block.variants:
        code, found = append_options(code, command, args)
        if not found:
            raise ExampleError(f"{block.where}: 'test:' names 'cfbci {command}', which the "
                               "block does not run")
    return code


def append_options(code: str, command: str, args: str) -> tuple[str, int]:
    """``args`` appended to every ``cfbci [GLOBAL OPTIONS] COMMAND`` invocation of a shell
    text, at the end of its command (before a pipe, redirection, ``&``, ``;``, comment or
    line break; backslash-continued lines included). Returns the new text and how many
    invocations were changed."""
    words = r"\s+".join(re.escape(w) for w in command.split())
    pattern = re.compile(rf"\bcfbci(?:\s+--[a-z-]+(?:[ =][^-\s]\S*)?)*\s+{words}(?=[\s;&|)]|$)")
    pieces: list[str] = []
    position = found = 0
    for match in pattern.finditer(code):
        if match.start() < position or not _command_position(code, match.start()):
            continue
        end = _command_end(code, match.end())
        while end > match.end() and code[end - 1] in " \t":
            end -= 1
        pieces += [code[position:end], f" {args}"]
        position, found = end, found + 1
    pieces.append(code[position:])
    return "".join(pieces), found


def _command_position(code: str, index: int) -> bool:
    """Whether a word at ``index`` is a command name (not an argument, as in ``echo cfbci``),
    after any ``NAME=value`` assignments."""
    before = _ASSIGNMENTS.sub("", code[:index]).rstrip(" \t")
    return not before or before[-1] in "\n;&|(" or before.endswith("$(")


_ASSIGNMENTS = re.compile(r"(?:(?<=[\s;&|(])|^)(?:[A-Za-z_]\w*=\S*[ \t]+)+$")


def _command_end(code: str, start: int) -> int:
    """Index of the character that ends the simple command going on at ``start``: an
    unquoted operator, comment or line break that is not continued (or the text's end)."""
    quote: str | None = None
    depth = 0
    index = start
    while index < len(code):
        char = code[index]
        if quote:
            if char == "\\" and quote == '"':
                index += 2
                continue
            if char == quote:
                quote = None
        elif char in "'\"":
            quote = char
        elif char == "\\" and code[index + 1:index + 2] == "\n":
            index += 2
            continue
        elif code.startswith("$(", index):
            depth += 1
            index += 2
            continue
        elif char == ")" and depth:
            depth -= 1
        elif depth == 0 and (char in "|&;<>)\n" or (char == "#" and code[index - 1] in " \t")):
            return index
        index += 1
    return index


def console_commands(code: str) -> str:
    """The commands of a console transcript (``$ `` lines, ``> `` continuations) as a
    script; the output lines are the reader's to compare."""
    commands: list[str] = []
    continuing = False
    for line in code.splitlines():
        if line.startswith("$ "):
            commands.append(line[2:])
        elif continuing and line.startswith("> "):
            commands.append(line[2:])
        elif continuing:
            commands.append(line)
        else:
            continue
        continuing = commands[-1].rstrip().endswith("\\")
    return "\n".join(commands) + "\n"


# --- running -----------------------------------------------------------------------------

_WRAPPER = """\
__pristine=$(compgen -v)
if [ -f "$EXAMPLE_STATE/env.sh" ]; then . "$EXAMPLE_STATE/env.sh"; fi
cd "$(cat "$EXAMPLE_STATE/cwd")"
__save() {
    export -p
    for __name in $(compgen -v); do
        case "$__name" in __*|BASH*|FUNCNAME|PIPESTATUS|_|COMP*|DIRSTACK|GROUPS|LINENO|\
            RANDOM|SRANDOM|SECONDS|EPOCH*|HIST*|OPT*|PPID|SHELLOPTS|UID|EUID) continue;; esac
        grep -qx "$__name" <<<"$__pristine" || declare -p "$__name"
    done
}
trap '__save > "$EXAMPLE_STATE/env.sh" 2>/dev/null; pwd > "$EXAMPLE_STATE/cwd"' EXIT
set -eo pipefail
"""


class PageRun:
    """The blocks of one page, run in order in one folder as one reader's terminal.

    Parameters
    ----------
    root : Path
        An empty folder: ``root/work`` is the reader's working directory, ``root/home`` their
        ``HOME``.
    environment : dict
        The environment the blocks start from (``PATH`` with the project's ``cfbci``).
    repository : Path
        The project's clone (``~/cfbci`` in the blocks).
    """

    def __init__(self, root: Path, environment: dict[str, str], repository: Path) -> None:
        from wire.zenoh_config import free_tcp_endpoint

        self.root = root
        (root / "work").mkdir(parents=True)
        (root / "home").mkdir()
        (root / "state").mkdir()
        (root / "home" / "cfbci").symlink_to(repository)
        (root / "state" / "cwd").write_text(str(root / "work"))
        self.environment = {**environment, "HOME": str(root / "home"),
                            "EXAMPLE_STATE": str(root / "state")}
        self.ports = {port: free_tcp_endpoint().rsplit(":", 1)[1] for port in PAGE_PORTS}
        self.processes: list[tuple[Block, subprocess.Popen[bytes], Path]] = []
        self.count = 0

    def __enter__(self) -> PageRun:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def run(self, block: Block) -> str:
        """Run one block (its test variant); its output. Raises `ExampleError`."""
        self.count += 1
        code = self._ports(variant_code(block))
        if block.kind == "console":
            code = console_commands(code)
        script = self.root / "state" / f"block{self.count}"
        if block.kind == "python":
            script.with_suffix(".py").write_text(code)
            code = f'python "{script.with_suffix(".py")}"\n'
        script.write_text(_WRAPPER + code)
        log = self.root / "state" / f"block{self.count}.log"
        with log.open("wb") as output:  # a file, not a pipe: background children keep it
            process = subprocess.Popen(
                ["bash", str(script)], stdout=output, stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL, env=self.environment, start_new_session=True,
            )
        self.processes.append((block, process, log))
        if block.background:
            if block.ready is not None and not _wait_ready(process, log, block.ready):
                raise ExampleError(f"{block.where}: background block did not print "
                                   f"{block.ready!r} within {READY_TIMEOUT:g} s (exit status "
                                   f"{process.poll()}):\n{_tail(log)}")
            return _tail(log)
        try:
            status = process.wait(block.timeout)
        except subprocess.TimeoutExpired:
            _signal_group(process, signal.SIGKILL)
            raise ExampleError(f"{block.where}: still running after {block.timeout:g} s:\n"
                               f"{_tail(log)}") from None
        output_text = log.read_text(errors="replace")
        if status != 0:
            raise ExampleError(f"{block.where}: exit status {status}:\n{_tail(log)}")
        for text in block.expect:
            if text not in output_text:
                raise ExampleError(f"{block.where}: output lacks {text!r}:\n{_tail(log)}")
        return output_text

    def stop(self) -> None:
        """End every process the page's blocks left running: SIGTERM to each block's
        process group, the time to exit cleanly (recordings closed), then SIGKILL."""
        for _, process, _ in reversed(self.processes):
            _signal_group(process, signal.SIGTERM)
        deadline = time.monotonic() + STOP_TIMEOUT
        for _, process, _ in self.processes:
            while group_alive(process.pid) and time.monotonic() < deadline:
                time.sleep(0.05)  # waiting for exits: a group has no handle to wait on
            _signal_group(process, signal.SIGKILL)
            process.wait()

    def _ports(self, code: str) -> str:
        for literal, port in self.ports.items():
            code = re.sub(rf"(?<![0-9]){literal}(?![0-9])", port, code)
        return code


def _wait_ready(process: subprocess.Popen[bytes], log: Path, text: str) -> bool:
    """Whether ``text`` appears in the log while the process runs, within the timeout."""
    deadline = time.monotonic() + READY_TIMEOUT
    while time.monotonic() < deadline and process.poll() is None:
        if text in log.read_text(errors="replace"):
            return True
        time.sleep(0.05)  # a file has no event to wait on; the deadline bounds it
    return False


def group_alive(group: int) -> bool:
    """Whether a process group has a member that is not a zombie (Linux: from /proc;
    elsewhere any member)."""
    proc = Path("/proc")
    if not proc.is_dir():
        try:
            os.killpg(group, 0)
        except (ProcessLookupError, PermissionError):
            return False
        return True
    for stat in proc.glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # the process ended meanwhile
        if int(fields[2]) == group and fields[0] != "Z":
            return True
    return False


def _signal_group(process: subprocess.Popen[bytes], signum: int) -> None:
    try:
        os.killpg(process.pid, signum)
    except (ProcessLookupError, PermissionError):
        pass


def _tail(log: Path, lines: int = 40) -> str:
    try:
        text = log.read_text(errors="replace")
    except FileNotFoundError:
        return ""
    return "\n".join(text.splitlines()[-lines:])
