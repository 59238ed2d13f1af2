"""The reference pages' generated parts, rendered at build time so that they cannot drift.

A page holds ``<!-- generated: NAME -->`` where a part goes; `on_page_markdown` (an
MkDocs hook, ``hooks:`` in mkdocs.yml) puts the part there:

``cli``
    every command's ``--help``, from `cfbci.cli.build_parser`;
``learner-settings``, ``continuous-settings``, ``puddle-settings``
    every field of `calibration_free.config.LearnerConfig`,
    `calibration_free.continuous_goals.ContinuousConfig` and
    `calibration_free.puddle_learner.PuddleConfig`: its default (the dataclass's),
    the values it accepts (read from the checks of its ``__post_init__``) and the first
    sentence of its docstring entry;
``service-limits``
    the limit flags of ``cfbci serve`` with their defaults and help;
``examples-not-run``
    the documentation's blocks marked ``<!-- example: skip: REASON -->``.

Pages the docs link to that other people write (``architecture.md``, ``recordings.md``) get
a stand-in page while they do not exist, so that the build stays strict.

Without MkDocs (another site generator): ``python docs/hooks/reference.py OUT`` writes a copy
of ``docs/`` with every part in place.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import os
import re
import shutil
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parents[1]
REPOSITORY = DOCS.parent
if str(REPOSITORY) not in sys.path:  # the project's packages, when not installed
    sys.path.insert(0, str(REPOSITORY))

#: Pages written by others, linked from these docs: a stand-in while they are missing.
OTHERS_PAGES = {
    "architecture.md": "Architecture",
    "recordings.md": "Recordings",
}
_MARKER = re.compile(r"^<!-- generated: (?P<name>[a-z-]+) -->$", re.MULTILINE)
#: A range's upper end from which it is shown as unbounded (``check_range(x, 0, 1e6)``).
UNBOUNDED = 1e6
#: Width of the rendered ``--help`` texts, columns.
HELP_WIDTH = 96


# --- the command line ---------------------------------------------------------------------

def cli_reference() -> str:
    """Every ``cfbci`` command's help, the commands with subcommands recursed into."""
    from cfbci.cli import build_parser

    previous = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(HELP_WIDTH)
    try:
        sections = list(_parser_sections(build_parser(), "cfbci", 2, ""))
    finally:
        if previous is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = previous
    return "\n".join(sections)


def _parser_sections(parser: argparse.ArgumentParser, name: str, level: int, summary: str):
    help_text = parser.format_help().replace(str(Path.home()), "~")
    lead = f"{summary[0].upper()}{summary[1:]}.\n\n" if summary else ""
    yield f"{'#' * level} `{name}`\n\n{lead}```text\n{help_text.rstrip()}\n```\n"
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            summaries = {a.dest: a.help or "" for a in action._choices_actions}
            for sub_name, sub_parser in action.choices.items():
                yield from _parser_sections(sub_parser, f"{name} {sub_name}", min(level + 1, 4),
                                            summaries.get(sub_name, ""))


# --- settings -------------------------------------------------------------------------------

def settings_reference(cls: type) -> str:
    """A table of a settings dataclass: setting, default, accepted values, what it does."""
    entries = docstring_entries(inspect.getdoc(cls) or "")
    accepted = accepted_values(cls)
    rows = ["| setting | default | accepts | what it does |", "|---|---|---|---|"]
    for spec in dataclasses.fields(cls):
        entry = entries.get(spec.name, ("", ""))
        default = _default_text(spec, entry[0])
        rows.append(
            f"| `{spec.name}` | {default} | {accepted.get(spec.name, _type_text(entry[0]))} "
            f"| {_first_sentence(entry[1]) or '-'} |"
        )
    return "\n".join(rows) + "\n"


def docstring_entries(doc: str) -> dict[str, tuple[str, str]]:
    """The ``Parameters``/``Attributes`` entries of a numpy docstring: name -> (the text
    after the colon, the description). ``a, b : int`` gives both names the entry."""
    entries: dict[str, tuple[str, str]] = {}
    lines = doc.splitlines()
    in_section = False
    current: list[str] = []
    description: list[str] = []
    kind = ""

    def close() -> None:
        for name in current:
            entries[name] = (kind, " ".join(description).strip())

    for index, line in enumerate(lines):
        following = lines[index + 1] if index + 1 < len(lines) else ""
        if line.strip() in ("Parameters", "Attributes") and set(following.strip()) == {"-"}:
            in_section = True
            continue
        if not in_section or set(line.strip()) == {"-"}:
            continue
        if line and not line.startswith(" "):
            if set(following.strip()) == {"-"}:  # the next section
                close()
                current, in_section = [], False
                continue
            close()
            names, _, kind = line.partition(" : ")
            current = [n.strip() for n in names.split(",")]
            description = []
            kind = kind.strip()
        elif line.startswith("    ") and current and _continues_kind(kind, description, line):
            kind += " " + line.strip()
        elif current:
            description.append(line.strip())
    close()
    return entries


def _continues_kind(kind: str, description: list[str], line: str) -> bool:
    """A kind line broken over two lines (``default the frame's (... 0.93 for feedback,``)."""
    return not description and kind.count("(") > kind.count(")")


def accepted_values(cls: type) -> dict[str, str]:
    """What each field accepts, read from the checks of ``cls.__post_init__``:
    ``check_option(name, ..., CHOICES)``, ``check_range(name, ..., low, high[,
    inclusive=False])``, ``check_at_least(name, ..., low[, strict=True])`` (also in a loop over
    names), ``if x not in CHOICES: raise``, ``if <comparison of x>: raise``, and ``if x ==
    high: raise`` after a range."""
    init = getattr(cls, "__post_init__", None)
    if init is None:
        return {}
    source = textwrap.dedent(inspect.getsource(init))
    module = sys.modules[cls.__module__]
    found: dict[str, str] = {}
    excluded_ends: dict[str, float] = {}

    def value(node: ast.AST) -> Any:
        return eval(compile(ast.Expression(node), "<check>", "eval"), vars(module))

    def field_name(node: ast.AST, loop: dict[str, list[str]]) -> list[str]:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return [node.value]
        if isinstance(node, ast.Name) and node.id in loop:
            return loop[node.id]
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            return [node.attr] if node.value.id == "self" else []
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "getattr":
            return field_name(node.args[1], loop)
        return []

    def visit(node: ast.AST, loop: dict[str, list[str]]) -> None:
        if isinstance(node, ast.For) and isinstance(node.target, ast.Name):
            try:
                names = list(value(node.iter))
            except Exception:  # a loop over something else
                names = []
            inner = {**loop, node.target.id: names} if names else loop
            for child in node.body:
                visit(child, inner)
            return
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.args:
            names = field_name(node.args[0], loop)
            if node.func.id == "check_option" and len(node.args) >= 3:
                for name in names:
                    found.setdefault(name, _choices(value(node.args[2])))
            elif node.func.id == "check_at_least" and len(node.args) >= 3:
                strict = any(k.arg == "strict" and isinstance(k.value, ast.Constant)
                             and k.value.value is True for k in node.keywords)
                for name in names:
                    found.setdefault(name, f"x {'>' if strict else '>='} {value(node.args[2]):g}")
            elif node.func.id == "check_range" and len(node.args) >= 4:
                inclusive = all(
                    not (k.arg == "inclusive" and isinstance(k.value, ast.Constant)
                         and k.value.value is False) for k in node.keywords)
                low, high = value(node.args[2]), value(node.args[3])
                text = f"[{low:g}, {high:g}]" if inclusive else f"({low:g}, {high:g})"
                if high >= UNBOUNDED:
                    text = f"x {'>=' if inclusive else '>'} {low:g}"
                for name in names:
                    found.setdefault(name, text)
        if isinstance(node, ast.If) and any(isinstance(s, ast.Raise) for s in node.body):
            test = node.test
            if (isinstance(test, ast.Compare) and len(test.ops) == 1
                    and isinstance(test.ops[0], ast.Eq)):
                for name in field_name(test.left, loop):
                    excluded_ends[name] = value(test.comparators[0])
            else:
                _condition(test, loop, found, value, field_name)
        for child in ast.iter_child_nodes(node):
            visit(child, loop)

    visit(ast.parse(source), {})
    for name, excluded in excluded_ends.items():  # ``if x == high: raise`` after a range
        if name in found and found[name].endswith(f", {excluded:g}]"):
            found[name] = found[name][:-1] + ")"
    return found


def _condition(test: ast.AST, loop: dict[str, list[str]], found: dict[str, str],
               value: Callable[[ast.AST], Any], field_name: Callable) -> None:
    """What a rejecting ``if`` says a field accepts (its negation)."""
    negated = isinstance(test, ast.UnaryOp) and isinstance(test.op, ast.Not)
    compare = test.operand if negated else test
    if not isinstance(compare, ast.Compare):
        return
    operands = [compare.left, *compare.comparators]
    fields_named = [field_name(operand, loop) for operand in operands]
    if sum(bool(names) for names in fields_named) != 1:
        return
    names = next(names for names in fields_named if names)
    text = None
    symbols = {ast.Lt: "<", ast.LtE: "<=", ast.Gt: ">", ast.GtE: ">="}
    flipped = {ast.Lt: ">=", ast.LtE: ">", ast.Gt: "<=", ast.GtE: "<"}
    if isinstance(compare.ops[0], ast.NotIn) and not negated:
        text = _choices(value(compare.comparators[0]))
    elif negated and all(type(op) in symbols for op in compare.ops):
        # ``not low <= x < high`` or ``not x > 0``: the accepted range itself
        parts = []
        for operand, op, named in zip(operands, [*compare.ops, None], fields_named,
                                      strict=True):
            parts.append("x" if named else f"{value(operand):g}")
            if op is not None:
                parts.append(symbols[type(op)])
        text = " ".join(parts)
    elif len(compare.ops) == 1 and type(compare.ops[0]) in flipped and fields_named[0]:
        text = f"x {flipped[type(compare.ops[0])]} {value(compare.comparators[0]):g}"
    if text is not None:
        for name in names:
            found.setdefault(name, text)


def _choices(choices: Any) -> str:
    return ", ".join(f'`"{c}"`' for c in choices)


def _default_text(spec: dataclasses.Field, kind: str) -> str:
    default = spec.default
    if default is None:  # resolved later: the docstring says by what
        said = re.search(r"default (.*)", kind)
        return _plain(said[1]) if said else "none"
    if isinstance(default, str):
        return f'`"{default}"`'
    if isinstance(default, bool):
        return f"`{str(default).lower()}`"
    return f"`{default:g}`" if isinstance(default, float) else f"`{default}`"


def _type_text(kind: str) -> str:
    choice = re.match(r"\{(.*?)\}", kind)
    if choice:
        return ", ".join(f"`{c.strip()}`" for c in choice[1].split(","))
    return _plain(kind.split(", default")[0]) or "-"


def _first_sentence(text: str) -> str:
    """The description's first sentence (a bare list of options skipped), cut at a colon
    or semicolon outside brackets when it runs long."""
    sentences = _sentences(_plain(text))
    if len(sentences) > 1 and sentences[0].startswith("One of "):
        sentences = sentences[1:]
    first = sentences[0] if sentences else ""
    if len(first) > 160:
        first = _cut(first, 40)
    return first.replace("|", "\\|")


def _sentences(text: str) -> list[str]:
    found, depth, start = [], 0, 0
    for index, char in enumerate(text):
        depth += (char in "([") - (char in ")]")
        if char == "." and depth == 0 and text[index + 1:index + 2] in (" ", ""):
            found.append(text[start:index + 1].strip())
            start = index + 1
    rest = text[start:].strip()
    return found + ([rest] if rest else [])


def _cut(text: str, shortest: int) -> str:
    depth = 0
    for index, char in enumerate(text):
        depth += (char in "([") - (char in ")]")
        if char in ":;" and depth == 0 and index >= shortest:
            return text[:index] + "."
    return text


def _plain(text: str) -> str:
    """Sphinx roles and double backquotes as Markdown code."""
    text = re.sub(r":[a-z]+:`~?(?:[\w.]*\.)?([\w]+)`", r"`\1`", text)
    return text.replace("``", "`")


# --- the service's limits ----------------------------------------------------------------

def limits_reference() -> str:
    """The limit flags of ``cfbci serve``: flag, default, what it bounds."""
    from dataclasses import fields

    from cfbci.cli import build_parser
    from cfbci.service.limits import ServiceLimits

    serve = _subparser(build_parser(), "serve")
    flags = {f"--{spec.name.replace('_', '-')}" for spec in fields(ServiceLimits)}
    rows = ["| flag of `cfbci serve` | default | what it bounds |", "|---|---|---|"]
    for action in serve._actions:
        flag = next((o for o in action.option_strings if o in flags), None)
        if flag:
            what = re.sub(r"\s*\(default [^)]*\)$", "", action.help or "")
            rows.append(f"| `{flag}` | `{action.default:g}` | {what} |")
    return "\n".join(rows) + "\n"


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices[name]
    raise KeyError(name)


# --- examples not run -------------------------------------------------------------------

def examples_not_run() -> str:
    """Every block of README.md and docs/ marked as not run, with its reason."""
    page_blocks = _tool("docs_examples").page_blocks
    rows = ["| page | line | why it is not run |", "|---|---|---|"]
    pages = [REPOSITORY / "README.md", *sorted(DOCS.rglob("*.md"))]
    for page in pages:
        for block in page_blocks(page):
            if block.skip:
                name = page.relative_to(REPOSITORY)
                rows.append(f"| `{name}` | {block.line} | {block.skip} |")
    return "\n".join(rows) + "\n"


def _tool(name: str) -> Any:
    """A module of tools/ (not a package), imported from its file."""
    import importlib.util

    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPOSITORY / "tools" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


# --- the hook -------------------------------------------------------------------------------

def _settings(module: str, name: str) -> Callable[[], str]:
    def render() -> str:
        import importlib

        return settings_reference(getattr(importlib.import_module(module), name))

    return render


PARTS: dict[str, Callable[[], str]] = {
    "cli": cli_reference,
    "learner-settings": _settings("calibration_free.config", "LearnerConfig"),
    "continuous-settings": _settings("calibration_free.continuous_goals", "ContinuousConfig"),
    "puddle-settings": _settings("calibration_free.puddle_learner", "PuddleConfig"),
    "service-limits": limits_reference,
    "examples-not-run": examples_not_run,
}


def render_parts(markdown: str, where: str) -> str:
    """``markdown`` with every generated part in place; an unknown part is an error."""
    def part(match: re.Match[str]) -> str:
        if match["name"] not in PARTS:
            raise ValueError(f"{where}: unknown generated part {match['name']!r}; known: "
                             f"{', '.join(PARTS)}")
        return PARTS[match["name"]]()

    return _MARKER.sub(part, markdown)


def on_files(files: Any, config: Any) -> Any:
    """A stand-in for each page written by others that does not exist yet."""
    from mkdocs.structure.files import File

    for name, title in OTHERS_PAGES.items():
        if files.get_file_from_path(name) is None:
            files.append(File.generated(config, name, content=(
                f"# {title}\n\nThis page is being written.\n")))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """The page with its generated parts in place."""
    return render_parts(markdown, page.file.src_uri)


def write_copy(out: Path) -> None:
    """A copy of docs/ with every generated part in place (for another site generator)."""
    shutil.copytree(DOCS, out, ignore=shutil.ignore_patterns("hooks", "__pycache__"))
    for page in out.rglob("*.md"):
        text = page.read_text()
        if _MARKER.search(text):
            page.write_text(render_parts(text, str(page)))


if __name__ == "__main__":
    write_copy(Path(sys.argv[1]))
