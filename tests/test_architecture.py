"""The architecture, checked: one session core steps every learner, no import cycle, the
command line's parsers in the CLI package only, and modules of a readable size."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import grimp

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cfbci", "acquisition", "replay", "wire", "session", "calibration_free", "decoding")
#: The layers allowed to call a learner's ``propose``/``observe``: the session core, and
#: the learners themselves (a learner made of learners).
CORE = ("session", "calibration_free", "decoding")
#: What a session object is called where it is stepped: its ``observe`` is the core's.
SESSION_NAMES = {"session", "core", "rerun", "loop"}


def _sources(*packages: str) -> list[Path]:
    return sorted(p for package in packages for p in (ROOT / package).rglob("*.py"))


def _learner_calls(path: Path, root: Path = ROOT) -> list[str]:
    """``propose``/``observe`` calls in a file whose receiver is not a session object."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
            continue
        if node.func.attr not in ("propose", "observe"):
            continue
        receiver = node.func.value
        name = receiver.attr if isinstance(receiver, ast.Attribute) else getattr(
            receiver, "id", None)
        if node.func.attr == "observe" and name in SESSION_NAMES:
            continue
        found.append(f"{path.relative_to(root)}:{node.lineno}: {ast.unparse(node.func)}")
    return found


def test_outside_tests_only_the_session_core_steps_a_learner() -> None:
    outside = [p for p in _sources(*PACKAGES, "tools") if p.parts[len(ROOT.parts)] not in CORE]
    calls = [call for path in outside for call in _learner_calls(path)]
    assert calls == []


def test_the_learner_call_check_finds_a_learner_stepped_outside_the_core(tmp_path: Path) -> None:
    stray = tmp_path / "stray.py"
    stray.write_text(
        "def run(learner, session, state, signal):\n"
        "    action = learner.propose(state)\n"
        "    learner.observe(state, action, signal)\n"
        "    session.observe(signal)\n"
    )
    assert [c.split(": ")[1] for c in _learner_calls(stray, tmp_path)] == [
        "learner.propose", "learner.observe"]


def _cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for imported in graph.find_modules_directly_imported_by(module):
            if imported not in index:
                visit(imported)
                low[module] = min(low[module], low[imported])
            elif imported in on_stack:
                low[module] = min(low[module], index[imported])
        if low[module] == index[module]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == module:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    return components


def test_no_import_cycle_anywhere() -> None:
    graph = grimp.build_graph(*PACKAGES, exclude_type_checking_imports=True)
    assert _cycles(graph) == []


def test_the_cycle_check_finds_a_cycle() -> None:
    graph = grimp.ImportGraph()
    for module in ("a", "b", "c"):
        graph.add_module(module)
    graph.add_import(importer="a", imported="b")
    graph.add_import(importer="b", imported="a")
    graph.add_import(importer="b", imported="c")
    assert _cycles(graph) == [["a", "b"]]


def _imports_argparse(path: Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import) and any(a.name == "argparse" for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and node.module == "argparse":
            return True
    return False


def test_argparse_only_in_the_cli_package_and_tools() -> None:
    users = [
        str(p.relative_to(ROOT)) for p in _sources(*PACKAGES)
        if _imports_argparse(p) and not p.is_relative_to(ROOT / "cfbci" / "cli")
    ]
    assert users == []


def test_modules_are_of_a_readable_size() -> None:
    """No module of cfbci/ over 500 lines, none of the service over about 400."""
    sizes = {p: len(p.read_text().splitlines()) for p in _sources("cfbci")}
    too_long = {str(p.relative_to(ROOT)): n for p, n in sizes.items() if n > 500 or (
        p.is_relative_to(ROOT / "cfbci" / "service") and n > 410)}
    assert too_long == {}
