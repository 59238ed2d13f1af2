"""Docstrings are Markdown: the API reference (mkdocstrings) renders a Sphinx role such as
``:class:`X``` as literal text, so none may appear in the packages it documents."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPOSITORY = Path(__file__).resolve().parents[1]
#: A Sphinx cross-reference role: ``:class:`X```, ``:py:func:`f```, ``:data:`~m.D```.
ROLE = re.compile(r":(?:py:)?(?:class|func|data|meth|mod|attr|exc|obj|const):`[^`]*`")


def documented_packages() -> list[str]:
    """The top-level packages of the modules the API reference pages show (``::: module``)."""
    pages = (REPOSITORY / "docs" / "reference" / "api").glob("*.md")
    found = {m[1].split(".")[0] for page in pages
             for m in re.finditer(r"^::: *([\w.]+)", page.read_text(), re.MULTILINE)}
    return sorted(found)


def roles_in(source: str) -> list[tuple[int, str]]:
    """``(line, role)`` of each Sphinx role in a module's docstrings (module, class and
    function docstrings) and ``#:`` attribute comments, which mkdocstrings also renders."""
    found: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                found += [(body[0].lineno, m[0]) for m in ROLE.finditer(body[0].value.value)]
    for number, line in enumerate(source.splitlines(), 1):
        if line.lstrip().startswith("#:"):
            found += [(number, m[0]) for m in ROLE.finditer(line)]
    return found


def test_the_reference_documents_packages() -> None:
    assert {"acquisition", "calibration_free"} <= set(documented_packages())


@pytest.mark.parametrize("package", documented_packages())
def test_no_sphinx_role_in_docstrings(package: str) -> None:
    """Each module of a documented package writes code as Markdown (`X`, or a mkdocstrings
    cross-reference [X][package.module.X]), never as a Sphinx role."""
    offenders = [f"{path.relative_to(REPOSITORY)}:{line}: {role}"
                 for path in sorted((REPOSITORY / package).rglob("*.py"))
                 for line, role in roles_in(path.read_text())]
    assert not offenders, "Sphinx roles render as literal text in the API reference; write " \
        "`X` instead:\n" + "\n".join(offenders)


def test_a_role_is_found() -> None:
    """The check sees roles in each place mkdocstrings renders from, and not elsewhere."""
    source = '''"""Module, see :mod:`a.b`."""
#: an attribute, see :data:`C`
C = 1
X = ":class:`not a docstring`"


class K:
    """A class, :class:`K`."""

    def f(self) -> None:
        """A method, :meth:`~K.f`."""
'''
    assert [role for _, role in roles_in(source)] == [
        ":mod:`a.b`", ":class:`K`", ":meth:`~K.f`", ":data:`C`"]
