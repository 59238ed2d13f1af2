"""A command line builds, and imports, only its own command group's parser (cfbci/cli):
``cfbci --version`` and ``cfbci datasets path`` start without the scientific stack, and
each group's parser built alone is the one of the whole parser."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from cfbci.cli import COMMAND_GROUPS, _own_command, build_parser


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_the_groups_are_every_command() -> None:
    """The table of groups names every command of the whole parser, once."""
    names = [name for group, _ in COMMAND_GROUPS for name in group]
    assert len(names) == len(set(names))
    assert set(names) == set(_subparsers(build_parser()))


@pytest.mark.parametrize("group", [g for g, _ in COMMAND_GROUPS], ids=lambda g: g[0])
def test_a_group_built_alone_is_the_same(group: tuple[str, ...]) -> None:
    """Each command of a group, built alone, has the help (options, defaults, choices) it
    has in the whole parser."""
    whole = _subparsers(build_parser())
    for name in group:
        alone = _subparsers(build_parser(only=name))
        assert set(alone) == set(group)
        assert alone[name].format_help() == whole[name].format_help()


@pytest.mark.parametrize(("argv", "own"), [
    (["simulate", "--steps", "20"], "simulate"),
    (["--blas-threads", "2", "datasets", "path", "s4"], "datasets"),
    (["--blas-threads=2", "lsl-check", "a", "b"], "lsl-check"),
    (["--version"], ""),
    (["--help"], None),
    ([], None),
    (["no-such-command"], None),
])
def test_the_command_of_a_command_line(argv: list[str], own: str | None) -> None:
    assert _own_command(argv) == own


def _imports_after(args: list[str], tmp_path: Path) -> set[str]:
    """The heavy packages imported by ``cfbci ARGS`` run in a fresh interpreter."""
    code = (
        "import sys\nfrom cfbci.cli import main\n"
        f"try:\n    main({args!r})\nexcept SystemExit:\n    pass\n"
        "print('imported:', *(m for m in ('numpy', 'scipy', 'sklearn', 'mcap') "
        "if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=tmp_path, env={"CFBCI_DATA_DIR": str(tmp_path), "PATH": ""},
                          check=True)
    return set(done.stdout.splitlines()[-1].split()[1:])


def test_light_commands_start_without_the_scientific_stack(tmp_path: Path) -> None:
    """``--version`` imports none of numpy, scipy, scikit-learn and MCAP; ``datasets path``
    (said in ``$(...)`` by many commands of the docs) neither scipy nor scikit-learn."""
    assert _imports_after(["--version"], tmp_path) == set()
    assert _imports_after(["datasets", "path", "s4"], tmp_path) <= {"numpy"}
