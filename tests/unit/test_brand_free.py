"""The routines, the solvers and the service name no robot brand: the cell file picks the brand
(``drivers.robot.driver``), and the code above the drivers works through ``drivers.interfaces``.

Checked on what the code does, not on what it says: every identifier, import, and string literal
other than a docstring of every module in ``routines/``, ``solvers/`` and ``daemon/``. Comments and
docstrings may still say where a number was measured (a tracker-measured arm of some make)."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BRAND = re.compile(r"(?i)(?<![a-z0-9])(franka|pylibfranka|libfranka|panda|fr3|ur_rtde|rtde|urscript|universal[ _-]?robots|"
                   r"ur\d{1,2}e?|kuka|iiwa|fanuc|abb|yaskawa|motoman)(?![a-z0-9])")
FOLDERS = ("routines", "solvers", "daemon")


def docstrings(tree: ast.AST) -> set[int]:
    """ids of the string nodes that are docstrings."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                found.add(id(first.value))
    return found


def words(path: Path):
    """(line, text) of every identifier, imported name and non-docstring string literal in `path`."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    skip = docstrings(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            yield node.lineno, node.id
        elif isinstance(node, ast.Attribute):
            yield node.lineno, node.attr
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            yield node.lineno, node.name
        elif isinstance(node, ast.arg):
            yield node.lineno, node.arg
        elif isinstance(node, ast.ImportFrom):
            yield node.lineno, node.module or ""
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
            yield node.lineno, node.value


@pytest.mark.parametrize("folder", FOLDERS)
def test_no_brand_in_the_code_above_the_drivers(folder):
    named = [f"{path.relative_to(ROOT)}:{line}: {text!r}" for path in sorted((ROOT / folder).rglob("*.py"))
             for line, text in words(path) if BRAND.search(text)]
    assert not named, "\n".join(named)


def test_the_check_finds_a_brand(tmp_path):
    """The pattern and the walk catch a brand where it would matter, and not inside a docstring."""
    tree = '''"""Measured on a UR10."""\nimport pylibfranka\nX = "ur_rtde"\ndef f():\n    """On a Franka."""\n    return UR10e\n'''
    path = tmp_path / "brand_probe.py"
    path.write_text(tree)
    assert sorted(text for _, text in words(path) if BRAND.search(text)) == ["UR10e", "pylibfranka", "ur_rtde"]
