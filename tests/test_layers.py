"""The layers' import rules, read from the source: the core imports neither the engines nor
the service nor the clients; the engines do not import the service or the clients; in the
service only app/engine.py imports the engines."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at any depth (inside functions too), named as in the
    repository (without the installed distribution's ``vloc.`` prefix)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module)
    return {name.removeprefix("vloc.") for name in found}


def _offences(folder: str, forbidden: tuple[str, ...], *, allowed: tuple[str, ...] = ()):
    out = []
    for path in sorted((REPO_ROOT / folder).rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel in allowed:
            continue
        for module in _imports(path):
            if any(module == f or module.startswith(f + ".") for f in forbidden):
                out.append(f"{rel} imports {module}")
    return out


@pytest.mark.parametrize(("folder", "forbidden", "allowed"), [
    ("workers/core", ("workers.engine", "app", "clients"), ()),
    ("workers/engine", ("app", "clients"), ()),
    ("app", ("workers.engine",), ("app/engine.py",)),
])
def test_layers_import_only_what_is_below_them(folder, forbidden, allowed):
    assert _offences(folder, forbidden, allowed=allowed) == []


def test_the_check_finds_an_offending_import(tmp_path, monkeypatch):
    bad = tmp_path / "pkg" / "mod.py"
    bad.parent.mkdir()
    bad.write_text("def f():\n    from vloc.app.db import make_engine\n")
    monkeypatch.setattr("tests.test_layers.REPO_ROOT", tmp_path)
    assert _offences("pkg", ("app",)) == ["pkg/mod.py imports app.db"]
